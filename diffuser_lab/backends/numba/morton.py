"""Compiled (numba) Morton (Z-order) of a cloud: the lattice of
:func:`~diffuser_lab.backends.morton.quantize` over the points' bounding box, the codes of
:func:`~diffuser_lab.backends.morton.morton_codes` and their stable argsort, in parallel chunks.
:func:`lattice` and :func:`code3` serve the grid kNN (``grid_knn.py``) and the voxel keys
(``voxel_map.py``) too."""
from __future__ import annotations

import numpy as np

from ..morton import MORTON_BITS, spread_bits

from . import NB
from . import parts as _parts

if NB is not None:
    from numba import njit, prange

    _QMAX = 2**MORTON_BITS - 1

    # the numpy function compiles as is for one uint64
    _spread = njit(cache=True, boundscheck=False, inline="always")(spread_bits)

    @njit(cache=True, boundscheck=False, inline="always")
    def code3(x, y, z):
        """Morton code (uint64) of three non-negative integer coordinates below 2^21."""
        return _spread(np.uint64(x)) | (_spread(np.uint64(y)) << np.uint64(1)) | (_spread(np.uint64(z)) << np.uint64(2))

    @njit(cache=True, boundscheck=False, inline="always")
    def lattice(v, o, step):
        """Lattice coordinate of one coordinate, as :func:`~diffuser_lab.backends.morton.quantize` computes it."""
        a = np.floor((np.float64(v) - o) / step)
        if not a > 0.0:  # NaN too: never an index out of the grid
            a = 0.0
        return np.int64(min(a, np.float64(_QMAX)))

    @njit(cache=True, boundscheck=False)
    def _bbox(points):
        """(3,) float64 lower and upper corners of the (N, 3) points."""
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        for i in range(points.shape[0]):
            for a in range(3):
                v = np.float64(points[i, a])
                lo[a] = min(lo[a], v)
                hi[a] = max(hi[a], v)
        return lo, hi

    @njit(cache=True, parallel=True, boundscheck=False)
    def _bbox_par(points, nparts):
        """:func:`_bbox` in nparts parallel chunks."""
        n = points.shape[0]
        lo = np.full((nparts, 3), np.inf)
        hi = np.full((nparts, 3), -np.inf)
        for t in prange(nparts):
            for i in range(t * n // nparts, (t + 1) * n // nparts):
                for a in range(3):
                    v = np.float64(points[i, a])
                    lo[t, a] = min(lo[t, a], v)
                    hi[t, a] = max(hi[t, a], v)
        out_lo = np.empty(3)
        out_hi = np.empty(3)
        for a in range(3):
            out_lo[a] = lo[:, a].min()
            out_hi[a] = hi[:, a].max()
        return out_lo, out_hi

    @njit(cache=True, parallel=True, boundscheck=False)
    def _morton_par(points, origin, step, q, out, nparts):
        """Lattice coordinates q (N, 3) int32 and Morton codes (N,) uint64 of the points."""
        n = points.shape[0]
        for t in prange(nparts):
            for i in range(t * n // nparts, (t + 1) * n // nparts):
                qx = lattice(points[i, 0], origin[0], step)
                qy = lattice(points[i, 1], origin[1], step)
                qz = lattice(points[i, 2], origin[2], step)
                q[i, 0] = qx
                q[i, 1] = qy
                q[i, 2] = qz
                out[i] = code3(qx, qy, qz)


def morton_order(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray]:
    """:func:`~diffuser_lab.backends.morton.quantize` + Morton codes + stable argsort, compiled.

    Args:
        points: (N, 3) float32 world points, metres (C-contiguous).
    Returns:
        order (N,) int64, equal to ``argsort(morton_codes(quantize(points)[0]), kind="stable")``;
        the lattice origin (3,) float64 and step (metres); qmax (3,) int64 the largest lattice
        coordinate per axis; q (N, 3) int32 the lattice coordinates (``quantize(points)[0]``).
    """
    n = points.shape[0]
    lo, hi = _bbox_par(points, _parts(n)) if n > 100_000 else _bbox(points)  # a launch costs ~0.2 ms
    extent = float((hi - lo).max()) if n else 0.0
    step = extent / (2**MORTON_BITS - 1) if extent > 0 else 1.0
    codes = np.empty(n, np.uint64)
    q = np.empty((n, 3), np.int32)
    _morton_par(points, lo, step, q, codes, _parts(n))
    qmax = np.clip(np.floor((hi - lo) / step), 0, 2**MORTON_BITS - 1).astype(np.int64)
    return np.argsort(codes, kind="stable"), lo, step, qmax, q
