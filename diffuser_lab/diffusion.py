"""Reduced label diffusion (paper Eqs. 10, 14-16).

With G the kNN weights (Eq. 3-4) and E the per-point pixel mass before lambda (Eq. 12):
    d_i        = Sum_j G_ij + lambda * Sum_c E_ic                      (denominator of Eqs. 14-15)
    P_ij       = G_ij / d_i                                           (Eq. 14)
    B_ic       = lambda * E_ic / d_i                                  (Z^{I->X}, Eq. 15)
    Z <- P Z + B, starting from Z = 0                                 (Eq. 10)
Rows of [P | B] sum to 1, so the iteration is the paper's full-graph diffusion with the
pixel nodes held fixed.

Numerical floor: float32 denormals (|x| < 1.2e-38) make every sparse product several times
slower, and they arise from numerically nil weights (e.g. exp(-25) across a crease) chained
over hops. So transition weights P_ij < EDGE_FLOOR are dropped, and the iteration runs on Z
scaled so that max(B) = 1 with entries below SCORE_FLOOR flushed to zero; Z is returned in
the paper's units. Both floors are many orders of magnitude below any mass that can change
an argmax. Label = argmax_c Z_ic (Eq. 16); a point whose row of Z is still
all zero (no evidence reached it) is IGNORE, never class 0.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
import scipy.sparse as sp

from .graph import KnnGraph
from .scene import IGNORE

Observer = Callable[[int, np.ndarray, dict], None]
"""Called as observer(iteration, Z, stats) after each iteration; Z (N, C) is read-only and
stats holds ``residual`` (relative, see :func:`diffuse`). Observers must not change anything.
An observer with a ``wants(iteration) -> bool`` method is called only where it returns True
(building Z in the paper's units for an iteration nobody records costs a full copy)."""


@dataclass
class System:
    """The normalised system of Eqs. 14-15: P (N, N) CSR float32 and B (N, C) float32."""

    P: sp.csr_matrix
    B: np.ndarray

    @property
    def row_sums(self) -> np.ndarray:
        """(N,) Sum_j P_ij + Sum_c B_ic: 1 for every point with any edge (0 for isolated ones)."""
        return np.asarray(self.P.sum(1)).ravel() + self.B.sum(1)


EDGE_FLOOR = 1e-12
"""Transition weights below this (of a row summing to 1) are dropped."""
SCORE_FLOOR = 1e-18
"""Scores below this fraction of max(B) are flushed to zero during the iteration."""


def normalise(graph: KnnGraph, mass: np.ndarray, pixel_weight: float) -> System:
    """Eqs. 14-15 from the graph and the (N, C) pixel mass (before lambda)."""
    pix = mass.astype(np.float32) * np.float32(pixel_weight)
    denom = graph.weights.sum(1, dtype=np.float32) + pix.sum(1)
    # a point whose edges all underflowed and that has no pixel mass is isolated: zero row
    inv = np.divide(1.0, denom, out=np.zeros_like(denom), where=denom > 1e-30).astype(np.float32)
    P = graph.matrix(row_scale=inv)
    P.data[P.data < EDGE_FLOOR] = 0.0
    P.eliminate_zeros()
    return System(P=P, B=pix * inv[:, None])


@dataclass
class DiffusionResult:
    """Z (N, C) float32 after ``iterations`` updates; residual is the last relative change."""

    Z: np.ndarray
    iterations: int
    converged: bool
    residual: float
    residuals: list[float] = field(default_factory=list)


def diffuse(system: System, *, max_iter: int = 200, tol: float = 1e-4,
            observer: Optional[Observer] = None) -> DiffusionResult:
    """Iterate Eq. 10 from Z = 0 until max|Z_t - Z_{t-1}| <= tol * max|Z_t| or ``max_iter``.

    The change is measured relative to Z's scale because Z carries lambda-sized values.
    """
    # Classes that no pixel voted for stay exactly zero: iterate on the others only.
    active = np.flatnonzero(system.B.any(0))
    full_shape = system.B.shape
    b_max = float(system.B.max()) if system.B.size else 0.0
    scale = np.float32(b_max if b_max > 0 else 1.0)
    B = np.ascontiguousarray(system.B[:, active]) / scale  # iterate on Z / max(B), see module doc
    floor = np.float32(SCORE_FLOOR)

    def paper_units(Zs: np.ndarray) -> np.ndarray:
        Z_full = np.zeros(full_shape, np.float32)
        Z_full[:, active] = Zs * scale
        return Z_full

    Z = np.zeros_like(B)
    residuals: list[float] = []
    converged = False
    it = 0
    for it in range(1, max_iter + 1):
        Z_new = system.P @ Z
        Z_new += B
        np.multiply(Z_new, Z_new >= floor, out=Z_new)
        top = float(Z_new.max()) if Z_new.size else 0.0  # Z >= 0 throughout
        change = float(np.abs(Z_new - Z).max()) if Z_new.size else 0.0
        residual = change / top if top > 0 else 0.0
        residuals.append(residual)
        Z = Z_new
        if observer is not None and (not hasattr(observer, "wants") or observer.wants(it)):
            view = paper_units(Z).view()
            view.flags.writeable = False
            observer(it, view, {"residual": residual})
        if residual <= tol:
            converged = True
            break
    return DiffusionResult(Z=paper_units(Z), iterations=it, converged=converged,
                           residual=residuals[-1] if residuals else 0.0, residuals=residuals)


def labels_from_scores(Z: np.ndarray) -> np.ndarray:
    """Eq. 16: (N, C) scores -> (N,) int16 argmax; IGNORE where the row is all zero."""
    lab = np.argmax(Z, axis=1).astype(np.int16)
    lab[Z.max(1) <= 0] = IGNORE
    return lab


def solve(system: System, cfg, observer: Optional[Observer] = None) -> DiffusionResult:
    """Dispatch on ``cfg`` (:class:`~diffuser_lab.config.SolverConfig`): the solver and backend."""
    name = getattr(cfg.name, "value", cfg.name)
    if name == "jacobi":
        return diffuse(system, max_iter=cfg.max_iter, tol=cfg.tol, observer=observer)
    raise NotImplementedError(f"solver.name={name} is not implemented yet")
