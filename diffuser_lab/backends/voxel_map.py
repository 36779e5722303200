"""The voxel map's index (:class:`~diffuser_lab.data.voxel_map.VoxelMap`): which voxels hold a map
point, and one frame's points summed per new voxel. Compiled (a hash table,
:class:`diffuser_lab.backends.numba.voxel_map.HashVoxels`) or the numpy twin
:class:`SortedVoxels` (sorted keys); :func:`voxel_index` picks one when a map is made. Both give
the same new voxels in the same order with the same float64 sums.
"""
from __future__ import annotations

import numpy as np

from .morton import spread_bits

from . import numba as nb
from .numba.hashing import OFF
from .numba.voxel_map import HashVoxels


def voxel_keys(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """(M, 3) world points -> (M,) int64 Morton codes of their voxels' integer coordinates
    ``floor(x / voxel_size)`` (offset by 2^20, so +-2^20 voxels per axis around the world origin)."""
    q = np.floor(np.asarray(points, np.float64) / voxel_size)
    q = (np.clip(q, -OFF, OFF - 1) + OFF).astype(np.uint64)
    code = spread_bits(q[:, 0]) | (spread_bits(q[:, 1]) << np.uint64(1)) | (spread_bits(q[:, 2]) << np.uint64(2))
    return code.astype(np.int64)


class SortedVoxels:
    """The occupied voxels of a map as their sorted keys (:func:`voxel_keys`)."""

    compiled = False

    def __init__(self, voxel_size: float):
        self.voxel_size = voxel_size
        self._sorted = np.empty(0, np.int64)  # occupied voxels' keys, ascending

    def occupied(self, points: np.ndarray) -> np.ndarray:
        """(M,) bool: the voxel of each of the (M, 3) float32 points is occupied (a map holding
        at least one point)."""
        keys = voxel_keys(points, self.voxel_size)
        pos = np.minimum(np.searchsorted(self._sorted, keys), self._sorted.shape[0] - 1)
        return self._sorted[pos] == keys

    def insert(self, points: np.ndarray, normals: np.ndarray | None, n_map: int):
        """As :meth:`~diffuser_lab.backends.numba.voxel_map.HashVoxels.insert`."""
        keys = voxel_keys(points, self.voxel_size)
        uk, first, inv, counts = np.unique(keys, return_index=True, return_inverse=True, return_counts=True)
        inv = inv.ravel()
        pos = np.searchsorted(self._sorted, uk)
        hit = np.zeros(uk.shape, bool)
        inside = pos < self._sorted.shape[0]
        hit[inside] = self._sorted[pos[inside]] == uk[inside]
        new = ~hit
        # per-voxel sums in input order (bincount adds sequentially, like the compiled loop)
        p64 = points.astype(np.float64)
        sums = np.stack([np.bincount(inv, p64[:, a], uk.shape[0]) for a in range(3)], 1)[new]
        nsums = None
        if normals is not None:
            n64 = normals.astype(np.float64)
            nsums = np.stack([np.bincount(inv, n64[:, a], uk.shape[0]) for a in range(3)], 1)[new]
        self._sorted = np.insert(self._sorted, pos[new], uk[new])
        return sums, nsums, counts[new], first[new]


def voxel_index(voxel_size: float) -> HashVoxels | SortedVoxels:
    """The index of a new map: compiled when the kernels are used
    (:func:`diffuser_lab.backends.numba.available`), else numpy."""
    return HashVoxels(voxel_size) if nb.available() else SortedVoxels(voxel_size)
