"""The fused evidence of one frame (Eqs. 1-2, 11-12 for hard labels) in one compiled pass:
projection with OpenCV pixel centres, image bounds, the depth check and the vote; the numpy
twin is :func:`diffuser_lab.method.evidence.add_frame`'s plain path."""
from __future__ import annotations

import numpy as np

from . import NB

if NB is not None:
    from numba import njit, prange

    @njit(cache=True, boundscheck=False, inline="always")
    def _vote(i, pts, R, t, K, depth, labels, tol, mass, links, seen):
        h, w = depth.shape
        x, y, z = np.float64(pts[i, 0]), np.float64(pts[i, 1]), np.float64(pts[i, 2])
        xc = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]
        yc = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]
        zc = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
        seen[i] = False
        if not zc > 1e-6:
            return
        u = K[0, 0] * (xc / zc) + K[0, 1] * (yc / zc) + K[0, 2]
        v = K[1, 1] * (yc / zc) + K[1, 2]
        col = np.rint(u)
        row = np.rint(v)
        if not (col >= 0 and col < w and row >= 0 and row < h):
            return
        r, c = int(row), int(col)
        d = depth[r, c]
        if not (d > 0 and abs(zc - d) <= tol):
            return
        seen[i] = True
        lab = labels[r, c]
        if lab >= 0:
            mass[i, lab] += 1.0
            links[i] += 1

    @njit(cache=True, parallel=True, boundscheck=False)
    def _evidence_hard(pts, R, t, K, depth, labels, tol, mass, links, seen):
        for i in prange(pts.shape[0]):
            _vote(i, pts, R, t, K, depth, labels, tol, mass, links, seen)

    @njit(cache=True, boundscheck=False)
    def _evidence_hard_serial(pts, R, t, K, depth, labels, tol, mass, links, seen):
        for i in range(pts.shape[0]):
            _vote(i, pts, R, t, K, depth, labels, tol, mass, links, seen)


    @njit(cache=True, boundscheck=False)
    def evidence_hard_frames(pts, Rs, ts, Ks, depth_pool, label_pool, off, hw, which, tol, mass, links):
        """The frames ``which`` (indices into the (F, 3, 3) Rs, (F, 3) ts, (F, 3, 3) Ks, and frame f's
        (H, W) = hw[f] depth and label images at off[f] in the flat float32 / int16 pools), in that
        order, added to the points as :func:`evidence_hard` adds one frame (one thread: a growing
        map's new points are few)."""
        seen = np.empty(pts.shape[0], np.bool_)
        for f in which:
            h, w = hw[f, 0], hw[f, 1]
            depth = depth_pool[off[f]:off[f] + h * w].reshape((h, w))
            lab = label_pool[off[f]:off[f] + h * w].reshape((h, w))
            for i in range(pts.shape[0]):
                _vote(i, pts, Rs[f], ts[f], Ks[f], depth, lab, tol, mass, links, seen)


PARALLEL_ABOVE = 16384
"""Points above which one frame's evidence runs on numba's threads (a parallel launch costs ~50 us:
measured, more than a growing map's few thousand new points take on one thread)."""


def evidence_hard(points, frame_R, frame_t, K, depth, labels, depth_tol, mass, links):
    """Project, depth-check and add one frame's hard labels in one pass; returns (N,) bool seen."""
    seen = np.empty(len(points), np.bool_)
    kernel = _evidence_hard if len(points) > PARALLEL_ABOVE else _evidence_hard_serial
    kernel(points, frame_R, frame_t, K, depth, labels, float(depth_tol), mass, links, seen)
    return seen
