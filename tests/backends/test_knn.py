"""The kNN rows (diffuser_lab.backends.knn and its compiled kernels: morton, grid_knn, weights)
against plain references: both paths give the brute-force rows of the one rule (float64
((dx*dx + dy*dy) + dz*dz), rows by (d2, index), element for element, ties included), the Morton
order is numpy's stable one, and the fused normalisation is bit for bit the numpy one."""
import numpy as np
import pytest
from knn_rule import brute_rows
from scipy.spatial import cKDTree

from diffuser_lab.backends import knn
from diffuser_lab.backends import numba as nb
from diffuser_lab.backends.numba import cell_search, grid_knn
from diffuser_lab.backends.morton import morton_codes, quantize
from diffuser_lab.method.diffusion import EDGE_FLOOR, normalise
from diffuser_lab.method.graph import build_graph
from diffuser_lab.method.graph import knn as graph_knn

needs_numba = pytest.mark.skipif(not nb.available(), reason="numba not importable or DIFFUSER_LAB_NUMBA=0")
PATHS = [pytest.param("numba", marks=needs_numba), "scipy"]


def tie_lattice(seed=3):
    """An integer lattice (every distance ties with many others) with 80 points repeated up to 3 times."""
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(np.arange(13), np.arange(11), np.arange(5), indexing="ij"), -1).reshape(-1, 3)
    dup = g[rng.choice(len(g), 80)]
    pts = np.vstack([g, dup, dup[:30]]).astype(np.float32)
    return pts[rng.permutation(len(pts))]


def tie_clouds():
    """Clouds with many exact distance ties: (name, points, k)."""
    lat = tie_lattice()
    yield "integer lattice, duplicates", lat, 24
    yield "integer lattice, k=7", lat, 7  # the 7th lies inside a shell of 12 (sqrt 2) or 8 (sqrt 3)
    yield "scaled lattice", lat * np.float32(0.05), 18
    g = np.stack(np.meshgrid(np.arange(30), np.arange(30), indexing="ij"), -1).reshape(-1, 2)
    yield "plane lattice", np.c_[g, np.zeros(len(g))].astype(np.float32), 24


def clouds():
    rng = np.random.default_rng(7)
    g = np.stack(np.meshgrid(np.arange(40), np.arange(40), indexing="ij"), -1).reshape(-1, 2) * 0.02
    yield "plane lattice (ties)", np.c_[g, np.zeros(len(g))], 24
    g3 = np.stack(np.meshgrid(np.arange(12), np.arange(12), np.arange(4), indexing="ij"), -1).reshape(-1, 3)
    yield "cubic lattice (ties)", g3 * 0.05, 24
    x = rng.random((1500, 3))
    x[:60] = x[0]
    yield "duplicates", x, 12
    a = rng.random((1500, 2))
    surf = np.c_[a, 0.01 * rng.normal(size=1500)]
    yield "surface and sparse outliers", np.vstack([surf, rng.random((150, 3)) * [1, 1, 0.5]]), 24
    t = np.sort(rng.random(1000))
    yield "line", np.c_[t, 1e-3 * rng.random(1000), np.zeros(1000)], 16
    yield "few points", rng.random((30, 3)), 20
    yield "five points", rng.random((5, 3)), 4


@needs_numba
@pytest.mark.parametrize("name,pts,k", list(clouds()), ids=[c[0] for c in clouds()])
def test_grid_knn_is_brute_force(name, pts, k):
    pts = pts.astype(np.float32)
    order, P4, _, res = grid_knn.sorted_knn(pts, None, k)
    np.testing.assert_array_equal(order, np.argsort(morton_codes(quantize(pts)[0]), kind="stable"))
    assert res is not None  # the grid, not the KD-tree fallback
    idx, d0 = res
    ref, d2 = brute_rows(pts[order], k)
    np.testing.assert_array_equal(idx, ref)  # rows in order: by (d2, index)
    np.testing.assert_array_equal(d0, np.where(d2 > 0, d2, np.inf).min(1))


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("name,pts,k", [*tie_clouds(), *clouds()], ids=[c[0] for c in [*tie_clouds(), *clouds()]])
def test_rows_follow_the_rule(name, pts, k, path):
    """sorted_knn on either path: the Morton order, and every row element for element the
    brute-force row of the rule (module doc of backends/knn.py), on clouds full of exact ties."""
    pts = np.ascontiguousarray(pts, np.float32)
    r = knn.sorted_knn(pts, None, k, path)
    np.testing.assert_array_equal(r.order, np.argsort(morton_codes(quantize(pts)[0]), kind="stable"))
    ref, d2 = brute_rows(pts[r.order], k)
    np.testing.assert_array_equal(r.idx, ref)
    np.testing.assert_array_equal(r.d0, np.where(d2 > 0, d2, np.inf).min(1))
    if r.d2 is not None:
        np.testing.assert_array_equal(r.d2, d2)


@needs_numba
def test_paths_give_the_same_graph_on_ties():
    """build_graph on a lattice with duplicates: the same rows, element for element, and weights
    on both paths (the compiled exp is a polynomial: at most one float32 ulp apart)."""
    pts = tie_lattice() * np.float32(0.03)
    g, s = build_graph(pts, 24), build_graph(pts, 24, backend="scipy")
    np.testing.assert_array_equal(g.order, s.order)
    np.testing.assert_array_equal(g.sorted_neighbors, s.sorted_neighbors)
    assert g.rho == s.rho and g.sigma_d == s.sigma_d
    ulps = np.abs(g.sorted_weights.view(np.int32).astype(np.int64) - s.sorted_weights.view(np.int32))
    assert ulps.max() <= 1


@needs_numba
def test_sparse_cloud_kdtree_fallback_follows_the_rule():
    """A cloud too sparse for the dense grid (a lattice and two points 10 km off): the compiled
    path's KD-tree fallback gives the rule's rows, as the scipy path."""
    pts = np.vstack([tie_lattice(), [[1e4, 0, 0], [0, 1e4, 1e4]]]).astype(np.float32)
    order, _, _, res = grid_knn.sorted_knn(pts, None, 24)
    assert res is None  # the fallback
    a, b = knn.sorted_knn(pts, None, 24, "numba"), knn.sorted_knn(pts, None, 24, "scipy")
    ref, _ = brute_rows(pts[order], 24)
    np.testing.assert_array_equal(a.idx, ref)
    np.testing.assert_array_equal(b.idx, ref)


def test_kdtree_rows_query_again_at_ties(monkeypatch):
    """kdtree_rows asks again, with more, the rows whose K-th may tie a point the tree left out
    (here: 40 copies of one point and a lattice, EXTRA = 1: one candidate to tell), and
    method.graph.knn (the caller's order) is the rule's too."""
    rng = np.random.default_rng(5)
    pts = rng.random((600, 3)).astype(np.float32)
    pts[100:140] = pts[7]
    pts = np.vstack([pts, tie_lattice()[:300] * np.float32(0.1)])
    monkeypatch.setattr(knn, "EXTRA", 1)
    calls = []
    tree = cKDTree(pts)
    query = tree.query

    class Tree:  # counts the queries
        n = tree.n

        def query(self, q, k, workers=1):
            calls.append((len(q), k))
            return query(q, k=k, workers=workers)

    idx, d2 = knn.kdtree_rows(Tree(), pts, np.arange(len(pts)), 12)
    ref, dref = brute_rows(pts, 12)
    np.testing.assert_array_equal(idx, ref)
    np.testing.assert_array_equal(d2, dref)
    # the tied rows only, with twice the candidates, until the 40 copies are all in
    assert len(calls) >= 3 and calls[0] == (len(pts), 14) and calls[1][0] < len(pts) // 2 and calls[1][1] == 28
    dist, gi = graph_knn(pts, 12)
    np.testing.assert_array_equal(gi, ref)
    np.testing.assert_array_equal(dist, np.sqrt(dref).astype(np.float32))


def test_sq_dist_is_the_rule():
    """sq_dist: float64 ((dx*dx + dy*dy) + dz*dz) of the float32 coordinates, bit for bit; and the
    kernels that compute it are compiled without fastmath (no FMA contraction)."""
    rng = np.random.default_rng(2)
    a, b = (rng.normal(size=(1000, 3)).astype(np.float32) * 7 for _ in range(2))
    dx, dy, dz = (a[:, c].astype(np.float64) - b[:, c].astype(np.float64) for c in range(3))
    np.testing.assert_array_equal(knn.sq_dist(a, b), (dx * dx + dy * dy) + dz * dz)
    if nb.available():
        from diffuser_lab.backends.numba import growing

        for kernel in (grid_knn._knn_cells, grid_knn._far_point, cell_search.ring_knn, growing.query_rows,
                       growing.merge_rows, growing.query_rings):
            assert not kernel.targetoptions.get("fastmath"), kernel


@needs_numba
def test_weights_and_normalisation_match_the_numpy_path():
    rng = np.random.default_rng(1)
    a = rng.random((3000, 2))
    pts = np.c_[a, 0.02 * np.sin(6 * a[:, 0])].astype(np.float32)
    nrm = rng.normal(size=(3000, 3)).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    mass = rng.integers(0, 3, (3000, 21)).astype(np.float32)
    g, s = build_graph(pts, 16, nrm), build_graph(pts, 16, nrm, backend="scipy")
    np.testing.assert_array_equal(g.order, s.order)
    np.testing.assert_array_equal(g.sorted_neighbors, s.sorted_neighbors)
    assert g.rho == s.rho
    # exp is a polynomial there (relative error ~1e-14): float32 results agree to an ulp at most
    np.testing.assert_allclose(g.sorted_weights, s.sorted_weights, rtol=2e-7, atol=0)
    # the fused normalisation against its numpy formulation
    sys_ = normalise(g, mass, 1e-3)
    pix = mass * np.float32(1e-3)
    wsum = np.empty(g.n, np.float32)
    wsum[g.order] = g.sorted_row_sums
    denom = wsum + pix.sum(1)
    inv = np.divide(1.0, denom, out=np.zeros_like(denom), where=denom > 1e-30).astype(np.float32)
    P = g.sorted_weights * inv[g.order][:, None]
    P[P < EDGE_FLOOR] = 0.0
    np.testing.assert_array_equal(sys_.sorted_P, P)
    np.testing.assert_array_equal(sys_.B, pix * inv[:, None])


if nb.available():  # compiled once per process (in the test it was compiled once per cloud: ~3 s each)
    @nb.NB.njit
    def _ring_rows(flo, fhi, c, h, dims, start, X, Y, Z, J, k):
        out = np.empty((J.shape[0], k), np.int64)
        bd = np.empty(k)
        no_table = np.empty(0, np.int64)
        for a in range(J.shape[0]):
            cell_search.ring_knn(J[a], X[a], Y[a], Z[a], (c[a, 0], c[a, 1], c[a, 2]), (flo[a, 0], flo[a, 1], flo[a, 2]),
                                 (fhi[a, 0], fhi[a, 1], fhi[a, 2]), h, np.zeros(3, np.int64), dims - 1, dims,
                                 no_table, no_table, 0, start, start[1:], X, Y, Z, J, k, bd, out[a])
        return out


@needs_numba
@pytest.mark.parametrize("name,pts,k", [*tie_clouds(), *clouds()], ids=[c[0] for c in [*tie_clouds(), *clouds()]])
def test_ring_search_is_brute_force(name, pts, k):
    """The ring search alone (cell_search.ring_knn: the grid kNN's last resort, shared with the
    growing map's hash grid), run for every point of a dense grid of about 10 cells a side, gives
    the brute-force rows."""
    p = pts.astype(np.float32).astype(np.float64)
    h = 0.1 * np.ptp(p, 0).max()
    lo = p.min(0)
    c = np.floor((p - lo) / h).astype(np.int64)
    dims = c.max(0) + 1
    lin = (c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2]
    o = np.argsort(lin, kind="stable")
    start = np.searchsorted(lin[o], np.arange(np.prod(dims) + 1))
    X, Y, Z = (np.ascontiguousarray(p[o, a]) for a in range(3))
    eps = 1e-9 * h  # the faces' distances a little short: cell of a point at a face by rounding
    flo, fhi = p - (lo + c * h) - eps, lo + (c + 1) * h - p - eps

    # the grid holds the points in cell order, J their indices
    idx = np.empty((len(o), k), np.int64)
    idx[o] = _ring_rows(flo[o], fhi[o], c[o], h, dims, start, X, Y, Z, o, k)
    np.testing.assert_array_equal(idx, brute_rows(pts.astype(np.float32), k)[0])
