"""A features run's reduced basis (diffuser_lab/method/basis.py, issue 49): the queries' span
exact, Halko's range finder, the probes' estimate of the residual, the evidence in the basis."""
import numpy as np
import pytest

from diffuser_lab.method.basis import BasisFeatures, fit_basis, query_span, range_finder
from diffuser_lab.method.diffusion import diffuse, normalise
from diffuser_lab.method.evidence import project_features, sample_basis, sample_features
from diffuser_lab.method.features import decode, encode
from diffuser_lab.method.graph import build_graph


def _unit(rng, shape):
    f = rng.normal(size=shape).astype(np.float32)
    return f / np.linalg.norm(f, axis=-1, keepdims=True)


def test_the_basis_is_orthonormal_and_holds_the_queries_exactly():
    rng = np.random.default_rng(0)
    D = 96
    E = _unit(rng, (7, D))
    E = np.concatenate([E, E[:2]])  # repeated queries: the span's rank is 7
    sample = _unit(rng, (400, D))
    b = fit_basis(sample, E, principal=10, probes=4, seed=3)
    assert (b.n_query, b.k, b.s, b.dim, b.residual_dim) == (7, 17, 4, D, D - 17)
    C = b.columns.astype(np.float64)
    np.testing.assert_allclose(C.T @ C, np.eye(b.width), atol=1e-6)
    np.testing.assert_allclose(b.queries @ b.vectors.T, E, atol=1e-6)  # the queries lie in the span
    np.testing.assert_allclose(np.linalg.norm(b.queries, axis=1), 1, atol=1e-6)
    again = fit_basis(sample, E, principal=10, probes=4, seed=3)
    np.testing.assert_array_equal(again.columns, b.columns)  # keyed draws: the same basis
    assert query_span(E).shape == (D, 7)


def test_the_range_finder_recovers_a_planted_subspace():
    rng = np.random.default_rng(1)
    D, p = 80, 5
    V = np.linalg.qr(rng.normal(size=(D, p)))[0]
    A = rng.normal(size=(2000, p)) * np.array([10, 8, 6, 5, 4]) @ V.T + 0.01 * rng.normal(size=(2000, D))
    W, energy = range_finder(A, p, seed=0)
    assert W.shape == (D, p) and np.all(np.diff(energy) <= 0)
    # the same subspace: the planted basis' projection on it keeps all of it
    np.testing.assert_allclose(np.linalg.svd(W.T @ V, compute_uv=False), 1, atol=1e-4)


def test_the_probes_estimate_the_residual_energy_without_bias():
    """|R f|^2 ~ (r / s) |U^T f|^2: over many vectors the mean estimate is the mean residual."""
    rng = np.random.default_rng(2)
    D = 128
    E = _unit(rng, (10, D))
    b = fit_basis(_unit(rng, (300, D)), E, principal=6, probes=6, seed=0)
    # features mostly in the basis, a tenth of their energy outside (as diffused features' noise)
    X = (rng.normal(size=(4000, b.k)) @ b.vectors.T + 0.15 * rng.normal(size=(4000, D))).astype(np.float32)
    feats = b.split(X @ b.columns)
    true_res = (X ** 2).sum(1) - ((X @ b.vectors) ** 2).sum(1)
    assert 0.05 < true_res.sum() / (X ** 2).sum() < 0.2
    assert feats.residual.mean() == pytest.approx(true_res.mean(), rel=0.03)
    # cosines with the queries: f.q exact, the norm estimated: closer than the projection's own cosines
    cos_true = (X @ E.T) / np.linalg.norm(X, axis=1, keepdims=True)
    err = np.abs(feats.cosines(b.queries) - cos_true)
    err_projection = np.abs(BasisFeatures(X @ b.vectors, np.zeros(4000, np.float32)).cosines(b.queries) - cos_true)
    assert np.median(err) < 0.5 * np.median(err_projection)
    exact = BasisFeatures(X @ b.vectors, true_res.astype(np.float32))  # with the exact residual: exact cosines
    np.testing.assert_allclose(exact.cosines(b.queries), cos_true, atol=1e-5)


def test_sampling_a_projected_map_is_the_projection_of_the_full_sample():
    """The bilinear sample's norm from the cells' dot products is exact: the basis' coordinates are
    those of the full path's unit feature, at the borders (clipped corners) and beside masked cells."""
    rng = np.random.default_rng(3)
    h, w, D = 6, 8, 64
    fmap = rng.normal(size=(h, w, D)).astype(np.float32)
    fmap[2, 3] = np.nan  # no feature
    fmap[5, :2] = np.nan
    cells = fmap.reshape(-1, D)
    cells = cells[np.isfinite(cells).all(1)]
    b = fit_basis(cells / np.linalg.norm(cells, axis=1, keepdims=True), _unit(rng, (5, D)), 8, 4, seed=0)
    H, W = 48, 64
    rows, cols = (a.ravel() for a in np.meshgrid(np.arange(H), np.arange(W), indexing="ij"))
    f, ok = sample_features(fmap, rows, cols, (H, W))
    g, okb, n2 = sample_basis(project_features(fmap, b), (h, w), rows, cols, (H, W))
    np.testing.assert_array_equal(ok, okb)
    np.testing.assert_allclose(g, f @ b.columns, atol=2e-6)
    assert (n2[okb] > 0).all() and (g[~okb] == 0).all()


@pytest.mark.parametrize("backend", ["numba", "scipy"])
def test_diffusing_the_coordinates_is_projecting_the_diffused_features(backend):
    """The diffusion is linear: diffuse(F) C = diffuse(F C) through the encoded core, so the
    query projections (and the labels) of a basis run are the full run's."""
    rng = np.random.default_rng(4)
    pts = rng.random((2500, 3)).astype(np.float32)
    graph = build_graph(pts, 12, None)
    D = 96
    b = fit_basis(_unit(rng, (200, D)), _unit(rng, (6, D)), 10, 3, seed=0)
    n = rng.integers(0, 4, 2500).astype(np.float32) * (rng.random(2500) < 0.4)
    F = np.stack([_unit(rng, (4, D))[: int(k)].sum(0) if k else np.zeros(D, np.float32) for k in n])
    kw = dict(max_iter=50, tol=0.0, backend=backend, sparse_classes="off")
    full = decode(diffuse(normalise(graph, encode(F, n), 1e-4), **kw).Z)
    small = decode(diffuse(normalise(graph, encode(F @ b.columns, n), 1e-4), **kw).Z)
    scale = np.abs(full).max()
    assert np.abs(small - full @ b.columns).max() <= 2e-5 * scale


@pytest.mark.parametrize("shape", [(24, 32), (48, 64), (37, 53)])
def test_compiled_basis_samples_equal_numpy_bit_for_bit(shape, monkeypatch):
    """The evidence's compiled pass (sample_basis and the adds in one numba kernel) equals the
    numpy path bit for bit: samples, usable flags, mass and links (cells without a feature, the
    image's edges, a map smaller than the image)."""
    from types import SimpleNamespace

    from diffuser_lab.backends import numba as nb
    from diffuser_lab.method import evidence as ev_mod

    if not nb.available():
        pytest.skip("numba not importable or DIFFUSER_LAB_NUMBA=0")
    rng = np.random.default_rng(3)
    h, w, D, width = 12, 16, 40, 9
    fmap = rng.normal(size=(h, w, D)).astype(np.float32)
    fmap[rng.random((h, w)) < 0.15] = np.nan
    fmap[0, 0] = np.nan
    cols_basis = np.linalg.qr(rng.normal(size=(D, width)))[0].astype(np.float32)
    prep = ev_mod.project_features(fmap, SimpleNamespace(columns=cols_basis))
    H, W = shape
    n = 5000
    m = 3000
    idx = rng.permutation(n)[:m].astype(np.int64)
    rows, cols = rng.integers(0, H, m), rng.integers(0, W, m)
    rows[:4], cols[:4] = [0, H - 1, 0, H - 1], [0, W - 1, W - 1, 0]
    out = {}
    for compiled in (True, False):
        if not compiled:
            monkeypatch.setattr(nb, "available", lambda: False)
        ev = ev_mod.Evidence(mass=rng.normal(size=(n, width)).astype(np.float32) * 0 + 0.25,
                             links=np.ones(n, np.int32))
        f, good = ev_mod._add_basis_samples(ev, prep, (h, w), rows, cols, (H, W), idx)
        out[compiled] = (f, good, ev.mass.copy(), ev.links.copy())
    (f1, g1, m1, l1), (f0, g0, m0, l0) = out[True], out[False]
    assert g1.any() and not g1.all()
    assert np.array_equal(g1, g0) and np.array_equal(l1, l0)
    assert np.array_equal(f1[g1].view(np.int32), f0[g0].view(np.int32))
    assert np.array_equal(m1.view(np.int32), m0.view(np.int32))
