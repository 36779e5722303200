"""VoxelMap (diffuser_lab.data.voxel_map) and IncrementalKnnGraph (diffuser_lab.method.growing): the
incrementally grown graph equals build_graph on the same points, the changed-row sets are complete,
the voxel map is fixed in the world. Both paths: compiled (numba) and numpy/scipy."""
from __future__ import annotations

import numpy as np
import pytest
from knn_rule import brute_rows

from diffuser_lab.backends import numba as nb
from diffuser_lab.backends.voxel_map import voxel_keys
from diffuser_lab.data import voxel_map
from diffuser_lab.data.geometry import backproject
from diffuser_lab.data.voxel_map import VoxelMap
from diffuser_lab.method import growing
from diffuser_lab.method.graph import build_graph
from diffuser_lab.method.growing import IncrementalKnnGraph

K = 24


@pytest.fixture(params=["numba", "numpy"])
def path(request, monkeypatch):
    if request.param == "numba":
        if not nb.available():
            pytest.skip("numba not available")
    else:
        monkeypatch.setattr(nb, "available", lambda: False)
    return request.param


@pytest.fixture(scope="module")
def frames():
    """Back-projected depth of 5 demo views (~16-19k points each, 160x120)."""
    from diffuser_lab.data.sources.demo import make_demo_scene

    scene, _ = make_demo_scene(n_views=5)
    return [backproject(f.depth, f.K, f.T_cw)[0] for f in scene.frames]


def _normals(m: int, rng) -> np.ndarray:
    n = rng.normal(size=(m, 3)).astype(np.float32)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _sorted_d2(points: np.ndarray, nbr: np.ndarray) -> np.ndarray:
    p = points.astype(np.float64)
    return np.sort(((p[nbr] - p[:, None, :]) ** 2).sum(-1), 1)


def _assert_same_graph(g: IncrementalKnnGraph, use_normals: bool, invariant: bool = False, min_same: float = 0.999):
    b = build_graph(g.points, K, g.normals, invariant_normals=invariant)
    # distances per row equal (robust to exact ties); neighbour sets equal except at ties
    np.testing.assert_array_equal(_sorted_d2(g.points, g.neighbors), _sorted_d2(g.points, b.neighbors))
    same = np.all(np.sort(g.neighbors, 1) == np.sort(b.neighbors, 1), 1)
    assert same.mean() > min_same
    assert g.rho == pytest.approx(b.rho, rel=1e-12)
    assert g.sigma_d == pytest.approx(b.sigma_d, rel=1e-12)
    # weights after refresh_weights: as build_graph's, neighbour by neighbour
    o1, o2 = np.argsort(g.neighbors, 1), np.argsort(b.neighbors, 1)
    w1 = np.take_along_axis(g.weights, o1, 1)[same]
    w2 = np.take_along_axis(b.weights, o2, 1)[same]
    np.testing.assert_allclose(w1, w2, rtol=2e-6, atol=1e-30)
    np.testing.assert_allclose(g.row_sums[same], b.weights.sum(1, dtype=np.float64)[same], rtol=2e-6)
    assert (g.normals is not None) == use_normals
    # rows sorted by distance
    d2 = g.dist2
    assert np.all(np.diff(d2, axis=1) >= 0)


@pytest.mark.parametrize("use_normals", [False, True], ids=["no-normals", "normals"])
def test_incremental_equals_rebuilt(path, frames, use_normals):
    rng = np.random.default_rng(0)
    vm = VoxelMap(0.02)
    g = IncrementalKnnGraph(K)
    assert g._nb == (path == "numba") and vm._nb == (path == "numba")
    for f in frames:
        nrm = _normals(len(f), rng) if use_normals else None
        pts, pn = vm.insert(f, nrm)
        prev_nbr, prev_w = g.neighbors.copy(), g.weights.copy()
        changed = g.add(pts, pn)
        assert changed.dtype == np.int64 and np.all(np.diff(changed) > 0)
        # complete: every old row whose neighbours or weights differ is reported, and every new row
        n_old = len(prev_nbr)
        diff = np.flatnonzero(np.any(prev_nbr != g.neighbors[:n_old], 1) | np.any(prev_w != g.weights[:n_old], 1))
        assert np.isin(diff, changed).all()
        assert np.isin(np.arange(n_old, g.n), changed).all()
        assert g.n == vm.n
    assert g.n > 40_000
    g.refresh_weights()
    _assert_same_graph(g, use_normals)


def _grow_both_paths(monkeypatch, batches, **kw) -> list[tuple]:
    """The same adds on the compiled and on the numpy/scipy path: per path (neighbours, dist2,
    weights, row sums, the changed rows of every add, sigma_d)."""
    out = []
    for use_nb in (True, False):
        monkeypatch.setattr(nb, "available", lambda v=use_nb: v)
        g = IncrementalKnnGraph(K, **kw)
        assert g._nb == use_nb
        changed = [g.add(pts, nrm) for pts, nrm in batches]
        out.append((g.neighbors.copy(), g.dist2.copy(), g.weights.copy(), g.row_sums.copy(), changed, g.sigma_d))
    return out


def _assert_paths_agree(a: tuple, b: tuple) -> None:
    """Rows element for element, the same changed rows per add; weights within one float32 ulp (the
    compiled exp is a polynomial, ~1e-14 relative: measured 0 ulp on the demo frames), row sums
    within their float64 summation order (K terms: measured 9e-16 relative)."""
    (n1, d1, w1, s1, c1, sd1), (n2, d2, w2, s2, c2, sd2) = a, b
    np.testing.assert_array_equal(n1, n2)
    np.testing.assert_array_equal(d1, d2)
    assert len(c1) == len(c2)
    for x, y in zip(c1, c2):
        np.testing.assert_array_equal(x, y)
    assert sd1 == sd2
    ulps = np.abs(w1.view(np.int32).astype(np.int64) - w2.view(np.int32))
    assert ulps.max() <= 1
    np.testing.assert_allclose(s1, s2, rtol=3e-15, atol=0)


def test_paths_agree(frames, monkeypatch):
    """The compiled and the numpy/scipy paths give the same graph, add by add: rows, distances and
    changed rows equal, weights to an ulp. A fixed sigma_d is never refreshed by rho's moves."""
    if not nb.available():
        pytest.skip("numba not available")
    vm, rng = VoxelMap(0.02), np.random.default_rng(1)
    batches = []
    for f in frames[:3]:
        batches.append(vm.insert(f, _normals(len(f), rng)))
    a, b = _grow_both_paths(monkeypatch, batches, sigma_d=0.05, invariant_normals=True)
    _assert_paths_agree(a, b)
    n = a[0].shape[0]
    assert a[5] == 0.05 and all(c.size < n for c in a[4][1:])  # no refresh: not every row changed


def test_paths_agree_on_ties(monkeypatch):
    """An integer lattice with duplicates, added in 4 shuffled batches: after every add, both paths
    hold the brute-force rows of the rule (ties by insertion index), and each add reports exactly
    the old rows whose neighbours changed (a new point at the K-th distance loses the tie)."""
    if not nb.available():
        pytest.skip("numba not available")
    rng = np.random.default_rng(4)
    g3 = np.stack(np.meshgrid(np.arange(12), np.arange(10), np.arange(5), indexing="ij"), -1).reshape(-1, 3)
    pts = np.vstack([g3, g3[rng.choice(len(g3), 60)]]).astype(np.float32)[rng.permutation(len(g3) + 60)]
    cuts = [0, 200, 420, 560, len(pts)]
    batches = [(pts[a:b], None) for a, b in zip(cuts[:-1], cuts[1:])]
    for use_nb in (True, False):
        monkeypatch.setattr(nb, "available", lambda v=use_nb: v)
        g = IncrementalKnnGraph(K, sigma_d=0.5)
        for b, (part, _) in zip(cuts[1:], batches):
            prev = g.neighbors.copy()
            changed = g.add(part, None)
            ref, d2 = brute_rows(pts[:b], K)
            np.testing.assert_array_equal(g.neighbors, ref)
            np.testing.assert_array_equal(g.dist2, d2)
            if len(prev) > K:
                moved = np.flatnonzero(np.any(prev != g.neighbors[: len(prev)], 1))
                np.testing.assert_array_equal(changed[changed < len(prev)], moved)
    a, b = _grow_both_paths(monkeypatch, batches, sigma_d=0.5)
    _assert_paths_agree(a, b)


def test_a_new_point_at_the_kth_distance_changes_nothing(path):
    """A sparse lattice beside a dense one (its rows reach beyond the compiled grid's cells) and a
    new point exactly at one sparse row's K-th distance: that row keeps its older neighbour (the
    tie goes to the smaller index) and is not reported; every reported old row did change."""

    def lat(nx, ny, nz, step, off):
        g = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1).reshape(-1, 3)
        return (g * step + np.asarray(off)).astype(np.float32)

    g = IncrementalKnnGraph(K, sigma_d=0.5)
    g.add(np.vstack([lat(20, 20, 3, 1, 0), lat(4, 4, 2, 4, [100, 0, 0])]), None)
    prev, kth = g.neighbors.copy(), g.dist2[:, -1].copy()
    new = np.array([[88, -4, -4], [5, 5, 1.5]], np.float32)
    d2 = ((g.points.astype(np.float64) - new[0]) ** 2).sum(1)
    assert np.all(d2 >= kth) and np.count_nonzero(d2 == kth) == 1  # a tie, never closer
    changed = g.add(new, None)
    moved = np.flatnonzero(np.any(prev != g.neighbors[: len(prev)], 1))
    np.testing.assert_array_equal(changed[changed < len(prev)], moved)
    assert np.flatnonzero(d2 == kth)[0] not in changed


def test_ring_search_alone_gives_the_rows(frames):
    """Every row of a grown graph recomputed by the ring search alone (cell_search.ring_knn, which
    the batch grid kNN shares) is the row the compiled path holds."""
    if not nb.available():
        pytest.skip("numba not available")
    vm, g = VoxelMap(0.02), IncrementalKnnGraph(K)
    for f in frames[:3]:
        g.add(*vm.insert(f, None))
    nbr, d2 = g.neighbors.copy(), g.dist2.copy()
    g._rows._rings(g._arrays(), np.arange(g.n, dtype=np.int64))
    np.testing.assert_array_equal(g.neighbors, nbr)
    np.testing.assert_array_equal(g.dist2, d2)


def test_small_start_and_duplicates(path):
    """From an empty graph: at most K points give padded rows (own index, weight 0); duplicates
    (distance 0) are neighbours and rho skips them, as in build_graph."""
    rng = np.random.default_rng(2)
    g = IncrementalKnnGraph(K, sigma_d_factor=2.0)
    assert g.n == 0 and g.neighbors.shape == (0, K) and np.isnan(g.rho)
    pts = rng.uniform(0, 1, (10, 3)).astype(np.float32)
    ch = g.add(pts, None)
    np.testing.assert_array_equal(ch, np.arange(10))
    # 9 real neighbours per row, then the row itself with weight 0
    np.testing.assert_array_equal(g.neighbors[:, 9:], np.repeat(np.arange(10)[:, None], K - 9, 1))
    assert np.all(g.weights[:, 9:] == 0) and np.all(g.weights[:, :9] > 0)
    assert np.all(np.isin(g.neighbors[0, :9], np.arange(1, 10)))
    more = rng.uniform(0, 1, (3000, 3)).astype(np.float32)
    more[:40] = more[40:80]  # exact duplicates
    g.add(more[:1500], None)
    g.add(more[1500:], None)
    g.add(np.empty((0, 3), np.float32), None)
    assert g.n == 3010
    g.refresh_weights()
    _assert_same_graph(g, False, min_same=0.95)  # a duplicate pair ties with itself in every row it reaches
    b = build_graph(g.points, K)
    assert g.rho == pytest.approx(b.rho, rel=1e-12)


def test_sigma_d_policy(path, frames):
    """Weights use sigma_d_factor * rho_w; a rho move beyond rho_tol refreshes all rows."""
    vm = VoxelMap(0.02)
    g = IncrementalKnnGraph(K, rho_tol=0.5)  # loose: no refresh while rho moves < 50 %
    g.add(*vm.insert(frames[0], None))
    sd0 = g.sigma_d
    assert sd0 == pytest.approx(2.0 * g.rho)
    changed = g.add(*vm.insert(frames[1], None))
    if abs(g.rho - sd0 / 2) <= 0.5 * sd0 / 2:
        assert g.sigma_d == sd0 and changed.size < g.n
    g2 = IncrementalKnnGraph(K, rho_tol=0.0)  # any move: refreshed every add
    vm2 = VoxelMap(0.02)
    g2.add(*vm2.insert(frames[0], None))
    changed = g2.add(*vm2.insert(frames[1], None))
    np.testing.assert_array_equal(changed, np.arange(g2.n))
    assert g2.sigma_d == pytest.approx(2.0 * g2.rho, rel=1e-12)


def test_voxel_map(path):
    vm = VoxelMap(0.02)
    pts = np.array([[0.001, 0.001, 0.001], [0.003, 0.005, 0.007], [0.019, 0.002, 0.002],  # voxel (0,0,0)
                    [0.021, 0.0, 0.0],  # (1,0,0)
                    [-0.001, 0.0, 0.0]],  # (-1,0,0): anchored at the world origin, not at the points
                   np.float32)
    nrm = np.array([[0, 0, 1], [0, 1, 0], [0, 0, 1], [1, 0, 0], [0, -1, 0]], np.float32)
    new, nn = vm.insert(pts, nrm)
    assert vm.n == 3 and new.shape == (3, 3) and new.dtype == np.float32
    keys = voxel_keys(new, 0.02)
    assert np.all(np.diff(keys) > 0)  # Morton order of the voxel keys
    i0 = int(np.flatnonzero(keys == voxel_keys(pts[:1], 0.02)[0])[0])
    np.testing.assert_allclose(new[i0], pts[:3].astype(np.float64).mean(0), rtol=1e-6)
    np.testing.assert_allclose(nn[i0], np.array([0, 1, 2]) / np.sqrt(5), rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(nn, axis=1), 1, rtol=1e-6)
    # occupied voxels drop points: the same frame again adds nothing, nor a point in an old voxel
    again, _ = vm.insert(pts, nrm)
    assert again.shape == (0, 3) and vm.n == 3
    mixed, mn = vm.insert(np.array([[0.01, 0.01, 0.01], [0.05, 0.0, 0.0]], np.float32), None)
    assert mn is None and vm.n == 4
    np.testing.assert_array_equal(mixed, np.array([[0.05, 0.0, 0.0]], np.float32))


def test_voxel_map_deterministic(frames, monkeypatch):
    """Same frames, same outputs (bit for bit), from either path."""
    outs = []
    for use_nb in ([True, False] if nb.available() else [False]):
        monkeypatch.setattr(nb, "available", lambda v=use_nb: v)
        for _ in range(2):
            vm = VoxelMap(0.02)
            outs.append(np.concatenate([vm.insert(f, None)[0] for f in frames[:3]]))
    for o in outs[1:]:
        np.testing.assert_array_equal(o, outs[0])
    assert len(np.unique(voxel_keys(outs[0], 0.02))) == len(outs[0])


def test_module_switch(monkeypatch):
    monkeypatch.setattr(nb, "available", lambda: False)
    assert not voxel_map.VoxelMap(0.02)._nb and not growing.IncrementalKnnGraph()._nb
    with pytest.raises(ValueError):
        VoxelMap(0.0)
    g = IncrementalKnnGraph(K)
    g.add(np.zeros((3, 3), np.float32), None)
    with pytest.raises(ValueError):
        g.add(np.zeros((3, 3), np.float32), np.zeros((3, 3), np.float32))  # normals with none before
