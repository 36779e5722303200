"""How a graph method's normalised system is solved (``solver.name``): the paper's early-stopped
iteration (:func:`~diffuser_lab.method.diffusion.diffuse`) or the exact fixed point
(:func:`~diffuser_lab.method.exact.solve_exact`), one registry entry each."""
from __future__ import annotations

from typing import Callable, Optional

from diffuser_lab.config import SolverConfig, SolverName

from .diffusion import DiffusionResult, Observer, System, diffuse
from .exact import solve_exact


def _jacobi(system: System, cfg: SolverConfig, observer: Optional[Observer]) -> DiffusionResult:
    return diffuse(system, max_iter=cfg.max_iter, tol=cfg.tol, observer=observer, backend=cfg.backend,
                   sparse_classes=cfg.sparse_classes, classes_per_point=cfg.classes_per_point)


def _exact(system: System, cfg: SolverConfig, observer: Optional[Observer]) -> DiffusionResult:
    return solve_exact(system, max_iter=cfg.max_iter, tol=cfg.tol, observer=observer, backend=cfg.backend)


SOLVERS: dict[SolverName, Callable[[System, SolverConfig, Optional[Observer]], DiffusionResult]] = {
    SolverName.jacobi: _jacobi,
    SolverName.exact: _exact,
}


def solve(system: System, cfg: SolverConfig, observer: Optional[Observer] = None) -> DiffusionResult:
    """Solve ``system`` as ``cfg`` (:class:`~diffuser_lab.config.SolverConfig`) says."""
    return SOLVERS[SolverName(cfg.name)](system, cfg, observer)
