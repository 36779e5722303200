"""A region's steps (the online map's steps on the rows a frame changed and their frontier):
:func:`diffuser_lab.backends.region.reach`, :func:`diffuser_lab.backends.base.row_runs` and the
backends' region steps, compiled and numpy/scipy."""
import numpy as np
import pytest

from diffuser_lab.backends import numba as nb
from diffuser_lab.backends.base import row_runs
from diffuser_lab.backends.region import reach
from diffuser_lab.method.diffusion import System
from diffuser_lab.method.graph import build_graph

needs_numba = pytest.mark.skipif(not nb.available(), reason="numba not importable or DIFFUSER_LAB_NUMBA=0")


def _system(n=3000, classes=5, seed=0):
    rng = np.random.default_rng(seed)
    pts = rng.random((n, 3)).astype(np.float32)
    pts[:, 2] *= 0.05  # a slab: a surface-like cloud
    g = build_graph(pts, 12)
    mass = np.zeros((n, classes), np.float32)
    seen = rng.random(n) < 0.3
    mass[seen, rng.integers(0, classes, seen.sum())] = rng.integers(1, 6, seen.sum())
    return System.from_graph(g, mass, 1e-4, gamma=0.99)


def test_row_runs_cover_exactly_the_rows_in_pieces():
    rows = np.array([1, 2, 3, 7, 8, 9, 10, 11, 20])
    runs = row_runs(rows, 3)
    np.testing.assert_array_equal(runs, [[1, 4], [7, 10], [10, 12], [20, 21]])
    assert row_runs(np.zeros(0, np.int64), 8).shape == (0, 2)


def test_reach_walks_the_neighbour_lists_and_joins_small_gaps():
    nbr = np.array([[1], [2], [3], [4], [5], [0]] + [[6]] * 194, np.int32)[:200]
    nbr[6:, 0] = np.arange(6, 200)  # rows 6.. read themselves
    assert reach(nbr, np.array([0]), 0, gap=1).tolist() == [0]
    assert reach(nbr, np.array([0]), 2, gap=1).tolist() == [0, 1, 2]
    assert reach(nbr, np.array([0]), 10, gap=1).tolist() == [0, 1, 2, 3, 4, 5]  # the cycle, no further
    assert reach(nbr, np.array([0]), 0, extra=(150, 152), gap=1).tolist() == [0, 150, 151]
    # rows fewer than `gap` apart are joined with the rows between them
    assert reach(nbr, np.array([10, 14, 60]), 0, gap=8).tolist() == [10, 11, 12, 13, 14, 60]


@needs_numba
def test_compiled_reach_is_the_numpy_one():
    rng = np.random.default_rng(1)
    nbr = rng.integers(0, 5000, (5000, 8)).astype(np.int32)
    rows = rng.choice(5000, 30, replace=False)
    a = reach(nbr, rows, 2, (100, 140))
    nb.defer_compile()
    try:
        b = reach(nbr, rows, 2, (100, 140))
    finally:
        nb.undefer()
    np.testing.assert_array_equal(a, b)
    assert 30 < a.size < 5000


@pytest.mark.parametrize("backend", [pytest.param("numba", marks=needs_numba), "scipy"])
@pytest.mark.parametrize("classes", [5, 40])  # one class block; two (the compiled path's several blocks)
def test_a_region_step_is_the_full_step_on_its_rows_and_leaves_the_others(backend, classes):
    s = _system(classes=classes)
    n = s.n
    s.start(backend=backend, tol=0.0, scale=1e-4, rows_hint=n)
    s.steps(3)  # a warm state: every row moved
    z0 = s.backend.state().copy()
    rows = reach(s.sorted_neighbors, np.array([5, 900, 2000]), 3)
    assert 10 < rows.size < n // 2
    out = s.steps(1, rows)
    z1 = s.backend.state().copy()
    others = np.setdiff1d(np.arange(n), rows)
    np.testing.assert_array_equal(z1[others], z0[others])
    s.backend.load(z0)
    full = s.steps(1)
    zf = s.backend.state()
    np.testing.assert_allclose(z1[rows], zf[rows], rtol=1e-6, atol=1e-12)
    # its (change, top) are those of its rows
    assert out[0, 0] == pytest.approx(np.abs(zf[rows] - z0[rows]).max(), rel=1e-5)
    assert out[0, 1] == pytest.approx(zf[rows].max(), rel=1e-6)
    assert full[0, 0] >= out[0, 0]
    # regions after full steps and full steps after regions: the buffers stay consistent
    s.steps(2, rows)
    s.steps(3)
    s.steps(5, rows)
    s.close()


@needs_numba
@pytest.mark.parametrize("classes", [5, 40])
def test_compiled_region_steps_equal_the_numpy_ones(classes):
    zs = []
    for backend in ("numba", "scipy"):
        s = _system(classes=classes)
        s.start(backend=backend, tol=0.0, scale=1e-4)
        s.steps(2)
        for seed in range(4):  # regions of several sizes, odd and even step counts
            rows = reach(s.sorted_neighbors, np.random.default_rng(seed).choice(s.n, 4), 2 + seed)
            s.steps(1 + seed, rows)
        zs.append(s.backend.state().copy())
        s.close()
    np.testing.assert_allclose(zs[0], zs[1], rtol=1e-5, atol=1e-9)
