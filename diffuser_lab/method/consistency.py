"""How much a network's labels agree between views that see the same surface.

Video-segmentation papers measure a network's temporal consistency (TC) as the mIoU between a
frame's prediction and the previous frame's prediction warped onto it by optical flow (Liu et
al., "Efficient Semantic Video Segmentation with Per-frame Inference", ECCV 2020). With depth and
poses the warp is exact: :func:`reproject_labels` carries one view's labels onto another's pixels
that see the same 3D points, and :func:`view_consistency` scores the agreement of neighbouring views
(docs/simulated-network.md calibrates the simulated network's persistence with it; the command
``python -m diffuser_lab.cli.consistency`` prints them for a configured scene).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from diffuser_lab.data.geometry import backproject, project
from diffuser_lab.data.scene import IGNORE, Frame

from .metrics import confusion_matrix, scores_from_confusion

__all__ = ["reproject_labels", "view_consistency"]


def reproject_labels(src_labels: np.ndarray, src: Frame, dst: Frame, depth_tol: float = 0.05) -> np.ndarray:
    """``src_labels`` (H_s, W_s) carried onto ``dst``'s pixels: each ``dst`` pixel with depth is
    back-projected, projected into ``src`` (nearest pixel) and takes its label when ``src``'s depth
    there agrees within ``depth_tol`` metres (the same surface, not an occluder).

    Returns:
        (H_d, W_d) int16 labels; IGNORE where ``src`` does not see the pixel's point.
    """
    out = np.full(dst.shape, IGNORE, np.int16)
    pts, pix = backproject(dst.depth, dst.K, dst.T_cw)
    if pts.shape[0] == 0:
        return out
    u, v, z = project(pts, src.K, src.T_cw)
    H, W = src.shape
    with np.errstate(invalid="ignore"):
        c, r = np.rint(u), np.rint(v)
        ok = (c >= 0) & (c < W) & (r >= 0) & (r < H)
    c, r = c[ok].astype(np.intp), r[ok].astype(np.intp)
    ok_idx = np.flatnonzero(ok)
    same = np.abs(src.depth[r, c] - z[ok]) <= depth_tol
    rows, cols = pix[ok_idx[same], 0], pix[ok_idx[same], 1]
    out[rows, cols] = src_labels[r[same], c[same]]
    return out


def view_consistency(frames: Sequence[Frame], num_classes: int, names: Sequence[str], step: int = 1,
                     depth_tol: float = 0.05) -> dict:
    """Agreement of the labels of views ``i`` and ``i + step`` on the pixels that see the same points.

    Args:
        frames: views with ``labels`` and ``gt_labels`` (e.g. :func:`~diffuser_lab.data.predictions.with_predictions`).
        num_classes, names: the taxonomy's class count and names.
        step: distance of the view pairs in the sequence (1 = neighbours).
    Returns:
        ``tc_miou``: mIoU (percent) of view i+step's labels scored against view i's reprojected
        labels (the TC of Liu et al. 2020, pairs accumulated); ``error_agreement``: among the
        co-visible pixels that view i gets wrong, the share that view i+step gets wrong with the
        same class (percent); ``error_overlap``: among them, the share view i+step gets wrong at
        all (percent); ``covisible_pixels``: pixels compared.
    """
    conf = np.zeros((num_classes, num_classes + 1), np.int64)
    wrong_a = same_wrong = wrong_both = covis = 0
    prev = None
    for i in range(len(frames) - step):
        a = prev if prev is not None and step == 1 else frames[i]
        b = frames[i + step]
        prev = b
        la = reproject_labels(a.labels, a, b, depth_tol)
        gt = b.gt_labels
        m = (la != IGNORE) & (gt != IGNORE) & (b.labels != IGNORE)
        covis += int(m.sum())
        conf += confusion_matrix(np.where(m, b.labels, IGNORE), np.where(m, la, IGNORE), num_classes)
        ea = m & (la != gt)
        wrong_a += int(ea.sum())
        same_wrong += int((ea & (b.labels == la)).sum())
        wrong_both += int((ea & (b.labels != gt)).sum())
    tc = scores_from_confusion(conf, tuple(names))["miou"]
    pct = (lambda x: 100.0 * x / wrong_a) if wrong_a else (lambda x: float("nan"))
    return {"tc_miou": tc, "error_agreement": pct(same_wrong), "error_overlap": pct(wrong_both),
            "covisible_pixels": covis}
