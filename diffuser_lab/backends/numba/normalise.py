"""Compiled Eqs. 14-15: rows of the normalised system of a kNN graph's fixed-length rows, as
:func:`diffuser_lab.backends.normalise.normalise_rows_numpy` computes them (same float32
operations, numpy's pairwise order for the row sums of the pixel mass)."""
from __future__ import annotations

import numpy as np

from . import NB
from . import parts as _parts

if NB is not None:
    from numba import njit, prange

    @njit(cache=True, boundscheck=False)
    def _pairwise_row(mass, o, lo, n, lam):
        """numpy's float32 sum of float32(mass[o, lo:lo + n]) * lam for n <= 128 (blocks of 8;
        numpy halves longer rows recursively, which numba cannot cache)."""
        if n < 8:
            r = np.float32(0.0)
            for c in range(lo, lo + n):
                r += np.float32(mass[o, c]) * lam
            return r
        else:
            r0 = np.float32(mass[o, lo]) * lam
            r1 = np.float32(mass[o, lo + 1]) * lam
            r2 = np.float32(mass[o, lo + 2]) * lam
            r3 = np.float32(mass[o, lo + 3]) * lam
            r4 = np.float32(mass[o, lo + 4]) * lam
            r5 = np.float32(mass[o, lo + 5]) * lam
            r6 = np.float32(mass[o, lo + 6]) * lam
            r7 = np.float32(mass[o, lo + 7]) * lam
            i = 8
            while i < n - n % 8:
                r0 += np.float32(mass[o, lo + i]) * lam
                r1 += np.float32(mass[o, lo + i + 1]) * lam
                r2 += np.float32(mass[o, lo + i + 2]) * lam
                r3 += np.float32(mass[o, lo + i + 3]) * lam
                r4 += np.float32(mass[o, lo + i + 4]) * lam
                r5 += np.float32(mass[o, lo + i + 5]) * lam
                r6 += np.float32(mass[o, lo + i + 6]) * lam
                r7 += np.float32(mass[o, lo + i + 7]) * lam
                i += 8
            res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
            while i < n:
                res += np.float32(mass[o, lo + i]) * lam
                i += 1
            return res

    @njit(cache=True, parallel=True, boundscheck=False)
    def _rows_par(rows, use_rows, order, use_order, w, wsum, mass, lam, gamma, floor, tiny, P, B, nparts):
        """Rows s (``rows``, or all) of Eqs. 14-15: o = order[s] (or s) the row's point in ``mass``;
        d = float32(wsum[s]) + Sum_c float32(mass[o, c]) * lam (numpy's order); inv = 1 / d (0
        when d is not above tiny); P[s] = w[s] * inv, entries below floor set to 0, times gamma;
        B[s] = (float32(mass[o]) * lam) * inv."""
        m = rows.shape[0] if use_rows else w.shape[0]
        k = w.shape[1]
        c = mass.shape[1]
        for t in prange(nparts):
            for r in range(t * m // nparts, (t + 1) * m // nparts):
                s = rows[r] if use_rows else r
                o = order[s] if use_order else s
                d = np.float32(wsum[s]) + _pairwise_row(mass, o, 0, c, lam)
                iv = np.float32(1.0) / d if d > tiny else np.float32(0.0)
                for j in range(k):
                    v = w[s, j] * iv
                    P[s, j] = np.float32(0.0) if v < floor else v * gamma
                for a in range(c):
                    B[s, a] = (np.float32(mass[o, a]) * lam) * iv


def takes(mass: np.ndarray) -> bool:
    """Whether :func:`normalise_rows` takes this pixel mass (a 2-D numeric array of at most 128
    classes: numpy's pairwise sums of longer rows are not reproduced)."""
    return mass.ndim == 2 and mass.dtype.kind in "fiu" and mass.shape[1] <= 128


def normalise_rows(rows, order, weights, row_sums, mass, pixel_weight: float, gamma: float, edge_floor: float,
                   P: np.ndarray, B: np.ndarray) -> None:
    """Eqs. 14-15 in one parallel pass, bit for bit :func:`diffuser_lab.backends.normalise.normalise_rows_numpy`
    (see there for the arguments); ``mass`` as :func:`takes` allows."""
    m = weights.shape[0] if rows is None else rows.shape[0]
    empty = np.zeros(0, np.int64)
    # numpy compares float32 arrays with Python floats in float32
    _rows_par(empty if rows is None else rows, rows is not None, empty if order is None else order,
              order is not None, weights, row_sums, mass, np.float32(pixel_weight), np.float32(gamma),
              np.float32(edge_floor), np.float32(1e-30), P, B, _parts(m))
