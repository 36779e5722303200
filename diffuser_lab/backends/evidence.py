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
