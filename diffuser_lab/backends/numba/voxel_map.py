"""Compiled (numba) index of :class:`~diffuser_lab.data.voxel_map.VoxelMap`: the occupied voxels'
Morton keys in a hash table (:mod:`.hashing`), a frame merged in one pass over its points."""
from __future__ import annotations

import numpy as np

from . import NB
from .hashing import HashTable

if NB is not None:
    from numba import njit

    from .hashing import coord, find
    from .morton import code3

    @njit(cache=True, boundscheck=False, inline="always")
    def _key(points, i, size):
        """Morton key (int64) of the voxel of point i."""
        return np.int64(code3(coord(points[i, 0], size), coord(points[i, 1], size), coord(points[i, 2], size)))

    @njit(cache=True, boundscheck=False)
    def voxel_insert(points, normals, use_n, size, hk, hv, bits, n_map, keys, slots, sums, nsums, counts, first):
        """One frame into the voxel map: points in occupied voxels (value < n_map) are dropped;
        the others are summed per new voxel, numbered n_map + t in order of first appearance.

        Returns t, the number of new voxels: keys[:t] their Morton keys, slots[:t] their table
        slots, sums/nsums[:t] (float64) sums of points / normals, counts[:t], first[:t] the
        index of their first point."""
        t = 0
        last = np.int64(-1)
        s = 0
        for i in range(points.shape[0]):
            key = _key(points, i, size)
            if key != last:  # neighbouring pixels mostly share a voxel: no probe
                s = find(hk, bits, key)
                last = key
            if hk[s] == -1:
                hk[s] = key
                hv[s] = n_map + t
                keys[t] = key
                slots[t] = s
                first[t] = i
                counts[t] = 0
                for a in range(3):
                    sums[t, a] = 0.0
                    nsums[t, a] = 0.0
                t += 1
            v = hv[s] - n_map
            if v < 0:
                continue
            counts[v] += 1
            for a in range(3):
                sums[v, a] += np.float64(points[i, a])
            if use_n:
                for a in range(3):
                    nsums[v, a] += np.float64(normals[i, a])
        return t

    @njit(cache=True, boundscheck=False)
    def voxel_occupied(points, size, hk, bits, out):
        """out[i]: point i's voxel is in the table (a map point holds it)."""
        last = np.int64(-1)
        hit = False
        for i in range(points.shape[0]):
            key = _key(points, i, size)
            if key != last:
                hit = hk[find(hk, bits, key)] == key
                last = key
            out[i] = hit


class HashVoxels:
    """The occupied voxels of a map as a hash table of their Morton keys (values: map point index)."""

    compiled = True

    def __init__(self, voxel_size: float):
        self.voxel_size = voxel_size
        self._table = HashTable()

    def occupied(self, points: np.ndarray) -> np.ndarray:
        """(M,) bool: the voxel of each of the (M, 3) float32 points is occupied."""
        out = np.empty(points.shape[0], np.bool_)
        voxel_occupied(points, self.voxel_size, self._table.keys, self._table.bits, out)
        return out

    def insert(self, points: np.ndarray, normals: np.ndarray | None, n_map: int):
        """Merge one frame's (M, 3) float32 points (and normals or None) into a map of ``n_map`` points.

        Returns:
            per new voxel, in Morton order of their keys: sums (t, 3) float64 of its points, nsums
            (t, 3) float64 of their normals (None without normals), counts (t,) int64 and first
            (t,) int64 the index of its first point.
        """
        tb = self._table
        m = points.shape[0]
        use_n = normals is not None
        tb.reserve(m)
        keys = np.empty(m, np.int64)
        slots = np.empty(m, np.int64)
        sums = np.empty((m, 3))
        nsums = np.empty((m, 3))
        counts = np.empty(m, np.int64)
        first = np.empty(m, np.int64)
        t = voxel_insert(points, normals if use_n else points, use_n, self.voxel_size, tb.keys, tb.vals, tb.bits,
                         n_map, keys, slots, sums, nsums, counts, first)
        order = np.argsort(keys[:t], kind="stable")  # keys are unique
        tb.vals[slots[:t][order]] = n_map + np.arange(t)
        tb.used += t
        return sums[order], nsums[order] if use_n else None, counts[order], first[order]
