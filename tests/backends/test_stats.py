"""Per-step statistics where the step already has Z (issue 50 item 1): the compiled Jacobi's
``stats_W`` kernels against their numpy twin, the ground truth on the rows (voxels: several
original points a row), and what System.run hands observers against the same figures computed
the old way, a second pass over Z in the paper's units; the labels and Z do not change."""
from __future__ import annotations

import numpy as np
import pytest

from diffuser_lab.backends import numba as nb
from diffuser_lab.backends.records import step_stats
from diffuser_lab.backends.stats import (CONFIDENCE, StatsRequest, StepTable, row_sums, step_statistics, truth_rows,
                                         width)
from diffuser_lab.method.diffusion import diffuse, normalise
from diffuser_lab.method.graph import build_graph
from diffuser_lab.method.metrics import confusion_matrix, scores_from_confusion
from diffuser_lab.runs.workloads import room_workload

BACKENDS = ["scipy"] + (["numba"] if nb.available() else [])
needs_numba = pytest.mark.skipif(not nb.available(), reason="numba is not importable (DIFFUSER_LAB_NUMBA=0?)")


def blocks(Z: np.ndarray) -> tuple[np.ndarray, int]:
    """Z (N, A) in the compiled backend's layout: (blocks, N * W) float32 and W."""
    from diffuser_lab.backends.numba.jacobi import blocks_of

    spec = blocks_of(Z.shape[1])
    W = spec[0][2]
    out = np.zeros((len(spec), Z.shape[0], W), np.float32)
    for b, (first, cnt, _) in enumerate(spec):
        out[b, :, :cnt] = Z[:, first:first + cnt]
    return out.reshape(len(spec), -1), W


def random_state(n: int, a: int, seed: int) -> np.ndarray:
    """Z (n, a) >= 0 with rows of zeros, exact ties between classes and values below one."""
    rng = np.random.default_rng(seed)
    Z = rng.random((n, a)).astype(np.float32) * (rng.random((n, a)) < 0.4)
    Z[rng.random(n) < 0.1] = 0.0  # unreached rows
    tie = rng.random(n) < 0.1
    Z[tie, a - 1] = Z[tie].max(1)  # the last class ties the first maximum: the first wins
    return Z


@needs_numba
@pytest.mark.parametrize("a", [3, 8, 13, 20, 24, 31, 32, 40, 70])
def test_compiled_statistics_equal_the_numpy_twin(a):
    from diffuser_lab.backends.numba import _unrolled, slp

    n, c = 3000, 80
    Z = random_state(n, a, a)
    rng = np.random.default_rng(1)
    active = np.sort(rng.choice(c, a, replace=False)).astype(np.int64)
    gt = rng.integers(-1, c, 5 * n)  # several original points a row, some on none
    truth = truth_rows(gt, rng.integers(-1, n, 5 * n), None, n, c)
    prev = rng.integers(-1, c, n).astype(np.int16)
    want, got = np.zeros(width(c)), np.zeros(width(c))
    lab_np, lab_nb = prev.copy(), prev.copy()
    step_statistics(Z, active, lab_np, truth, want)
    Zs, W = blocks(Z)
    with slp():
        kernel = getattr(_unrolled, f"stats_{W}")
        for lo in range(0, n, 512):  # in runs of rows, as the threads take them
            kernel(Zs, active, lab_nb, truth.ptr, truth.cls, truth.cnt, lo, min(n, lo + 512), got)
    np.testing.assert_array_equal(lab_nb, lab_np)
    keep = np.arange(len(want)) != CONFIDENCE
    np.testing.assert_array_equal(got[keep], want[keep])
    assert got[CONFIDENCE] == pytest.approx(want[CONFIDENCE], rel=1e-12)  # float64 sums in another order


def test_row_sums_are_the_blocks_pairwise_halves():
    Z = random_state(50, 21, 0)
    pad = np.zeros((50, 32), np.float32)
    pad[:, :21] = Z
    s = ((pad[:, :16] + pad[:, 16:])[:, :8] + (pad[:, :16] + pad[:, 16:])[:, 8:])
    s = (s[:, :4] + s[:, 4:])
    s = (s[:, :2] + s[:, 2:])
    np.testing.assert_array_equal(row_sums(Z), s[:, 0] + s[:, 1])
    np.testing.assert_allclose(row_sums(random_state(50, 70, 1)), random_state(50, 70, 1).sum(1), rtol=1e-5)


def test_truth_on_the_rows_gives_the_original_points_scores():
    """Voxels: a row holds several original points (of several classes); the scores from the
    per-class counts are scores_from_confusion's of the points' transferred labels."""
    rng = np.random.default_rng(3)
    n, c, p = 400, 7, 3000
    to_work = rng.integers(0, n, p)
    gt = rng.integers(-1, c, p)
    order = rng.permutation(n)  # row s is work point order[s]
    truth = truth_rows(gt, to_work, order, n, c)
    labels_rows = rng.integers(-1, c, n).astype(np.int16)
    Z = np.zeros((n, c), np.float32)  # one-hot states of those labels, in row order
    on = labels_rows >= 0
    Z[np.flatnonzero(on), labels_rows[on]] = 1.0
    row = np.zeros(width(c))
    step_statistics(Z, np.arange(c), np.full(n, -1, np.int16), truth, row)
    miou, acc = StepTable(np.array([1]), np.array([1.0]), row[None], truth.total).scores()
    labels_points = np.empty(n, np.int16)
    labels_points[order] = labels_rows  # work point order[s] has row s's label
    want = scores_from_confusion(confusion_matrix(labels_points[to_work], gt, c), [str(i) for i in range(c)])
    assert miou[0] == pytest.approx(want["miou"], abs=1e-9) and acc[0] == pytest.approx(want["accuracy"], abs=1e-9)
    assert truth.total.sum() == (gt >= 0).sum()


@pytest.fixture(scope="module")
def room():
    w = room_workload(4000, n_views=4, width=160, height=120)
    system = normalise(build_graph(w.points, 16, w.normals, backend="scipy"), w.mass, 1e-4)
    gt = np.random.default_rng(0).integers(-1, w.mass.shape[1], system.n).astype(np.int16)
    return system, gt


class Watch:
    """Asks for every step's statistics and sees every iteration's Z (the old way's input)."""

    def __init__(self, gt, ask=True):
        self.gt, self.ask, self.tables, self.Z = gt, ask, [], {}

    def statistics(self):
        return StatsRequest(self.gt, None) if self.ask else None

    def on_statistics(self, table):
        self.tables.append(table)

    def wants(self, it):
        return True

    def __call__(self, it, Z, stats):
        self.Z[it] = Z.copy()


@pytest.mark.parametrize("backend", BACKENDS + ["scipy-sparse"])
def test_every_steps_statistics_are_those_of_its_z_and_change_nothing(room, backend):
    system, gt = room
    kw = {"backend": "scipy", "sparse_classes": "on", "classes_per_point": 8} if backend == "scipy-sparse" \
        else {"backend": backend}
    plain = diffuse(system, max_iter=25, tol=0.0, **kw)
    w = Watch(gt)
    res = diffuse(system, max_iter=25, tol=0.0, observer=w, **kw)
    np.testing.assert_array_equal(res.Z, plain.Z)  # statistics never change the result
    its = np.concatenate([t.iterations for t in w.tables])
    assert its.tolist() == list(range(1, 26))
    table = StepTable(its, np.concatenate([t.residual for t in w.tables]), np.concatenate([t.rows for t in w.tables]),
                      w.tables[0].total)
    miou, acc = table.scores()
    np.testing.assert_allclose(table.residual, res.residuals)
    prev = np.full(system.n, -1, np.int16)
    names = [str(i) for i in range(system.num_classes)]
    for k, it in enumerate(its):  # the old way: a second pass over Z in the paper's units
        s = step_stats(w.Z[it], prev, gt)
        prev = s.labels
        sc = scores_from_confusion(s.counts, names)
        assert table.changed[k] == s.n_changed and table.labelled[k] == s.n_labelled, it
        assert miou[k] == pytest.approx(sc["miou"], abs=1e-9) and acc[k] == pytest.approx(sc["accuracy"], abs=1e-9)
        assert table.mean_confidence()[k] == pytest.approx(s.mean_confidence, rel=1e-5)


@needs_numba
def test_compiled_sparse_backend_tracks_beside_its_steps(room):
    system, gt = room
    kw = {"backend": "numba", "sparse_classes": "on", "classes_per_point": 8}
    plain = diffuse(system, max_iter=12, tol=0.0, **kw)
    w = Watch(gt)
    res = diffuse(system, max_iter=12, tol=0.0, observer=w, **kw)
    np.testing.assert_array_equal(res.Z, plain.Z)
    assert sum(len(t) for t in w.tables) == 12
    last = step_stats(w.Z[12], step_stats(w.Z[11], np.full(system.n, -1, np.int16), gt).labels, gt)
    assert w.tables[-1].changed[-1] == last.n_changed


def test_no_request_no_statistics(room):
    system, gt = room
    w = Watch(gt, ask=False)
    diffuse(system, max_iter=5, tol=0.0, observer=w, backend=BACKENDS[-1])
    assert w.tables == [] and sorted(w.Z) == [1, 2, 3, 4, 5]


def test_without_ground_truth_the_per_class_columns_stay_zero(room):
    system, _ = room
    w = Watch(None)
    diffuse(system, max_iter=5, tol=0.0, observer=w, backend=BACKENDS[-1])
    t = w.tables[0]
    assert t.total is None and t.scores() == (None, None) and not t.rows[:, 3:].any()
    assert (t.labelled > 0).all() and t.changed[0] == t.labelled[0]  # the first step labels from none
