"""Compiled Eqs. 14-15: the normalised system of a kNN graph's fixed-length rows, as
:func:`diffuser_lab.method.diffusion.normalise` computes it with numpy (same float32 operations,
numpy's pairwise order for the row sums of the pixel mass)."""
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
    def _pixsum_par(mass, lam, out, nparts):
        """out[o] = (mass[o].astype(float32) * lam).sum() as numpy computes it."""
        n, c = mass.shape
        for t in prange(nparts):
            for o in range(t * n // nparts, (t + 1) * n // nparts):
                out[o] = _pairwise_row(mass, o, 0, c, lam)

    @njit(cache=True, parallel=True, boundscheck=False)
    def _scale_rows_par(order, wsum, pixsum, w, floor, tiny, Ps, inv, nparts):
        """Per sorted row s: inv = 1 / (float32(wsum[s]) + pixsum[order[s]]) (0 when that is not
        above tiny), Ps[s] = w[s] * inv with entries below floor set to 0; inv kept per point."""
        n, k = w.shape
        for t in prange(nparts):
            for s in range(t * n // nparts, (t + 1) * n // nparts):
                o = order[s]
                d = np.float32(wsum[s]) + pixsum[o]
                iv = np.float32(1.0) / d if d > tiny else np.float32(0.0)
                inv[o] = iv
                for c in range(k):
                    v = w[s, c] * iv
                    Ps[s, c] = np.float32(0.0) if v < floor else v

    @njit(cache=True, parallel=True, boundscheck=False)
    def _pix_scaled_par(mass, lam, inv, B, nparts):
        """B = (mass.astype(float32) * lam) * inv[:, None]."""
        n, c = mass.shape
        for t in prange(nparts):
            for o in range(t * n // nparts, (t + 1) * n // nparts):
                iv = inv[o]
                for a in range(c):
                    B[o, a] = (np.float32(mass[o, a]) * lam) * iv


def normalise_sorted(order: np.ndarray, sorted_weights: np.ndarray, sorted_row_sums: np.ndarray, mass: np.ndarray,
                     pixel_weight: float, edge_floor: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Eqs. 14-15 for a :class:`~diffuser_lab.method.graph.SortedKnnGraph` in three parallel passes,
    bit for bit the numpy computation of :func:`diffuser_lab.method.diffusion.normalise`.

    Args:
        order: (N,) int64 Morton order; sorted_weights: (N, K) float32; sorted_row_sums: (N,)
            float64; mass: (N, C) pixel mass (caller's order); pixel_weight: lambda;
            edge_floor: transition weights below it become 0.
    Returns:
        (P (N, K) float32 in sorted order, B (N, C) float32 in the caller's order), or None for a
        mass this path does not take (not a 2-D numeric array, or more than 128 classes).
    """
    mass = np.asarray(mass)
    if mass.ndim != 2 or mass.dtype.kind not in "fiu" or mass.shape[0] != order.shape[0] or mass.shape[1] > 128:
        return None
    n = order.shape[0]
    lam = np.float32(pixel_weight)
    parts = _parts(n)
    pixsum = np.empty(n, np.float32)
    _pixsum_par(mass, lam, pixsum, parts)
    Ps = np.empty_like(sorted_weights)
    inv = np.empty(n, np.float32)
    # numpy compares float32 arrays with Python floats in float32
    _scale_rows_par(order, sorted_row_sums, pixsum, sorted_weights, np.float32(edge_floor), np.float32(1e-30), Ps,
                    inv, parts)
    B = np.empty(mass.shape, np.float32)
    _pix_scaled_par(mass, lam, inv, B, parts)
    return Ps, B
