"""Compiled (numba) Eq. 4 edge weights, w_ij = exp(-|x_i - x_j|^2 / (2 sigma_d^2) - |n_i - n_j|^2 / (2 sigma_s^2)):
every row of the batch graph (:func:`edge_weights`, from the Morton-sorted points) and given rows
of the growing map's graph (:func:`row_weights`, from their squared distances). Both take exp
from :func:`exp_split`, so the growing graph's weights are bit for bit the batch graph's."""
from __future__ import annotations

import numpy as np

from . import NB, n_threads
from . import parts as _parts

if NB is not None:
    from numba import njit, prange

    # exp(x) for x <= 0 to ~1e-14 relative, written without branches or calls so that it
    # vectorises (numba's np.exp is a scalar libm call; no SVML here): x = n ln2 + r with
    # |r| <= ln2/2, a degree-12 Taylor polynomial for exp(r), 2^n from its bits (a table would
    # need gathers, which LLVM does not vectorise for this CPU).
    _LN2_HI = 0.6931471803691238
    _LN2_LO = 1.9082149292705877e-10
    _INV_LN2 = 1.4426950408889634

    @njit(cache=True, boundscheck=False, inline="always")
    def exp_split(x):
        """exp(max(x, -150)) for x <= 0 as (m, bits): m in [0.7, 1.5] and the int64 bits of the
        float64 2^n, exp = m * 2^n (exp(-150) is 0 in float32). Kept apart so that a loop of them
        vectorises: callers store the bits in an int64 array viewed as float64."""
        x = max(x, -150.0)
        nf = np.rint(x * _INV_LN2)
        r = (x - nf * _LN2_HI) - nf * _LN2_LO
        p = 1.0 / 479001600.0
        p = p * r + 1.0 / 39916800.0
        p = p * r + 1.0 / 3628800.0
        p = p * r + 1.0 / 362880.0
        p = p * r + 1.0 / 40320.0
        p = p * r + 1.0 / 5040.0
        p = p * r + 1.0 / 720.0
        p = p * r + 1.0 / 120.0
        p = p * r + 1.0 / 24.0
        p = p * r + 1.0 / 6.0
        p = p * r + 0.5
        p = p * r + 1.0
        return p * r + 1.0, (np.int64(nf) + 1023) << 52

    @njit(cache=True, boundscheck=False)
    def _weights_rows(P4, idx, N4, use_n, invariant, a_d, a_s, out_w, out_sum, lo, hi):
        """Eq. 4 for rows lo..hi-1: out_w = exp(-d2 a_d - |n_i - n_j|^2 a_s) (float32; d2 and the
        normal term in float64, as the numpy path), out_sum their float64 sums."""
        k = idx.shape[1]
        rows = 64  # exponents of 64 rows at a time: long vectorised loops for exp
        ex = np.empty(rows * k)
        pw = np.empty(rows * k, np.int64)
        pwf = pw.view(np.float64)
        wf = out_w.reshape(-1)
        for r0 in range(lo, hi, rows):
            r1 = min(r0 + rows, hi)
            for i in range(r0, r1):
                e0 = (i - r0) * k
                px, py, pz = P4[i, 0], P4[i, 1], P4[i, 2]
                if use_n:
                    n0, n1, n2 = N4[i, 0], N4[i, 1], N4[i, 2]
                    for s in range(k):
                        j = idx[i, s]
                        dx = P4[j, 0] - px
                        dy = P4[j, 1] - py
                        dz = P4[j, 2] - pz
                        dot = n0 * N4[j, 0] + n1 * N4[j, 1] + n2 * N4[j, 2]
                        if invariant:
                            dot = abs(dot)
                        t = 2.0 - 2.0 * dot
                        t = t if t > 0.0 else 0.0
                        ex[e0 + s] = -(dx * dx + dy * dy + dz * dz) * a_d - t * a_s
                else:
                    for s in range(k):
                        j = idx[i, s]
                        dx = P4[j, 0] - px
                        dy = P4[j, 1] - py
                        dz = P4[j, 2] - pz
                        ex[e0 + s] = -(dx * dx + dy * dy + dz * dz) * a_d
            ne = (r1 - r0) * k
            for e in range(ne):
                ex[e], pw[e] = exp_split(ex[e])
            base = r0 * k
            for e in range(ne):
                wf[base + e] = np.float32(ex[e] * pwf[e])
            for i in range(r0, r1):
                acc = 0.0
                for s in range(k):
                    acc += np.float64(out_w[i, s])
                out_sum[i] = acc

    @njit(cache=True, parallel=True, boundscheck=False)
    def _weights_par(P4, idx, N4, use_n, invariant, a_d, a_s, out_w, out_sum, nparts):
        n = idx.shape[0]
        for t in prange(nparts):
            _weights_rows(P4, idx, N4, use_n, invariant, a_d, a_s, out_w, out_sum,
                          t * n // nparts, (t + 1) * n // nparts)

    @njit(cache=True, parallel=True, boundscheck=False)
    def _row_weights_par(rows, nbr, d2, N, use_n, invariant, a_d, a_s, w, wsum, nparts):
        """Eq. 4 for the given rows (in nparts parallel chunks): w = exp(-d2 a_d - |n_i - n_j|^2 a_s)
        (float64, stored float32; padded entries have d2 = inf, so weight 0), wsum the float64 row sums."""
        k = nbr.shape[1]
        nr = rows.shape[0]
        for t in prange(nparts):
            ex = np.empty(k)
            pw = np.empty(k, np.int64)
            pwf = pw.view(np.float64)
            for q in range(t * nr // nparts, (t + 1) * nr // nparts):
                i = rows[q]
                if use_n:
                    n0 = np.float64(N[i, 0])
                    n1 = np.float64(N[i, 1])
                    n2 = np.float64(N[i, 2])
                    for e in range(k):
                        j = nbr[i, e]
                        dot = n0 * np.float64(N[j, 0]) + n1 * np.float64(N[j, 1]) + n2 * np.float64(N[j, 2])
                        if invariant:
                            dot = abs(dot)
                        tt = 2.0 - 2.0 * dot
                        ex[e] = -d2[i, e] * a_d - (tt if tt > 0.0 else 0.0) * a_s
                else:
                    for e in range(k):
                        ex[e] = -d2[i, e] * a_d
                for e in range(k):
                    ex[e], pw[e] = exp_split(ex[e])
                acc = 0.0
                for e in range(k):
                    v = np.float32(ex[e] * pwf[e])
                    w[i, e] = v
                    acc += np.float64(v)
                wsum[i] = acc


def edge_weights(P4: np.ndarray, idx: np.ndarray, N4: np.ndarray | None, invariant: bool,
                 sigma_d: float, sigma_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 4 weights (N, K) float32 and their row sums (N,) float64.

    Args:
        P4: (N, 4) float64 points (x, y, z, 0), metres; idx: (N, K) int32 neighbours (rows of
            P4); N4: (N, 4) float64 unit normals likewise, or None; sigma_d: metres; sigma_s.
    """
    n, k = idx.shape
    out_w = np.empty((n, k), np.float32)
    out_sum = np.empty(n, np.float64)
    use_n = N4 is not None
    nrm = N4 if use_n else np.zeros((1, 4))
    # unsigned indices: no wrap-around handling of negative ones in the gathers
    _weights_par(P4, idx.view(np.uint32), nrm, use_n, invariant, 0.5 / sigma_d**2, 0.5 / sigma_s**2, out_w,
                 out_sum, _parts(n))
    return out_w, out_sum


def row_weights(rows: np.ndarray, nbr: np.ndarray, d2: np.ndarray, normals: np.ndarray | None, invariant: bool,
                sigma_d: float, sigma_s: float, w: np.ndarray, wsum: np.ndarray) -> None:
    """Eq. 4 for the given rows of a graph stored by rows, in place.

    Args:
        rows: (r,) int64; nbr: (n, K) int32 neighbours; d2: (n, K) float64 their squared distances,
            m^2 (inf: a padded entry, weight 0); normals: (n, 3) float32 unit normals or None;
            sigma_d: metres; sigma_s; w: (n, K) float32 and wsum: (n,) float64, written at ``rows``.
    """
    parts = max(1, min(n_threads() * 8, rows.size // 256 + 1))
    use_n = normals is not None
    _row_weights_par(rows, nbr, d2, normals if use_n else np.zeros((1, 3), np.float32), use_n, invariant,
                     0.5 / sigma_d**2, 0.5 / sigma_s**2, w, wsum, parts)
