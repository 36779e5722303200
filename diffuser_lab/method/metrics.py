"""Segmentation scores: per-class IoU, mIoU, overall accuracy, coverage.

Conventions: mIoU and IoU are in percent, averaged over the classes present in the
ground truth; points (or pixels) whose ground truth is IGNORE are excluded; a prediction
of IGNORE (unlabeled) at an annotated point counts as a miss for its true class.
Coverage is the share of *all* points that received a label.
"""
from __future__ import annotations

import numpy as np

from diffuser_lab.data.scene import IGNORE


def confusion_matrix(pred: np.ndarray, gt: np.ndarray, num_classes: int) -> np.ndarray:
    """(C, C+1) int64 counts: rows = true class, columns = predicted class, last = unlabeled.

    Args:
        pred, gt: equal-shape integer arrays of class ids or IGNORE (any shape: points or pixels).
    """
    pred = np.asarray(pred).ravel().astype(np.int64)
    gt = np.asarray(gt).ravel().astype(np.int64)
    if pred.shape != gt.shape:
        raise ValueError(f"predictions ({pred.size}) and ground truth ({gt.size}) differ in size")
    valid = gt != IGNORE
    p = np.where(pred[valid] == IGNORE, num_classes, pred[valid])
    flat = gt[valid] * (num_classes + 1) + p
    return np.bincount(flat, minlength=num_classes * (num_classes + 1)).reshape(num_classes, num_classes + 1)


def scores_from_confusion(conf: np.ndarray, names: tuple[str, ...] | list[str]) -> dict:
    """mIoU (percent), accuracy (percent), per-class IoU (percent, classes present in gt only)."""
    c = conf.shape[0]
    tp = np.diag(conf[:, :c]).astype(np.float64)
    gt_count = conf.sum(1).astype(np.float64)
    pred_count = conf[:, :c].sum(0).astype(np.float64)
    present = gt_count > 0
    iou = np.divide(tp, gt_count + pred_count - tp, out=np.zeros(c), where=present)
    total = gt_count.sum()
    return {
        "miou": float(100.0 * iou[present].mean()) if present.any() else float("nan"),
        "accuracy": float(100.0 * tp.sum() / total) if total > 0 else float("nan"),
        "per_class_iou": {names[i]: float(100.0 * iou[i]) for i in np.flatnonzero(present)},
    }


def score(pred: np.ndarray, gt: np.ndarray, names: tuple[str, ...] | list[str]) -> dict:
    """Scores of (N,) predicted labels against (N,) ground truth, with coverage in percent."""
    out = scores_from_confusion(confusion_matrix(pred, gt, len(names)), names)
    out["coverage"] = float(100.0 * np.mean(np.asarray(pred) != IGNORE)) if np.size(pred) else 0.0
    return out
