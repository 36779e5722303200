"""Compiled (numba) exact K-nearest search by rings of grid cells, the one candidate search of the
batch grid kNN (``grid_knn.py``, a dense grid of cells in x-major order) and of the growing map's
grid (``growing.py``, cells numbered in a hash table): rings of cells around a point's cell are
scanned, the K best candidates kept by (squared distance, index), until the K-th distance lies
within the radius the rings are sure to cover; a cell entirely beyond the current K-th distance
is skipped. Squared distances are float64 from the coordinates the grid stores.
"""
from __future__ import annotations

import numpy as np

from . import NB

PRUNE = 1.0 - 1e-12
"""A cell is skipped when its lower bound of squared distance, times this (rounding: the bound's
own error is ~1e-15 relative), is above the current K-th: skipping never depends on a last bit."""

if NB is not None:
    from numba import njit

    from .hashing import cell_key, find

    @njit(cache=True, boundscheck=False, inline="always")
    def push(bd, bj, cnt, k, d, j):
        """Insert (d, j) into the ascending K-buffer bd/bj holding cnt entries, ordered by (d, j);
        returns the new cnt."""
        if cnt == k:
            if d > bd[k - 1] or (d == bd[k - 1] and j > bj[k - 1]):
                return cnt
            p = k - 1
        else:
            p = cnt
            cnt += 1
        while p > 0 and (bd[p - 1] > d or (bd[p - 1] == d and bj[p - 1] > j)):
            bd[p] = bd[p - 1]
            bj[p] = bj[p - 1]
            p -= 1
        bd[p] = d
        bj[p] = j
        return cnt

    @njit(cache=True, boundscheck=False, inline="always")
    def _gap(d, lo, hi, h):
        """Lower bound of the distance along one axis to the cell d cells away from the point's
        (lo, hi: the point's distance to its own cell's lower / upper face)."""
        if d == 0:
            return 0.0
        g = (-d - 1) * h + lo if d < 0 else (d - 1) * h + hi
        return g if g > 0.0 else 0.0

    @njit(cache=True, boundscheck=False, inline="always")
    def _scan(i, px, py, pz, cid, g2, cs, ce, X, Y, Z, J, k, bd, bj, m):
        """The points of cell cid (none if cid < 0) into the K-buffer, unless the cell lies beyond
        the current K-th distance (g2: a lower bound of its squared distance); returns the count."""
        if cid < 0 or cs[cid] == ce[cid] or (m == k and g2 * PRUNE > bd[k - 1]):
            return m
        for a in range(cs[cid], ce[cid]):
            j = J[a]
            if j == i:
                continue
            ex = X[a] - px
            ey = Y[a] - py
            ez = Z[a] - pz
            d2 = ex * ex + ey * ey + ez * ez
            if m < k or d2 <= bd[k - 1]:
                m = push(bd, bj, m, k, d2, j)
        return m

    @njit(cache=True, boundscheck=False, inline="always")
    def _cell(ix, iy, iz, dims, hk, hv, bits):
        """Index of cell (ix, iy, iz): x-major in the dense grid of dims cells when the table hk
        is empty, else its value in the hash table (hk, hv); -1 if it holds no points."""
        if hk.shape[0] == 0:
            return (ix * dims[1] + iy) * dims[2] + iz
        s = find(hk, bits, cell_key(ix, iy, iz))
        return hv[s] if hk[s] != -1 else -1

    @njit(cache=True, boundscheck=False)
    def ring_knn(i, px, py, pz, c, flo, fhi, h, cmin, cmax, dims, hk, hv, bits, cs, ce, X, Y, Z, J, k, bd, bj):
        """The k nearest of point i at (px, py, pz) (float64; itself excluded, exact ties by
        index) into bd/bj (k,), ascending by (d2, index).

        Args:
            c: (3,) the point's cell; flo/fhi: (3,) tuples, lower bounds of the point's distance
                to its cell's lower / upper face along each axis (may be negative); h: the cell
                side (metres); cmin/cmax: (3,) bounds of the cells' coordinates; dims, hk, hv,
                bits: cell lookup (:func:`_cell`); cs/ce: each cell's points are X/Y/Z/J[cs:ce].
        Returns:
            the count found: k unless fewer points exist (bd/bj padded with inf / i).
        """
        cx, cy, cz = c[0], c[1], c[2]
        face = min(min(flo[0], fhi[0]), min(min(flo[1], fhi[1]), min(flo[2], fhi[2])))
        rmax = max(max(cx - cmin[0], cmax[0] - cx), max(max(cy - cmin[1], cmax[1] - cy),
                                                           max(cz - cmin[2], cmax[2] - cz)))
        m = 0
        r = 0
        while True:  # the shell of ring r: the cells whose largest offset is r
            for ix in range(max(cx - r, cmin[0]), min(cx + r, cmax[0]) + 1):
                gx = _gap(ix - cx, flo[0], fhi[0], h)
                for iy in range(max(cy - r, cmin[1]), min(cy + r, cmax[1]) + 1):
                    gy = _gap(iy - cy, flo[1], fhi[1], h)
                    gxy = gx * gx + gy * gy
                    if abs(ix - cx) == r or abs(iy - cy) == r:
                        for iz in range(max(cz - r, cmin[2]), min(cz + r, cmax[2]) + 1):
                            gz = _gap(iz - cz, flo[2], fhi[2], h)
                            m = _scan(i, px, py, pz, _cell(ix, iy, iz, dims, hk, hv, bits), gxy + gz * gz, cs, ce,
                                      X, Y, Z, J, k, bd, bj, m)
                    else:  # inside the shell's x-y square: its two ends along z
                        if cz - r >= cmin[2]:
                            gz = _gap(-r, flo[2], fhi[2], h)
                            m = _scan(i, px, py, pz, _cell(ix, iy, cz - r, dims, hk, hv, bits), gxy + gz * gz, cs,
                                      ce, X, Y, Z, J, k, bd, bj, m)
                        if cz + r <= cmax[2]:
                            gz = _gap(r, flo[2], fhi[2], h)
                            m = _scan(i, px, py, pz, _cell(ix, iy, cz + r, dims, hk, hv, bits), gxy + gz * gz, cs,
                                      ce, X, Y, Z, J, k, bd, bj, m)
            bound = r * h + face  # no point outside the rings so far is nearer
            if (m == k and bound > 0 and bd[k - 1] < bound * bound) or r >= rmax:
                break
            r += 1
        for e in range(m, k):
            bd[e] = np.inf
            bj[e] = i
        return m
