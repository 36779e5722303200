"""Features through the one diffusion core (diffuser_lab/method/features.py): the encoding, the
linearity the method rests on, the evidence of feature maps."""
import numpy as np
import pytest

from diffuser_lab.data.scene import Frame
from diffuser_lab.method.diffusion import diffuse, normalise
from diffuser_lab.method.evidence import Evidence, add_frame, sample_features
from diffuser_lab.method.features import decode, encode, normalised
from diffuser_lab.method.graph import build_graph


def _unit(rng, shape):
    f = rng.normal(size=shape).astype(np.float32)
    return f / np.linalg.norm(f, axis=-1, keepdims=True)


def test_encoding_is_a_class_mass_and_decodes_exactly():
    rng = np.random.default_rng(0)
    n = rng.integers(0, 6, 500).astype(np.float32)
    F = np.stack([_unit(rng, (6, 64))[: int(k)].sum(0) if k else np.zeros(64, np.float32) for k in n])
    g = encode(F, n)
    assert g.shape == (500, 65) and (g >= 0).all()
    np.testing.assert_allclose(g.sum(1), n, rtol=1e-5, atol=1e-5)  # each pixel's mass is 1 (Eq. 13)
    np.testing.assert_allclose(decode(g), F, atol=2e-5)
    extreme = encode(np.eye(64, dtype=np.float32) * -1, np.ones(64))  # f_d = -1: still >= 0
    assert (extreme >= 0).all()


@pytest.mark.parametrize("backend", ["numba", "scipy"])
def test_diffusing_linear_features_is_diffusing_the_class_mass_times_the_embeddings(backend):
    """F = Y E: the diffusion of the features equals the diffusion of the class mass Y, times E."""
    rng = np.random.default_rng(1)
    pts = rng.random((3000, 3)).astype(np.float32)
    graph = build_graph(pts, 12, None)
    C, D = 7, 96
    E = _unit(rng, (C, D))
    Y = np.zeros((3000, C), np.float32)
    seen = rng.random(3000) < 0.3
    for _ in range(4):  # up to 4 one-hot pixels a seen point
        Y[np.flatnonzero(seen), rng.integers(0, C, seen.sum())] += (rng.random(seen.sum()) < 0.8)
    F, n = Y @ E, Y.sum(1)
    kw = dict(max_iter=60, tol=0.0, backend=backend, sparse_classes="off")
    ZY = diffuse(normalise(graph, Y, 1e-4), **kw).Z
    ZF = decode(diffuse(normalise(graph, encode(F, n), 1e-4), **kw).Z)
    scale = np.abs(ZY @ E).max()
    assert np.abs(ZF - ZY @ E).max() <= 1e-5 * scale * D ** 0.5, np.abs(ZF - ZY @ E).max() / scale
    cos = (ZF * (ZY @ E)).sum(1)[n > 0] / (np.linalg.norm(ZF, axis=1) * np.linalg.norm(ZY @ E, axis=1))[n > 0]
    assert cos.min() > 0.9999


def _frame(depth, fmap):
    K = np.array([[40.0, 0, 32], [0, 40.0, 24], [0, 0, 1]])
    return Frame("f", K, np.eye(4), depth, features=fmap)


def test_a_feature_map_at_a_coarser_grid_is_sampled_bilinearly_at_pixel_centres():
    rng = np.random.default_rng(2)
    fmap = _unit(rng, (6, 8, 16))
    H, W = 48, 64  # the map's cells are 8 x 8 pixels
    rows, cols = np.array([3, 4, 20, 47]), np.array([3, 4, 35, 0])
    f, ok = sample_features(fmap, rows, cols, (H, W))
    assert ok.all()
    # pixel (3, 3) and (4, 4): cell centre (3.5 / 8 - 0.5 < 0): clamped to cell (0, 0)
    np.testing.assert_allclose(f[0], fmap[0, 0], atol=1e-6)
    y, x = (20 + 0.5) / 8 - 0.5, (35 + 0.5) / 8 - 0.5
    y0, x0, wy, wx = int(y), int(x), y - int(y), x - int(x)
    want = ((1 - wy) * (1 - wx) * fmap[y0, x0] + (1 - wy) * wx * fmap[y0, x0 + 1]
            + wy * (1 - wx) * fmap[y0 + 1, x0] + wy * wx * fmap[y0 + 1, x0 + 1])
    np.testing.assert_allclose(f[2], want / np.linalg.norm(want), atol=1e-6)


def test_pixels_without_a_feature_give_no_evidence():
    rng = np.random.default_rng(3)
    H, W, D = 48, 64, 16
    fmap = _unit(rng, (6, 8, D)).astype(np.float16)
    fmap[:, :4] = np.nan  # the left half of the image has no feature
    depth = np.full((H, W), 2.0, np.float32)
    K = np.array([[40.0, 0, 32], [0, 40.0, 24], [0, 0, 1]])
    uv = np.stack(np.meshgrid(np.arange(W), np.arange(H)), -1).reshape(-1, 2)
    pts = (np.linalg.inv(K) @ np.c_[uv, np.ones(len(uv))].T).T * 2.0
    ev = Evidence.empty(len(pts), D)
    add_frame(ev, pts.astype(np.float32), _frame(depth, fmap))
    left = uv[:, 0] < 28  # pixel centres whose four cells are all in the left half
    right = uv[:, 0] >= 36
    assert (ev.links[left] == 0).all() and (ev.mass[left] == 0).all()
    assert (ev.links[right] == 1).all()
    np.testing.assert_allclose(np.linalg.norm(ev.mass[right], axis=1), 1, atol=1e-3)
    assert ev.seen.sum() == (ev.links > 0).sum()


def test_normalised_drops_nan_and_zero_features():
    f, ok = normalised(np.array([[3.0, 4.0], [0, 0], [np.nan, 1]]))
    assert ok.tolist() == [True, False, False]
    np.testing.assert_allclose(f, [[0.6, 0.8], [0, 0], [0, 0]])


def test_features_in_blocks_diffuse_as_all_columns_at_once():
    """Each block carries its balance column, so its rows' masses are the pixel counts: the same
    system; with the first block's iteration count the result is the all-at-once one."""
    from diffuser_lab.config import SolverConfig
    from diffuser_lab.method.features import diffuse_features

    rng = np.random.default_rng(4)
    pts = rng.random((2000, 3)).astype(np.float32)
    graph = build_graph(pts, 12, None)
    D = 40
    n = (rng.random(2000) < 0.4) * rng.integers(1, 4, 2000)
    F = np.stack([_unit(rng, (3, D))[:k].sum(0) for k in n]).astype(np.float32)
    solver = SolverConfig(max_iter=300, tol=1e-4, backend="scipy", sparse_classes="off")
    whole, r1 = diffuse_features(graph, F.copy(), n, 1e-4, solver)
    parts, r2 = diffuse_features(graph, F.copy(), n, 1e-4, solver, block=16)
    assert r2.info["feature_blocks"] == 3 and r2.Z is None
    exact, _ = diffuse_features(graph, F.copy(), n, 1e-4,
                                SolverConfig(max_iter=r2.iterations, tol=0.0, backend="scipy", sparse_classes="off"))
    scale = np.abs(exact).max()
    assert np.abs(parts - exact).max() <= 1e-4 * scale  # float32: rounding of the encodings differs
    assert abs(r1.iterations - r2.iterations) <= 0.1 * r1.iterations  # the first block's stop is the whole one's, near enough


@pytest.mark.parametrize("compiled", [False, True], ids=["numpy", "numba"])
def test_top_probability_is_class_scores_share_bit_for_bit(compiled, monkeypatch):
    """The best view's confidence (top_probability: class-major numpy, or the numba rows) equals
    class_scores' max over sum, bit for bit: NaN rows, infinities, classes no query names, C < 8,
    C a multiple of 8 and not, Q = 1."""
    from diffuser_lab.backends import numba as nb
    from diffuser_lab.method.features import class_scores, top_probability

    if compiled and not nb.available():
        pytest.skip("numba not importable or DIFFUSER_LAB_NUMBA=0")
    if not compiled:
        monkeypatch.setattr(nb, "available", lambda: False)
    rng = np.random.default_rng(7)
    for C in (1, 3, 7, 8, 9, 16, 20, 21, 40, 128):
        for Q in (1, 5, 20, 33):
            to_class = rng.integers(-1, C, Q)
            cos = (rng.random((3000, Q)) * 2 - 1).astype(np.float32)
            cos[::97] = np.nan
            cos[4, 0], cos[5, -1] = -np.inf, np.inf
            before = cos.copy()
            with np.errstate(all="ignore"):
                s = class_scores(cos, to_class, C)
                total = s.sum(1)
                want = np.divide(s.max(1), total, out=np.zeros_like(total), where=total > 0)
                got = top_probability(cos, to_class, C)
            assert np.array_equal(cos, before, equal_nan=True)  # the input untouched
            assert got.dtype == np.float32 and np.array_equal(got.view(np.int32), want.view(np.int32)), (C, Q)
    assert top_probability(np.zeros((0, 3), np.float32), np.arange(3), 4).shape == (0,)
