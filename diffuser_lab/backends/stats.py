"""Per-step statistics of the Jacobi iteration, computed by the backend where its step already
has Z: the labels (Eq. 16) of every step, how many changed since the step before, how confident
they are and, given ground truth, how many are right per class. What a record plots at every
iteration (labels changed, mean confidence, mIoU and accuracy so far) follows from them in
O(C) per step, with no second pass over Z and no Z in the paper's units.

A caller asks for them with :meth:`~diffuser_lab.backends.base.JacobiBackend.track` and a
:class:`Truth` (the ground truth in the backend's row order, or None); each ``steps(count)``
call then leaves the (done, :func:`width`) float64 rows of its steps in the backend's
``stats``. Columns of a row (C = Z's classes):

    CHANGED      rows whose label differs from the step before (the first step: from the labels
                 of the state ``track`` found, all unlabeled from Z = 0)
    LABELLED     rows with a label (their largest score > 0)
    CONFIDENCE   Sum over labelled rows of max_c Z / sum_c Z (float32 per row, summed in float64)
    CORRECT + c  annotated points of class c whose row's label is c       (c = 0 .. C-1)
    PREDICTED + c annotated points whose row's label is c (any true class) (PREDICTED = CORRECT + C)

"Annotated points" are the :class:`Truth`'s: the original points with a ground-truth class,
each counted on the row it was transferred to (a voxel's row counts its points), so mIoU and
accuracy are the original points', as :func:`~diffuser_lab.method.metrics.scores_from_confusion`
computes them from the confusion matrix (true-class counts :attr:`Truth.total` are fixed).

Where it is computed: the compiled Jacobi (:mod:`.numba.jacobi`) in the same compiled call as
the step, per run of rows right after the thread wrote them (generated ``stats_W`` kernels,
``_unrolled.py``); the numpy/scipy backend (:mod:`.scipy`) and every backend that steps one
step at a time beside each step on its row-order state, with :func:`step_statistics` here (the
numpy twin: the same bits for the same Z, the confidence sum apart, which is float64 summed in
another order). Row sums follow one fixed order in both: within each class block (the compiled
kernels' width: :func:`block_width`) the halves of the block padded to a power of two are added
pairwise, then the blocks in order.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

NONE = -1
"""A row nothing reached (the data layer's IGNORE)."""
CHANGED, LABELLED, CONFIDENCE, CORRECT = 0, 1, 2, 3


@dataclass
class StatsRequest:
    """What an observer asks the statistics against (:data:`~diffuser_lab.method.diffusion.Observer`):
    ``gt`` (P,) int the ground truth of the original points (None: none: the per-class columns
    stay 0), ``to_work`` (P,) each one's work point in the caller's order (-1: on none; None:
    point i is work point i)."""

    gt: Optional[np.ndarray] = None
    to_work: Optional[np.ndarray] = None


def width(num_classes: int) -> int:
    """Columns of a statistics row for Z with ``num_classes`` columns: 3 + 2 C."""
    return CORRECT + 2 * int(num_classes)


@dataclass
class Truth:
    """Ground truth in a backend's row order, as CSR over the rows (what :meth:`track` takes).

    Attributes:
        ptr: (N + 1,) int64 row s's entries are ptr[s]:ptr[s + 1].
        cls: (E,) int64 the true class of each entry (0 <= c < C).
        cnt: (E,) float64 how many original points of that class sit on that row.
        total: (C,) float64 annotated original points per true class (the points on no row too:
            they count as misses, as unlabeled points do).
    """

    ptr: np.ndarray
    cls: np.ndarray
    cnt: np.ndarray
    total: np.ndarray

    @property
    def num_classes(self) -> int:
        return int(self.total.shape[0])


def truth_rows(gt: np.ndarray, to_work: Optional[np.ndarray], order: Optional[np.ndarray], n_rows: int,
               num_classes: int) -> Truth:
    """The :class:`Truth` of original points' ground truth ``gt`` (P,) (IGNORE or any value outside
    [0, C): not annotated) on a system's rows: ``to_work`` (P,) each point's work point in the
    caller's order (-1: on none; None: point i is work point i), ``order`` (N,) the caller's work
    point of row s (None: row s is work point s). Points of one class on one row are one entry."""
    gt = np.asarray(gt).ravel().astype(np.int64)
    c = int(num_classes)
    annotated = (gt >= 0) & (gt < c)
    total = np.bincount(gt[annotated], minlength=c)[:c].astype(np.float64)
    work = np.arange(len(gt), dtype=np.int64) if to_work is None else np.asarray(to_work, np.int64).ravel()
    keep = annotated & (work >= 0)
    work, g = work[keep], gt[keep]
    if order is None:
        rows = work
    else:
        inv = np.full(max(n_rows, 1), -1, np.int64)
        inv[np.asarray(order, np.int64)[:n_rows]] = np.arange(n_rows)
        rows = inv[work]
        on = rows >= 0
        rows, g = rows[on], g[on]
    ptr = np.zeros(n_rows + 1, np.int64)
    if to_work is None:  # one point a row at most: no sort
        per_row = np.full(n_rows, -1, np.int64)
        per_row[rows] = g
        on = per_row >= 0
        np.cumsum(on, out=ptr[1:])
        return Truth(ptr=ptr, cls=per_row[on], cnt=np.ones(int(on.sum()), np.float64), total=total)
    key, cnt = np.unique(rows * c + g, return_counts=True)
    rows, cls = key // c, key % c
    np.cumsum(np.bincount(rows, minlength=n_rows)[:n_rows], out=ptr[1:])
    return Truth(ptr=ptr, cls=cls.astype(np.int64), cnt=cnt.astype(np.float64), total=total)


def no_truth(n_rows: int, num_classes: int) -> Truth:
    """A :class:`Truth` with no annotated point (the per-class columns stay 0)."""
    return Truth(np.zeros(n_rows + 1, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float64),
                 np.zeros(int(num_classes), np.float64))


MULTI_WIDTH = 32
"""Class-block width of the compiled Jacobi kernels when the active classes need several blocks
(more than 32): the row sums' order depends on it (``numba.jacobi`` takes it from here)."""


def block_width(n_active: int) -> int:
    """Columns per class block of the row-sum order: the compiled kernels' blocks (one block up
    to 32 active classes, blocks of :data:`MULTI_WIDTH` beyond) padded to a power of two (8, 16
    or 32)."""
    if n_active > 32:
        return MULTI_WIDTH
    return 8 if n_active <= 8 else 16 if n_active <= 16 else 32


def row_sums(Z: np.ndarray) -> np.ndarray:
    """(N, A) float32 -> (N,) float32 Sum_c Z_ic in the order of :func:`block_width` (pairwise
    halves within a block, then the blocks in order): the compiled kernels' sums, bit for bit."""
    n, a = Z.shape
    out = np.zeros(n, np.float32)
    if a == 0:
        return out
    w = block_width(a)
    for first in range(0, a, w):
        blk = np.zeros((n, w), np.float32)
        part = Z[:, first:first + w]
        blk[:, :part.shape[1]] = part
        while blk.shape[1] > 1:
            h = blk.shape[1] // 2
            blk = blk[:, :h] + blk[:, h:]
        out += blk[:, 0]
    return out


def step_statistics(Z: np.ndarray, active: np.ndarray, labels: np.ndarray, truth: Truth, out: np.ndarray) -> None:
    """The numpy twin of the compiled statistics: Z (N, A) float32 the state after a step in row
    order (any positive scale: Z / scale), ``active`` (A,) its classes, ``labels`` (N,) int16 the
    labels of the step before (updated in place to this step's), ``truth`` (:class:`Truth`);
    ``out`` (:func:`width` (C),) float64 is filled (see the module doc)."""
    c = truth.num_classes
    out[:] = 0.0
    n = Z.shape[0]
    if Z.shape[1]:
        best = np.argmax(Z, axis=1)
        top = Z[np.arange(n), best]
        new = np.where(top > 0, np.asarray(active, np.int64)[best], NONE).astype(np.int16)
        tot = row_sums(Z)
        conf = np.divide(top, tot, out=np.zeros(n, np.float32), where=top > 0)
    else:
        new = np.full(n, NONE, np.int16)
        conf = np.zeros(n, np.float32)
    lab = new >= 0
    out[CHANGED] = np.count_nonzero(new != labels)
    out[LABELLED] = np.count_nonzero(lab)
    out[CONFIDENCE] = conf[lab].astype(np.float64).sum()
    labels[:] = new
    if truth.cls.size:
        rows = np.repeat(np.arange(n), np.diff(truth.ptr))
        pred = new[rows].astype(np.int64)
        hit = pred == truth.cls
        out[CORRECT:CORRECT + c] = np.bincount(truth.cls[hit], weights=truth.cnt[hit], minlength=c)[:c]
        got = pred >= 0
        out[CORRECT + c:CORRECT + 2 * c] = np.bincount(pred[got], weights=truth.cnt[got], minlength=c)[:c]


@dataclass
class StepTable:
    """Per-step statistics of consecutive iterations, with what follows from them (vectorised).

    Attributes:
        iterations: (k,) int64 1-based iterations. residual: (k,) float64 relative change of each.
        rows: (k, :func:`width` (C)) float64 the backend's statistics rows (module doc).
        total: (C,) float64 annotated points per true class, or None without ground truth.
    """

    iterations: np.ndarray
    residual: np.ndarray
    rows: np.ndarray
    total: Optional[np.ndarray]

    @property
    def num_classes(self) -> int:
        return (self.rows.shape[1] - CORRECT) // 2

    @property
    def changed(self) -> np.ndarray:
        return self.rows[:, CHANGED]

    @property
    def labelled(self) -> np.ndarray:
        return self.rows[:, LABELLED]

    def mean_confidence(self) -> np.ndarray:
        """(k,) mean of max_c Z / sum_c Z over the labelled rows (0 without any)."""
        lab = self.rows[:, LABELLED]
        return np.divide(self.rows[:, CONFIDENCE], lab, out=np.zeros(len(lab)), where=lab > 0)

    def scores(self) -> tuple[Optional[np.ndarray], Optional[np.ndarray]]:
        """((k,) mIoU, (k,) accuracy) in percent over the annotated points, as
        :func:`~diffuser_lab.method.metrics.scores_from_confusion` (IoU over the classes present
        in the ground truth; NaN where none is); (None, None) without ground truth."""
        if self.total is None:
            return None, None
        c = self.num_classes
        tp = self.rows[:, CORRECT:CORRECT + c]
        pred = self.rows[:, CORRECT + c:CORRECT + 2 * c]
        gt = self.total[None, :]
        present = self.total > 0
        iou = np.divide(tp, gt + pred - tp, out=np.zeros_like(tp), where=(gt + pred - tp) > 0)
        n = present.sum()
        miou = 100.0 * iou[:, present].sum(1) / n if n else np.full(len(tp), np.nan)
        total = self.total.sum()
        acc = 100.0 * tp.sum(1) / total if total > 0 else np.full(len(tp), np.nan)
        return miou, acc

    def __len__(self) -> int:
        return int(self.rows.shape[0])


__all__ = ["StatsRequest", "Truth", "truth_rows", "no_truth", "width", "row_sums", "step_statistics", "StepTable", "block_width",
           "CHANGED", "LABELLED", "CONFIDENCE", "CORRECT"]
