"""The fused evidence pass of one frame (hard labels, the paper's single pixel), where the compiled
kernel runs (:mod:`diffuser_lab.backends.numba.evidence`); the general vectorised path (any pixel
window, probabilities, and this one without numba) is :func:`diffuser_lab.method.evidence.add_frame`'s."""
from __future__ import annotations

from typing import Optional

import numpy as np

from . import numba as nb
from .numba import evidence as compiled


def hard_votes(points: np.ndarray, T_cw: np.ndarray, K: np.ndarray, depth: np.ndarray, labels: np.ndarray,
               depth_tol: float, mass: np.ndarray, links: np.ndarray) -> Optional[np.ndarray]:
    """Project the (N, 3) world points, depth-check them and add the frame's (H, W) hard labels to
    ``mass`` (N, C) C-contiguous and ``links`` (N,) in one compiled pass; returns the (M,) int64
    sorted points that passed, or None where the compiled kernels are off (the caller's numpy path
    then runs)."""
    if not nb.available() or not mass.flags.c_contiguous:
        return None
    T = np.asarray(T_cw, np.float64)
    seen = compiled.evidence_hard(np.ascontiguousarray(points, np.float32), T[:3, :3].copy(), T[:3, 3].copy(),
                                  np.asarray(K, np.float64), np.ascontiguousarray(depth, np.float32),
                                  np.ascontiguousarray(labels), depth_tol, mass, links)
    return np.flatnonzero(seen)


class KeptVotes:
    """Frames kept for the compiled pass (:func:`hard_votes`) to be added again, several at a time
    in one call (an online map adds the earlier frames' evidence to its new points): each frame's
    pose and intrinsics stacked, its depth and label images in numba's typed lists. Made only
    where the compiled kernels run (:meth:`make`)."""

    def __init__(self):
        from numba import types
        from numba.typed import List

        self.Rt = np.zeros((0, 4, 3))  # per frame R (rows 0-2) and t (row 3)
        self.K = np.zeros((0, 3, 3))
        self.depths = List.empty_list(types.float32[:, ::1])
        self.labels = List.empty_list(types.int16[:, ::1])

    @classmethod
    def make(cls) -> Optional["KeptVotes"]:
        return cls() if nb.available() else None

    def __len__(self) -> int:
        return len(self.depths)

    def add(self, T_cw: np.ndarray, K: np.ndarray, depth: np.ndarray, labels: np.ndarray) -> None:
        T = np.asarray(T_cw, np.float64)
        self.Rt = np.concatenate([self.Rt, np.vstack([T[:3, :3], T[:3, 3]])[None]])
        self.K = np.concatenate([self.K, np.asarray(K, np.float64)[None]])
        self.depths.append(np.ascontiguousarray(depth, np.float32))
        self.labels.append(np.ascontiguousarray(labels, np.int16))

    def drop_oldest(self) -> None:
        self.Rt, self.K = self.Rt[1:], self.K[1:]
        self.depths.pop(0)
        self.labels.pop(0)

    def add_to(self, points: np.ndarray, which: np.ndarray, depth_tol: float, mass: np.ndarray,
               links: np.ndarray) -> None:
        """The kept frames ``which`` (int64 indices, in that order) added to the (N, 3) points'
        ``mass`` (N, C) C-contiguous and ``links`` (N,), as :func:`hard_votes` adds each."""
        if len(which):
            compiled.evidence_hard_frames(np.ascontiguousarray(points, np.float32), np.ascontiguousarray(self.Rt[:, :3]),
                                          np.ascontiguousarray(self.Rt[:, 3]), self.K, self.depths, self.labels,
                                          np.asarray(which, np.int64), float(depth_tol), mass, links)
