"""The plain numpy/scipy Jacobi backend: one CSR product per step (``solver.backend=scipy``, and
what ``auto`` uses without numba or with ``DIFFUSER_LAB_NUMBA=0``)."""
from __future__ import annotations

from typing import Optional

import numpy as np
import scipy.sparse as sp

from .base import IterationInputs, JacobiBackend
from .krylov import KrylovOps, gmres


class ScipyJacobi(JacobiBackend):
    name = "scipy"

    def setup(self, inputs: IterationInputs) -> None:
        super().setup(inputs)
        n = inputs.shape[0]
        Pm = sp.csr_matrix((inputs.data, inputs.indices, inputs.indptr), shape=(n, n), copy=True)  # never alias
        Pm.eliminate_zeros()
        self.P = Pm
        self.B = np.ascontiguousarray(inputs.B[:, inputs.active]) / inputs.scale  # iterate on Z / scale
        self.Z = np.zeros_like(self.B)
        self._U: Optional[np.ndarray] = None

    def update(self, inputs: IterationInputs, rows: Optional[np.ndarray] = None,
               moved: Optional[np.ndarray] = None) -> None:
        U = self._U
        super().update(inputs, rows, moved)
        if U is not None and U.shape[1:] == self.Z.shape:
            self._U = U  # the GMRES basis keeps its memory

    def step(self) -> tuple[float, float]:
        Z = self.Z
        Z_new = self.P @ Z
        Z_new += self.B
        np.multiply(Z_new, Z_new >= self.inputs.floor, out=Z_new)
        top = float(Z_new.max()) if Z_new.size else 0.0  # Z >= 0 throughout
        change = float(np.abs(Z_new - Z).max()) if Z_new.size else 0.0
        self.Z = Z_new
        return change, top

    regions = True

    def region(self, rows: np.ndarray):
        P = self.P[rows]
        return rows, P, self.B[rows]

    def step_region(self, region) -> tuple[float, float]:
        rows, P, B = region
        Z_new = P @ self.Z
        Z_new += B
        np.multiply(Z_new, Z_new >= self.inputs.floor, out=Z_new)
        top = float(Z_new.max()) if Z_new.size else 0.0
        change = float(np.abs(Z_new - self.Z[rows]).max()) if Z_new.size else 0.0
        self.Z[rows] = Z_new
        return change, top

    def state(self) -> np.ndarray:
        return self.Z

    def load(self, Z: np.ndarray) -> None:
        self.Z = np.array(Z, np.float32, copy=True).reshape(self.B.shape)

    def krylov(self, m: int) -> float:
        if self._U is None or self._U.shape != (m + 1,) + self.Z.shape:
            self._U = np.zeros((m + 1,) + self.Z.shape, np.float32)
        res, bn = gmres(self.Z, self.B, self._U, m, _CsrOps(self.P))
        return res / bn if bn > 0 else 0.0


class _CsrOps(KrylovOps):
    def __init__(self, P: sp.csr_matrix):
        self.P = P

    def residual(self, Z, B, out) -> None:
        out[:] = B - Z + self.P @ Z

    def apply(self, X, out) -> None:
        out[:] = X - self.P @ X
