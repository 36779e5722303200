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
    pose and intrinsics stacked, its depth and label images in two flat pools (numba's typed lists
    cost seconds of compiling on first use). The oldest frame goes first (:meth:`drop_oldest`); the
    pools are compacted when half of them is dead. Made only where the compiled kernels run (:meth:`make`)."""

    def __init__(self):
        self.Rt = np.zeros((0, 4, 3))  # per frame R (rows 0-2) and t (row 3)
        self.K = np.zeros((0, 3, 3))
        self.off = np.zeros(0, np.int64)  # where each frame's pixels start in the pools
        self.hw = np.zeros((0, 2), np.int64)
        self._depth = np.zeros(0, np.float32)
        self._labels = np.zeros(0, np.int16)
        self._end = 0  # pool entries in use (the dead ones included)
        self._dead = 0

    @classmethod
    def make(cls) -> Optional["KeptVotes"]:
        return cls() if nb.available() else None

    def __len__(self) -> int:
        return self.off.size

    def add(self, T_cw: np.ndarray, K: np.ndarray, depth: np.ndarray, labels: np.ndarray) -> None:
        T = np.asarray(T_cw, np.float64)
        h, w = depth.shape
        if self._end + h * w > self._depth.size:
            self._grow(h * w)
        self._depth[self._end : self._end + h * w] = depth.ravel()
        self._labels[self._end : self._end + h * w] = labels.ravel()
        self.Rt = np.concatenate([self.Rt, np.vstack([T[:3, :3], T[:3, 3]])[None]])
        self.K = np.concatenate([self.K, np.asarray(K, np.float64)[None]])
        self.off = np.r_[self.off, self._end]
        self.hw = np.concatenate([self.hw, [[h, w]]])
        self._end += h * w

    def _grow(self, need: int) -> None:
        """Room for ``need`` more pixels: the live frames compacted, the pools doubled if still short."""
        live = self.hw.prod(1)
        size = int(live.sum())
        cap = max(self._depth.size, 1024)
        while size + need > cap // 2 if self._dead == 0 else size + need > cap:
            cap *= 2
        depth, labels = np.empty(cap, np.float32), np.empty(cap, np.int16)
        pos = 0
        for f in range(self.off.size):
            o, n = self.off[f], live[f]
            depth[pos : pos + n] = self._depth[o : o + n]
            labels[pos : pos + n] = self._labels[o : o + n]
            self.off[f] = pos
            pos += n
        self._depth, self._labels, self._end, self._dead = depth, labels, pos, 0

    def drop_oldest(self) -> None:
        self._dead += int(self.hw[0].prod())
        self.Rt, self.K, self.off, self.hw = self.Rt[1:], self.K[1:], self.off[1:], self.hw[1:]

    def add_to(self, points: np.ndarray, which: np.ndarray, depth_tol: float, mass: np.ndarray,
               links: np.ndarray) -> None:
        """The kept frames ``which`` (int64 indices, in that order) added to the (N, 3) points'
        ``mass`` (N, C) C-contiguous and ``links`` (N,), as :func:`hard_votes` adds each."""
        if len(which):
            compiled.evidence_hard_frames(np.ascontiguousarray(points, np.float32), np.ascontiguousarray(self.Rt[:, :3]),
                                          np.ascontiguousarray(self.Rt[:, 3]), self.K, self._depth, self._labels,
                                          self.off, self.hw, np.asarray(which, np.int64), float(depth_tol), mass,
                                          links)
