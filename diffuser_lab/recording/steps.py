"""What each recorded diffusion iteration shows, computed once and shared by both recorders
(and by ``diffuser-lab-inspect --to-rrd``, which rebuilds the same steps from run.mcap)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional, Sequence

import numpy as np
from scipy.spatial import cKDTree

from diffuser_lab.backends.records import step_stats
from diffuser_lab.data.scene import IGNORE
from diffuser_lab.method.metrics import scores_from_confusion


@dataclass
class Step:
    """One recorded iteration. Arrays on the work cloud have M rows, on the original points N.

    Attributes:
        iteration: 1-based diffusion iteration.
        Z: (M, C) float32 scores in the paper's units (read-only; valid during the call only).
        labels: (M,) int16 argmax of Z (Eq. 16), IGNORE where the row is all zero.
        confidence: (M,) float32 normalised max of Z, max_c Z / sum_c Z (0 where unlabeled).
        residual: relative change max|Z_t - Z_{t-1}| / max|Z_t| of this iteration.
        n_changed: labels changed since the previous recorded iteration.
        previous: the previous recorded iteration (0: none; changes counted from all-unlabeled).
        miou, accuracy: percent on the original points, None without ground truth.
        coverage: percent of work points with a label.
        mean_confidence: mean confidence over labelled work points.
        wrong: (N,) bool, annotated original points whose transferred label is wrong, or None.
    """

    iteration: int
    Z: np.ndarray
    labels: np.ndarray
    confidence: np.ndarray
    residual: float
    n_changed: int
    previous: int
    miou: Optional[float]
    accuracy: Optional[float]
    coverage: float
    mean_confidence: float
    wrong: Optional[np.ndarray]


def original_to_work(work_points: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N,) int64 index of the nearest work point of every original point: the same query as
    :func:`diffuser_lab.data.geometry.nearest_transfer`, so transferred labels match the run's."""
    _, idx = cKDTree(work_points).query(points, k=1, workers=-1)
    return np.asarray(idx, np.int64)


class StepTracker:
    """Turns (iteration, Z, residual) into :class:`Step` s, remembering the previous labels.

    Args:
        n_work: M, rows of Z.
        class_names: the taxonomy's names (metrics per class).
        gt: (N,) int16 ground truth of the original points, or None.
        to_work: (N,) int index of each original point's work point, or None when the work
            cloud is the original cloud.
        misses: (C,) annotated points of each class on no work point (a single-frame target's
            pixels without depth): they count as unlabeled, or None.
    """

    def __init__(self, n_work: int, class_names: Sequence[str], gt: Optional[np.ndarray] = None,
                 to_work: Optional[np.ndarray] = None, misses: Optional[np.ndarray] = None):
        self.names = list(class_names)
        self.gt = None if gt is None else np.asarray(gt)
        self.to_work = to_work
        self.misses = misses
        self.prev_labels = np.full(n_work, IGNORE, np.int16)
        self.prev_iteration = 0

    def step(self, iteration: int, Z: np.ndarray, residual: float, labels: Optional[np.ndarray] = None) -> Step:
        """``labels``: the (M,) labels of the exact Z when ``Z`` is a stored approximation (they
        replace Z's argmax; confidence still comes from Z)."""
        s = step_stats(Z, self.prev_labels, self.gt, self.to_work, labels)
        miou = acc = None
        if s.counts is not None:
            counts = s.counts
            if self.misses is not None:
                counts = counts.copy()
                counts[:, -1] += np.asarray(self.misses, np.int64)[:counts.shape[0]]
            sc = scores_from_confusion(counts, self.names)
            miou, acc = sc["miou"], sc["accuracy"]
        st = Step(iteration=int(iteration), Z=Z, labels=s.labels, confidence=s.confidence, residual=float(residual),
                  n_changed=s.n_changed, previous=self.prev_iteration, miou=miou, accuracy=acc,
                  coverage=100.0 * s.n_labelled / max(len(s.labels), 1), mean_confidence=s.mean_confidence,
                  wrong=s.wrong)
        self.prev_labels = s.labels
        self.prev_iteration = int(iteration)
        return st


def metrics_rows(table: Any) -> np.ndarray:
    """run.rrd's scalars of consecutive iterations from the backend's statistics (a
    :class:`~diffuser_lab.backends.stats.StepTable`): (k, 6) float64 rows of iteration, relative
    residual, labels changed since the iteration before, mean confidence over labelled work
    points, mIoU and accuracy in percent on the original points (NaN without ground truth), what
    :class:`StepTracker` gives for a recorded iteration."""
    miou, acc = table.scores()
    k = len(table)
    nan = np.full(k, np.nan)
    return np.stack([np.asarray(table.iterations, np.float64), np.asarray(table.residual, np.float64),
                     np.asarray(table.changed, np.float64), table.mean_confidence(),
                     nan if miou is None else miou, nan if acc is None else acc], 1)


__all__ = ["Step", "StepTracker", "original_to_work", "metrics_rows"]
