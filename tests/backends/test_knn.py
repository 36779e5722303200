"""The compiled graph pieces (diffuser_lab.backends.numba: morton, grid_knn, weights) against plain
references: the grid kNN gives the brute-force neighbour sets (float64 distances, ties by sorted
index), the Morton order is numpy's, and the fused normalisation is bit for bit the numpy one."""
import numpy as np
import pytest

from diffuser_lab.backends import numba as nb
from diffuser_lab.backends.numba import cell_search, grid_knn
from diffuser_lab.backends.morton import morton_codes, quantize
from diffuser_lab.method.diffusion import EDGE_FLOOR, normalise
from diffuser_lab.method.graph import build_graph

pytestmark = pytest.mark.skipif(not nb.available(), reason="numba not importable or DIFFUSER_LAB_NUMBA=0")


def brute(ps, k):
    """(N, K) the k nearest of every row of ps by (float64 d2, index), sorted."""
    p = ps.astype(np.float64)
    d = ((p[None, :, :] - p[:, None, :]) ** 2).sum(-1)
    np.fill_diagonal(d, np.inf)
    j = np.broadcast_to(np.arange(len(p)), d.shape)
    return np.sort(np.lexsort((j, d), axis=-1)[:, :k], 1)


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


@pytest.mark.parametrize("name,pts,k", list(clouds()), ids=[c[0] for c in clouds()])
def test_grid_knn_is_brute_force(name, pts, k):
    pts = pts.astype(np.float32)
    order, P4, _, res = grid_knn.sorted_knn(pts, None, k)
    np.testing.assert_array_equal(order, np.argsort(morton_codes(quantize(pts)[0]), kind="stable"))
    assert res is not None  # the grid, not the KD-tree fallback
    idx, d0 = res
    ref = brute(pts[order], k)
    np.testing.assert_array_equal(np.sort(idx, 1), ref)
    p = pts[order].astype(np.float64)
    d2 = ((p[ref] - p[:, None, :]) ** 2).sum(-1)
    np.testing.assert_array_equal(d0, np.where(d2 > 0, d2, np.inf).min(1))


def test_weights_and_normalisation_match_the_numpy_path():
    rng = np.random.default_rng(1)
    a = rng.random((3000, 2))
    pts = np.c_[a, 0.02 * np.sin(6 * a[:, 0])].astype(np.float32)
    nrm = rng.normal(size=(3000, 3)).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    mass = rng.integers(0, 3, (3000, 21)).astype(np.float32)
    g, s = build_graph(pts, 16, nrm), build_graph(pts, 16, nrm, backend="scipy")
    np.testing.assert_array_equal(g.order, s.order)
    np.testing.assert_array_equal(np.sort(g.sorted_neighbors, 1), np.sort(s.sorted_neighbors, 1))
    assert g.rho == s.rho
    og, os_ = np.argsort(g.sorted_neighbors, 1), np.argsort(s.sorted_neighbors, 1)
    # exp is a polynomial there (relative error ~1e-14): float32 results agree to an ulp at most
    np.testing.assert_allclose(np.take_along_axis(g.sorted_weights, og, 1),
                               np.take_along_axis(s.sorted_weights, os_, 1), rtol=2e-7, atol=0)
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


@pytest.mark.parametrize("name,pts,k", list(clouds()), ids=[c[0] for c in clouds()])
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

    @nb.NB.njit
    def rows(flo, fhi, c, h, dims, start, X, Y, Z, J, k):
        out = np.empty((J.shape[0], k), np.int64)
        bd = np.empty(k)
        no_table = np.empty(0, np.int64)
        for a in range(J.shape[0]):
            cell_search.ring_knn(J[a], X[a], Y[a], Z[a], (c[a, 0], c[a, 1], c[a, 2]), (flo[a, 0], flo[a, 1], flo[a, 2]),
                                 (fhi[a, 0], fhi[a, 1], fhi[a, 2]), h, np.zeros(3, np.int64), dims - 1, dims,
                                 no_table, no_table, 0, start, start[1:], X, Y, Z, J, k, bd, out[a])
        return out

    # the grid holds the points in cell order, J their indices
    idx = np.empty((len(o), k), np.int64)
    idx[o] = rows(flo[o], fhi[o], c[o], h, dims, start, X, Y, Z, o, k)
    np.testing.assert_array_equal(np.sort(idx, 1), brute(pts.astype(np.float32), k))
