"""Morton (Z-order) codes of points on a lattice over their bounding box, numpy (the compiled
order of many points: :mod:`diffuser_lab.backends.numba.morton`). Sorting points along the curve
puts points near in space near in memory: the kNN graph, the diffusion and a growing map's rows
are kept in that order."""
from __future__ import annotations

import numpy as np


MORTON_BITS = 21
"""Bits per axis of :func:`morton_codes` (3 x 21 = 63 bits in a uint64)."""


def spread_bits(x: np.ndarray) -> np.ndarray:
    """Insert two zero bits between the low 21 bits of ``x`` (uint64)."""
    x = x & np.uint64(0x1FFFFF)
    x = (x | (x << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    x = (x | (x << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    x = (x | (x << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    x = (x | (x << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    x = (x | (x << np.uint64(2))) & np.uint64(0x1249249249249249)
    return x


def quantize(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(N, 3) points -> (N, 3) int64 integer coordinates on a cubic lattice of
    ``step`` metres (2^21 steps span the largest extent), the lattice origin (3,) float64
    and ``step``. Depends only on the set of points, not on their order."""
    p = np.asarray(points, np.float64)
    origin = p.min(0)
    extent = float((p.max(0) - origin).max()) if len(p) else 0.0
    step = extent / (2**MORTON_BITS - 1) if extent > 0 else 1.0
    q = np.floor((p - origin) / step).astype(np.int64)
    np.clip(q, 0, 2**MORTON_BITS - 1, out=q)
    return q, origin, step


def morton_codes(q: np.ndarray) -> np.ndarray:
    """(N, 3) non-negative integer coordinates (< 2^21) -> (N,) uint64 Z-order codes."""
    q = q.astype(np.uint64)
    return spread_bits(q[:, 0]) | (spread_bits(q[:, 1]) << np.uint64(1)) | (spread_bits(q[:, 2]) << np.uint64(2))


def spatial_order(points: np.ndarray) -> np.ndarray:
    """(N,) int64 permutation that sorts (N, 3) points along a Z-order (Morton) curve on a
    2^21-step lattice over their bounding box, so that points near in space are near in memory.
    The order depends only on the set of points (ties, i.e. points within one lattice step of each
    other in every axis, keep their input order)."""
    q, _, _ = quantize(points)
    return np.argsort(morton_codes(q), kind="stable")
