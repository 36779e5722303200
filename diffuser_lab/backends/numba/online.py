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
    def renormalise_rows(rows, W, wsum, mass, lam, gamma, edge_floor, slot, P, B):
        """Rows ``rows`` of Eqs. 14-15: d_i = Sum_j w_ij + lam Sum_c E_ic; P_ij = gamma w_ij / d_i
        (0 where w_ij / d_i < ``edge_floor``); B[i, slot[c]] = E_ic / d_i (the paper's B divided
        by lam; classes with slot -1 have no evidence anywhere yet)."""
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
                P[i, j] = p * np.float32(gamma) if p >= edge_floor else np.float32(0.0)
            for a in range(c):
                if slot[a] >= 0:
                    B[i, slot[a]] = mass[i, a] * inv

    @njit(cache=True, boundscheck=False)
    def argmax_rows(S, na, active, labels):
        """labels[i] = active[argmax_{s < na} S[i, s]] (the first of equal maxima), -1 where the
        row's first na entries are all <= 0; returns how many labels changed."""
        n = labels.shape[0]
        cnt = 0
        for i in range(n):
            best = -1
            top = np.float32(0.0)
            for a in range(na):
                v = S[i, a]
                if v > top:
                    top = v
                    best = a
            lab = active[best] if best >= 0 else -1
            if labels[i] != lab:
                cnt += 1
                labels[i] = lab
        return cnt
