"""The plain numpy/scipy Jacobi backend: one CSR product per step (``solver.backend=scipy``, and
what ``auto`` uses without numba or with ``DIFFUSER_LAB_NUMBA=0``)."""
from __future__ import annotations

from typing import Optional

import numpy as np
import scipy.sparse as sp

from .base import IterationInputs, JacobiBackend


class ScipyJacobi(JacobiBackend):
    name = "scipy"

    def __init__(self, inputs: IterationInputs, tol: float):
        super().__init__(inputs, tol)
        n = inputs.shape[0]
        Pm = sp.csr_matrix((inputs.data, inputs.indices, inputs.indptr), shape=(n, n), copy=True)  # never alias
        Pm.eliminate_zeros()
        self.P = Pm
        self.B = np.ascontiguousarray(inputs.B[:, inputs.active]) / inputs.scale  # iterate on Z / max(B)
        self.Z = np.zeros_like(self.B)

    def step(self) -> tuple[float, float]:
        Z = self.Z
        Z_new = self.P @ Z
        Z_new += self.B
        np.multiply(Z_new, Z_new >= self.inputs.floor, out=Z_new)
        top = float(Z_new.max()) if Z_new.size else 0.0  # Z >= 0 throughout
        change = float(np.abs(Z_new - Z).max()) if Z_new.size else 0.0
        self.Z = Z_new
        return change, top

    def paper_units(self, out: Optional[np.ndarray] = None) -> np.ndarray:
        inp = self.inputs
        Z_full = np.zeros(inp.shape, np.float32) if out is None else out
        if inp.order is None:
            Z_full[:, inp.active] = self.Z * inp.scale
        else:
            tmp = np.zeros(inp.shape, np.float32)
            tmp[:, inp.active] = self.Z * inp.scale
            Z_full[inp.order] = tmp
        return Z_full
