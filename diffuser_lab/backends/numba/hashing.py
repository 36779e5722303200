"""Compiled (numba) hash tables and world-anchored integer cell coordinates, shared by the voxel
map (``voxel_map.py``) and the growing map's grid (``growing.py``).

Hash tables: open addressing with linear probing on non-negative int64 keys (-1 = empty slot),
Fibonacci hashing, at most half full (:class:`HashTable` grows them first, :func:`rehash`).
"""
from __future__ import annotations

import numpy as np

from . import NB

OFF = 1 << 20
"""Offset of signed cell / voxel coordinates into 21 unsigned bits."""

if NB is not None:
    from numba import njit

    @njit(cache=True, boundscheck=False, inline="always")
    def _slot(key, bits):
        return np.int64((np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(64 - bits))

    @njit(cache=True, boundscheck=False, inline="always")
    def find(hk, bits, key):
        """Slot of ``key`` or of the empty slot where it would go."""
        mask = (np.int64(1) << bits) - 1
        s = _slot(key, bits)
        while hk[s] != key and hk[s] != -1:
            s = (s + 1) & mask
        return s

    @njit(cache=True, boundscheck=False)
    def rehash(hk, hv, nk, nv, bits):
        """Copy the entries of table (hk, hv) into the empty table (nk, nv) of 2**bits slots."""
        for s in range(hk.shape[0]):
            if hk[s] != -1:
                t = find(nk, bits, hk[s])
                nk[t] = hk[s]
                nv[t] = hv[s]

    @njit(cache=True, boundscheck=False, inline="always")
    def coord(v, size):
        """Cell coordinate ``floor(v / size)`` of one coordinate, offset by :data:`OFF` (clamped to 21 bits)."""
        a = np.floor(np.float64(v) / size)
        a = min(max(a, -float(OFF)), float(OFF - 1))  # NaN -> -OFF (np.clip's NaN stays; never here)
        return np.int64(a) + OFF

    @njit(cache=True, boundscheck=False, inline="always")
    def cell_key(cx, cy, cz):
        """Hash key of a cell from its three offset coordinates (21 bits each)."""
        return (cx << 42) | (cy << 21) | cz


class HashTable:
    """Open-addressing int64 -> int64 hash table, kept at most half full.

    Attributes:
        keys, vals: (2**bits,) int64 slots (key -1: empty); used: keys stored.
    """

    def __init__(self, bits: int = 12):
        self.bits = bits
        self.keys = np.full(1 << bits, -1, np.int64)
        self.vals = np.empty(1 << bits, np.int64)
        self.used = 0

    def reserve(self, extra: int) -> None:
        """Room for ``extra`` more keys."""
        need = 2 * (self.used + extra)
        if need <= self.keys.shape[0]:
            return
        bits = self.bits
        while (1 << bits) < need:
            bits += 1
        nk = np.full(1 << bits, -1, np.int64)
        nv = np.empty(1 << bits, np.int64)
        rehash(self.keys, self.vals, nk, nv, bits)
        self.keys, self.vals, self.bits = nk, nv, bits
