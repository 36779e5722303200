"""The hot loops, below the method: numba kernels (numba/) with their numpy/scipy twins, and torch
for CUDA (torch.py). Without numba (or with DIFFUSER_LAB_NUMBA=0) everything runs on numpy/scipy;
the modules here choose, once per operation: normalise.py (Eqs. 14-15), knn.py (the kNN graph),
growing.py and voxel_map.py (a growing map's graph and voxels), evidence.py (the fused evidence
pass), records.py (the Z states a run records), krylov.py (GMRES on a backend's products),
threads.py (BLAS kept off the kernels' cores).

The Jacobi steps of Eq. 10 sit behind one small interface (:class:`~diffuser_lab.backends.base.JacobiBackend`):
:data:`BACKENDS` is their registry (``solver.backend``), each with its dense and, where it has one,
its sparse-class-set variant (``solver.sparse_classes``). A new backend is one module and one
entry of :data:`BACKENDS`."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

from diffuser_lab.config import SolverBackend

from . import numba as nb
from .base import IterationInputs, JacobiBackend
from .numba.jacobi import NumbaJacobi
from .numba.sparse import NumbaSparseJacobi
from .scipy import ScipyJacobi
from .sparse import SparseClassesJacobi
from .torch import TorchJacobi


@dataclass(frozen=True)
class Backend:
    """One Jacobi backend: ``dense(inputs, tol, rows_hint, device)`` and ``sparse(inputs, tol,
    per_point, rel, refresh, rows_hint)`` (its sparse-class-set variant, or None) make it; whether
    it is usable here and the error line when it is asked for but is not."""

    name: str
    dense: Callable[..., JacobiBackend]
    sparse: Optional[Callable[..., JacobiBackend]]
    available: Callable[[], bool] = lambda: True
    unavailable: str = ""


BACKENDS: dict[str, Backend] = {b.name: b for b in [
    Backend("numba", lambda inp, tol, rows_hint, device: NumbaJacobi(inp, tol, rows_hint),
            lambda inp, tol, m, rel, refresh, rows_hint: NumbaSparseJacobi(inp, tol, m, rel, refresh, rows_hint),
            nb.available, "solver.backend=numba: numba is not importable (it is a dependency: pip install numba) "
                          "or DIFFUSER_LAB_NUMBA=0 is set"),
    Backend("scipy", lambda inp, tol, rows_hint, device: ScipyJacobi(inp, tol, rows_hint),
            lambda inp, tol, m, rel, refresh, rows_hint: SparseClassesJacobi(inp, tol, m, rel, rows_hint)),
    # TorchJacobi says what is missing (torch, a CUDA device) in one line
    Backend("torch", lambda inp, tol, rows_hint, device: TorchJacobi(inp, tol, rows_hint, device), None),
]}


def resolve_backend(backend: SolverBackend | str) -> str:
    """``solver.backend`` -> a name of :data:`BACKENDS` (``auto``: numba when available, else scipy)."""
    try:
        backend = SolverBackend(backend)
    except ValueError:
        raise ValueError(f"solver.backend={backend}: expected {', '.join(b.value for b in SolverBackend)}") from None
    if backend == SolverBackend.auto:
        return "numba" if nb.available() else "scipy"
    b = BACKENDS[backend.value]
    if not b.available():
        raise RuntimeError(b.unavailable)
    return b.name


def make_backend(name: str, inputs: IterationInputs, tol: float, *, device: Optional[str] = None, sparse: int = 0,
                 rel: float = 0.0, refresh: int = 1, rows_hint: int = 0) -> JacobiBackend:
    """The backend ``name`` (resolved) on ``inputs``: its sparse variant with ``sparse`` classes per
    point when ``sparse`` > 0, else the dense one."""
    b = BACKENDS[name]
    if not sparse:
        return b.dense(inputs, tol, rows_hint, device)
    if b.sparse is None:
        raise ValueError(f"solver.sparse_classes=on runs on the numba or scipy backend, not solver.backend={name}")
    return b.sparse(inputs, tol, sparse, rel, refresh, rows_hint)
