"""Compiled kernels of the online Diffuser (:mod:`diffuser_lab.method.online`): the rows a frame
changed renormalised (Eqs. 14-15) for warm-started steps of the
discounted iteration Z <- gamma P Z + B run by the batch Jacobi's threads
(:class:`~diffuser_lab.backends.numba.jacobi.StepRunner`), and the labels. Their numpy twins are
in :mod:`diffuser_lab.method.online` (same arithmetic, float32; results agree to rounding).

All arrays are in the online map's storage order; ``rows`` are sorted int64 row indices.
"""
from __future__ import annotations

import numpy as np

from . import NB

if NB is not None:
    from numba import njit, prange

    @njit(cache=True, parallel=True, boundscheck=False)
    def renormalise_rows(rows, W, wsum, mass, lam, gamma, edge_floor, slot, P, B, Pneg):
        """Rows ``rows`` of Eqs. 14-15: d_i = Sum_j w_ij + lam Sum_c E_ic; P_ij = gamma w_ij / d_i
        (0 where w_ij / d_i < ``edge_floor``); B[i, slot[c]] = E_ic / d_i (the paper's B divided
        by lam; classes with slot -1 have no evidence anywhere yet); Pneg = -P (what the Jacobi row
        kernel multiplies by to give (I - P) X)."""
        k = W.shape[1]
        c = mass.shape[1]
        for r in prange(rows.shape[0]):
            i = rows[r]
            s = np.float32(0.0)
            for a in range(c):
                s += mass[i, a]
            den = np.float32(wsum[i]) + np.float32(lam) * s
            inv = np.float32(1.0) / den if den > np.float32(1e-30) else np.float32(0.0)
            for j in range(k):
                p = W[i, j] * inv
                v = p * np.float32(gamma) if p >= edge_floor else np.float32(0.0)
                P[i, j] = v
                Pneg[i, j] = -v
            for a in range(c):
                if slot[a] >= 0:
                    B[i, slot[a]] = mass[i, a] * inv

    @njit(cache=True, boundscheck=False, inline="always")
    def _relabel(S, i, na, active, labels):
        """labels[i] = active[argmax_{s < na} S[i, s]] (the first of equal maxima), -1 where the
        row's first na entries are all <= 0; 1 if the label changed, else 0."""
        best = -1
        top = np.float32(0.0)
        for a in range(na):
            v = S[i, a]
            if v > top:
                top = v
                best = a
        lab = active[best] if best >= 0 else -1
        if labels[i] == lab:
            return 0
        labels[i] = lab
        return 1

    @njit(cache=True, boundscheck=False)
    def argmax_rows(S, na, active, labels):
        """:func:`_relabel` for every row; returns how many labels changed."""
        cnt = 0
        for i in range(labels.shape[0]):
            cnt += _relabel(S, i, na, active, labels)
        return cnt

    # -- GMRES(m) on (I - gamma P) Z = B, column by column, rows in fixed chunks (deterministic sums)

    @njit(cache=True, parallel=True, boundscheck=False, fastmath={"contract"})
    def gmres_dots(X, U, j, parts, dots):
        """dots[p, i, c] = Sum over row chunk p of X[:, c] U[i][:, c], for i <= j (float64 sums)."""
        n, c = X.shape
        step = (n + parts - 1) // parts
        for p in prange(parts):
            acc = np.zeros((j + 1, c))
            for r in range(p * step, min(n, (p + 1) * step)):
                for i in range(j + 1):
                    for a in range(c):
                        acc[i, a] += np.float64(X[r, a] * U[i, r, a])
            for i in range(j + 1):
                for a in range(c):
                    dots[p, i, a] = acc[i, a]

    @njit(cache=True, parallel=True, boundscheck=False, fastmath={"contract"})
    def gmres_orthogonalise(U, j, coef, n, parts, sq):
        """U[j+1] -= Sum_{i <= j} coef[i, c] U[i]; sq[p, c] = Sum over chunk p of U[j+1]^2."""
        c = U.shape[2]
        step = (n + parts - 1) // parts
        dst = U[j + 1]
        cf = coef.astype(np.float32)
        for p in prange(parts):
            acc = np.zeros(c)
            for r in range(p * step, min(n, (p + 1) * step)):
                for i in range(j + 1):
                    for a in range(c):
                        dst[r, a] -= cf[i, a] * U[i, r, a]
                for a in range(c):
                    acc[a] += np.float64(dst[r, a]) * dst[r, a]
            for a in range(c):
                sq[p, a] = acc[a]

    @njit(cache=True, parallel=True, boundscheck=False, fastmath={"contract"})
    def gmres_combine(Z, U, ys, m, active, labels, parts):
        """Z += Sum_{j < m} ys[j, c] U[j] (ys = y s: the least-squares coefficients times the basis
        scales), clamped at 0; labels = active[argmax] (-1 where the row is all 0). Returns how many
        labels changed."""
        n = labels.shape[0]
        c = Z.shape[1]
        step = (n + parts - 1) // parts
        changed = np.zeros(parts, np.int64)
        for p in prange(parts):
            cnt = 0
            for r in range(p * step, min(n, (p + 1) * step)):
                for a in range(c):
                    v = Z[r, a]
                    for j in range(m):
                        v += np.float32(ys[j, a]) * U[j, r, a]
                    Z[r, a] = v if v > np.float32(0.0) else np.float32(0.0)
                cnt += _relabel(Z, r, active.shape[0], active, labels)
            changed[p] = cnt
        return changed.sum()
