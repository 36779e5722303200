"""Compiled passes of GMRES(m) (:mod:`diffuser_lab.backends.krylov`, ``online.solver=gmres``) on
the numba backend's class blocks: products with P on the Jacobi row kernels and threads, the
dot products, the orthogonalisation and the update over rows in fixed chunks (sums add up in the
same order every run)."""
from __future__ import annotations

import numpy as np

from ..krylov import KrylovOps
from . import NB

if NB is not None:
    from numba import njit, prange

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
    def gmres_combine(Z, U, ys, m, parts):
        """Z += Sum_{j < m} ys[j, c] U[j] (ys = y s: the least-squares coefficients times the basis
        scales), clamped at 0."""
        n, c = Z.shape
        step = (n + parts - 1) // parts
        for p in prange(parts):
            for r in range(p * step, min(n, (p + 1) * step)):
                for a in range(c):
                    v = Z[r, a]
                    for j in range(m):
                        v += np.float32(ys[j, a]) * U[j, r, a]
                    Z[r, a] = v if v > np.float32(0.0) else np.float32(0.0)


class NumbaKrylovOps(KrylovOps):
    """GMRES's passes on one (n, W) class block: products on the Jacobi row kernels (``runner``:
    the backend's :class:`~diffuser_lab.backends.numba.jacobi.StepRunner`; ``wneg`` = -P)."""

    NOFLOOR = np.float32(-np.inf)

    def __init__(self, runner, width: int, nbr: np.ndarray, wts: np.ndarray, wneg: np.ndarray, n: int):
        self.runner, self.width, self.nbr, self.wts, self.wneg, self.n = runner, width, nbr, wts, wneg, n
        self.parts = max(1, min(64, n // 2048 + 1))  # fixed row chunks: the same sums every run

    def residual(self, Z, B, out) -> None:
        self.runner.run(self.width, self.nbr, self.wts, Z, out, B - Z, self.NOFLOOR, -1.0, 1)  # P Z + (B - Z)

    def apply(self, X, out) -> None:
        self.runner.run(self.width, self.nbr, self.wneg, X, out, X, self.NOFLOOR, -1.0, 1)  # -P X + X

    def dots(self, U, j):
        dots = np.zeros((self.parts, j + 1, U.shape[2]))
        gmres_dots(U[j + 1], U, j, self.parts, dots)
        return dots.sum(0)

    def orthogonalise(self, U, j, coef):
        sq = np.zeros((self.parts, U.shape[2]))
        gmres_orthogonalise(U, j, coef, self.n, self.parts, sq)
        return sq.sum(0)

    def combine(self, Z, U, ys, m) -> None:
        gmres_combine(Z, U, ys, m, self.parts)
