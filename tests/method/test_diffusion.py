"""The one diffusion core (diffuser_lab.method.diffusion.System): what every user of the method gets
from it. Renormalising a set of rows equals normalising anew; steps from Z = 0 with gamma = 1 are the
batch diffusion; rows re-ordered or appended, classes activated and warm starts on every backend give
the numbers a system built at once gives."""
from __future__ import annotations

import numpy as np
import pytest

from diffuser_lab.backends import BACKENDS
from diffuser_lab.backends import numba as nb
from diffuser_lab.method.diffusion import System, diffuse, normalise
from diffuser_lab.method.graph import build_graph

BACKEND_NAMES = [b for b in BACKENDS if b != "torch"]


@pytest.fixture(scope="module")
def cloud():
    rng = np.random.default_rng(3)
    pts = rng.random((3000, 3)).astype(np.float32)
    nrm = rng.normal(size=(3000, 3)).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    mass = np.zeros((3000, 12), np.float32)
    seen = rng.random(3000) < 0.4
    mass[seen, rng.integers(0, 12, seen.sum())] = rng.integers(1, 4, seen.sum())
    return build_graph(pts, 12, nrm), mass


def test_renormalising_rows_equals_normalising_anew(cloud):
    g, mass = cloud
    s = normalise(g, mass.copy(), 1e-3)
    more = mass.copy()
    rows = np.sort(np.random.default_rng(0).choice(len(more), 200, replace=False))
    more[g.order[rows], 5] += 2.0  # new evidence on the points of system rows `rows`
    s.mass = more
    s.renormalise(rows)
    fresh = normalise(g, more, 1e-3)
    np.testing.assert_array_equal(s.sorted_P, fresh.sorted_P)
    np.testing.assert_array_equal(s.B_rows, fresh.B_rows)
    np.testing.assert_array_equal(s.active, fresh.active)


@pytest.mark.parametrize("backend", BACKEND_NAMES)
def test_steps_from_zero_are_the_batch_diffusion(cloud, backend):
    g, mass = cloud
    batch = diffuse(normalise(g, mass, 1e-3), max_iter=30, tol=0.0, backend=backend)
    s = normalise(g, mass, 1e-3)
    s.start(backend=backend, tol=0.0)
    done = sum(len(s.steps(10)) for _ in range(3))  # three calls: Z is kept between them
    assert done == 30
    np.testing.assert_array_equal(s.scores(), batch.Z)
    s.close()


def _first_rows(nbr, w, half):
    """The graph of the first ``half`` rows alone: edges into the others point at the row itself
    with weight 0 (as fixed-length rows are padded)."""
    inside = nbr[:half] < half
    return (np.where(inside, nbr[:half], np.arange(half, dtype=np.int32)[:, None]),
            np.where(inside, w[:half], 0).astype(np.float32))


@pytest.mark.parametrize("backend", BACKEND_NAMES)
def test_rows_moved_appended_and_classes_activated_keep_the_numbers(cloud, backend):
    """A system that grows while it runs (rows appended, class 7 named only then: Z kept, never
    restarted) and is re-ordered gives bit for bit what a system of its final size gives when it
    runs the same steps with the second half's rows idle (no edges, no evidence) at first."""
    g, mass = cloud
    n = g.n
    lam, gamma = 1e-3, 0.99
    nbr, w, ws, order = g.sorted_neighbors, g.sorted_weights, g.sorted_row_sums, g.order
    half = n // 2
    early = mass.copy()
    early[:, 7] = 0  # class 7 is named only when the rows are appended
    assert mass[:, 7].any()
    nbr0, w0 = _first_rows(nbr, w, half)
    # the grown system: the first half for 3 steps, then every row and class 7, 8 steps, moved, 8 more
    s = System(nbr0, w0, w0.sum(1, dtype=np.float64), early, lam, order=order[:half], gamma=gamma)
    s.start(backend=backend, tol=0.0, scale=lam, rows_hint=n)
    s.steps(3)
    assert 7 not in s.active
    s.resize(n)
    s.set_order(np.arange(half, n), order[half:])
    s.sorted_neighbors[:] = nbr
    s.edge_weights[:] = w
    s.edge_sums[:] = ws
    s.mass = mass
    s.renormalise(np.arange(n))
    assert 7 in s.active
    s.steps(8)
    # the reference: all n rows from the start, the second half idle (edges to itself of weight 0, no evidence)
    idle = early.copy()
    idle[order[half:]] = 0
    nbr_i = np.concatenate([nbr0, np.repeat(np.arange(half, n, dtype=np.int32)[:, None], nbr.shape[1], 1)])
    w_i = np.concatenate([w0, np.zeros((n - half, w.shape[1]), np.float32)])
    ref = System(nbr_i, w_i, w_i.sum(1, dtype=np.float64), idle, lam, order=order, gamma=gamma)
    ref.start(backend=backend, tol=0.0, scale=lam)
    ref.steps(3)
    ref.sorted_neighbors[:] = nbr
    ref.edge_weights[:] = w
    ref.edge_sums[:] = ws
    ref.mass = mass
    ref.renormalise(np.arange(n))
    ref.steps(8)
    np.testing.assert_array_equal(s.scores(), ref.scores())  # the 3 early steps count in both
    fresh = System(nbr, w, ws, mass, lam, order=order, gamma=gamma)
    fresh.start(backend=backend, tol=0.0, scale=lam)
    fresh.steps(8)
    assert not np.array_equal(s.scores(), fresh.scores())  # ... and they do change the numbers
    perm = np.random.default_rng(1).permutation(n)
    s.move(perm)
    np.testing.assert_array_equal(s.scores(), ref.scores())  # caller's order: the move is invisible
    s.steps(8)
    ref.steps(8)
    np.testing.assert_array_equal(s.scores(), ref.scores())
    lab_s, lab_r = np.zeros(n, np.int16), np.zeros(n, np.int16)
    s.labels(lab_s)
    ref.labels(lab_r)
    np.testing.assert_array_equal(lab_s[np.argsort(perm)], lab_r)  # row order follows the move
    for x in (s, ref, fresh):
        x.close()


@pytest.mark.parametrize("backend", BACKEND_NAMES)
def test_warm_start_takes_new_evidence(cloud, backend):
    """Evidence arriving between calls (rows renormalised, a class named for the first time): the
    iteration goes on from its Z, equal on every backend."""
    g, mass = cloud
    first = mass.copy()
    first[:, 7] = 0  # class 7 is named only later
    s = normalise(g, first, 1e-3)
    s.start(backend=backend, tol=0.0, scale=1e-3)
    s.steps(5)
    s.mass = mass
    rows = np.flatnonzero((mass[g.order] != first[g.order]).any(1))
    s.renormalise(rows)
    assert 7 in s.active
    s.steps(5)
    out = s.scores()
    s.close()
    ref = normalise(g, first, 1e-3)
    ref.start(backend="scipy", tol=0.0, scale=1e-3)
    ref.steps(5)
    ref.mass = mass
    ref.renormalise(rows)
    ref.steps(5)
    np.testing.assert_allclose(out, ref.scores(), rtol=1e-5, atol=1e-7 * float(np.abs(out).max()))
    ref.close()


def _grow_while_running(g, mass, backend):
    """Half the rows for 4 steps, then every row (appended: they start at 0) for 4 more."""
    n, half = g.n, g.n // 2
    nbr, w, order = g.sorted_neighbors, g.sorted_weights, g.order
    nbr0, w0 = _first_rows(nbr, w, half)
    s = System(nbr0, w0, w0.sum(1, dtype=np.float64), mass, 1e-3, order=order[:half], gamma=0.99)
    s.start(backend=backend, tol=0.0, scale=1e-3, rows_hint=n)
    s.steps(4)
    s.resize(n)
    s.set_order(np.arange(half, n), order[half:])
    s.sorted_neighbors[:] = nbr
    s.edge_weights[:] = w
    s.edge_sums[:] = g.sorted_row_sums
    s.renormalise(np.arange(n))
    s.steps(4)
    out = s.scores()
    s.close()
    return out


@pytest.mark.parametrize("backend", [b for b in BACKEND_NAMES if b != "scipy"])
def test_rows_appended_while_running_agree_with_scipy(cloud, backend):
    g, mass = cloud
    a, b = _grow_while_running(g, mass, backend), _grow_while_running(g, mass, "scipy")
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7 * float(np.abs(b).max()))
    assert (a[g.order[: g.n // 2]] > 0).any() and (a[g.order[g.n // 2:]] > 0).any()


TIE_BACKENDS = [(b, sparse) for b in BACKEND_NAMES for sparse in ("off", "on")] + [("torch", "off")]


@pytest.mark.parametrize("classes", [12, 40], ids=["one-block", "several-blocks"])
@pytest.mark.parametrize("backend,sparse", TIE_BACKENDS, ids=[f"{b}-sparse" if s == "on" else b for b, s in TIE_BACKENDS])
def test_labels_take_the_first_class_at_exact_ties(backend, sparse, classes):
    """Eq. 16 at exact ties in Z: the lowest class of the row's equal maxima, on every backend (the
    numba kernels scan class blocks in ascending order and keep a strictly larger score only; 40
    classes make several blocks there, with ties across them), IGNORE where the row is all 0."""
    if backend == "numba" and not nb.available():
        pytest.skip("numba not importable or DIFFUSER_LAB_NUMBA=0")
    device = None
    if backend == "torch":
        pytest.importorskip("torch", reason="torch is not installed: the torch backend's ties are not checked")
        device = "cpu"
    rng = np.random.default_rng(classes)
    n, k = 500, 8
    nbr = rng.integers(0, n, (n, k)).astype(np.int32)
    w = np.ones((n, k), np.float32)
    mass = np.zeros((n, classes), np.float32)
    mass[np.arange(n), np.arange(n) % classes] = 1.0  # every class active
    s = System(nbr, w, w.sum(1, dtype=np.float64), mass, 1e-3)
    s.start(backend=backend, device=device, tol=0.0, sparse_classes=sparse, classes_per_point=classes)
    Z = rng.integers(0, 3, (n, classes)).astype(np.float32) * np.float32(0.25)  # many equal maxima
    Z[:40] = 0.0  # nothing reached these
    Z[40:60, :] = 0.5  # all classes tie
    Z[60:80, [classes - 1, classes // 2, classes // 2 + 1]] = 2.0  # ties across the middle (block edges)
    s.backend.load(Z)
    out = np.full(n, 99, np.int16)
    s.labels(out)
    top = Z.max(1, keepdims=True)
    first = np.where(Z == top, np.arange(classes), classes).min(1)  # the lowest class at the maximum
    expect = np.where(top[:, 0] > 0, s.active[np.minimum(first, classes - 1)], -1)
    np.testing.assert_array_equal(out, expect)
    assert out[40] == 0 and out[60] == classes // 2 and np.all(out[:40] == -1)
    s.close()
