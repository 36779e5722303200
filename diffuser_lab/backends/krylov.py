"""GMRES(m) on (I - P) Z = B from the current Z, each class column on its own (``online.solver=gmres``).

GMRES minimises the residual over the m-step Krylov space, so it gets closer to the fixed point
in m products with P than m Jacobi steps do (docs/online.md). The basis is stored unnormalised:
v_i = s_i U_i (per column), U_{j+1} = A U_j minus its projections (classical Gram-Schmidt,
float64 sums), so each product is one call of a backend's row kernel. Z is clamped at 0 after
the update. A backend gives the products (:class:`KrylovOps`); the numpy versions of the other
passes are here, the compiled ones in :mod:`diffuser_lab.backends.numba.krylov`.
"""
from __future__ import annotations

import numpy as np


class KrylovOps:
    """The passes of :func:`gmres` on (n, W) float32 blocks; ``residual`` and ``apply`` are the
    backend's products, the rest numpy (a compiled backend overrides them)."""

    def residual(self, Z: np.ndarray, B: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - interface
        """out = B - Z + P Z."""
        raise NotImplementedError

    def apply(self, X: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - interface
        """out = X - P X."""
        raise NotImplementedError

    def dots(self, U: np.ndarray, j: int) -> np.ndarray:
        """(j + 1, W) float64 <U[j + 1], U[i]> per column, i <= j."""
        return np.einsum("rc,irc->ic", U[j + 1], U[: j + 1], dtype=np.float64)

    def orthogonalise(self, U: np.ndarray, j: int, coef: np.ndarray) -> np.ndarray:
        """U[j + 1] -= Sum_{i <= j} coef[i] U[i]; returns (W,) float64 |U[j + 1]|^2 per column."""
        U[j + 1] -= np.einsum("ic,irc->rc", coef.astype(np.float32), U[: j + 1])
        return np.square(U[j + 1], dtype=np.float64).sum(0)

    def combine(self, Z: np.ndarray, U: np.ndarray, ys: np.ndarray, m: int) -> None:
        """Z += Sum_{j < m} ys[j] U[j], clamped at 0."""
        Z += np.einsum("jc,jrc->rc", ys.astype(np.float32), U[:m])
        np.maximum(Z, 0, out=Z)


def gmres(Z: np.ndarray, B: np.ndarray, U: np.ndarray, m: int, ops: KrylovOps) -> tuple[float, float]:
    """GMRES(m) for the columns of the (n, W) block Z in place (B its right-hand side; U a
    (m + 1, n, W) float32 work array). Returns (the largest column residual of the least-squares
    solution, the largest column norm of B): their ratio is the relative residual."""
    W = Z.shape[1]
    s = np.zeros((m + 1, W))
    H = np.zeros((W, m + 1, m))
    ops.residual(Z, B, U[0])
    beta = np.sqrt(np.square(U[0], dtype=np.float64).sum(0))
    s[0] = np.divide(1.0, beta, out=np.zeros(W), where=beta > 0)
    tiny = 1e-7 * beta
    for j in range(m):
        ops.apply(U[j], U[j + 1])
        g = ops.dots(U, j)  # <X, U_i>
        # h_ij = <A v_j, v_i> = s_j s_i <X, U_i>; X -= Sum_i (h_ij s_i / s_j) U_i = Sum_i s_i^2 g_i U_i
        h = s[j] * s[: j + 1] * g
        coef = np.square(s[: j + 1]) * g
        xn = np.sqrt(ops.orthogonalise(U, j, coef))
        hn = s[j] * xn  # |A v_j - projections|
        H[:, : j + 1, j] = h.T
        H[:, j + 1, j] = hn
        s[j + 1] = np.divide(1.0, xn, out=np.zeros(W), where=hn > tiny)
    e1 = np.zeros((W, m + 1))
    e1[:, 0] = beta
    y = (np.linalg.pinv(H) @ e1[:, :, None])[:, :, 0]  # (W, m): least squares, rank-deficient safe
    res = np.linalg.norm(e1 - (H @ y[:, :, None])[:, :, 0], axis=1)
    bn = np.sqrt(np.square(B, dtype=np.float64).sum(0))
    ys = np.ascontiguousarray(y.T * s[:m])  # (m, W): coefficients of the stored basis
    ops.combine(Z, U, ys, m)
    return (float(res.max()) if W else 0.0), (float(bn.max()) if W else 0.0)
