"""The one interface between the diffusion loop and a Jacobi backend.

:func:`diffuser_lab.method.diffusion.diffuse` owns the iteration loop, the observer calls, the
progress line and the early stop; a backend only runs steps of Eq. 10 on what
:class:`IterationInputs` gives it and hands Z back in the paper's units. A backend never imports
the method that dispatches to it. The stopping rule is :func:`residual` <= tol, checked after
every step (the numba backend evaluates the same rule inside its compiled steps).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np


@dataclass
class IterationInputs:
    """What every Jacobi backend iterates on.

    Attributes:
        active: (A,) int64 classes any pixel voted for; the other columns of Z stay exactly 0.
        shape: (N, C) of Z.
        scale: max(B) as float32; the iteration runs on Z / scale (returned in paper units).
        floor: float32 entries of Z / scale below this are flushed to zero after each step.
        order: (N,) int64 caller's index of the row that is iterated in place s (Morton order),
            or None when the rows are in the caller's order.
        indptr, indices, data: CSR of P in that row order (int64, int32, float32).
        B: (N, C) float32 rows of B in that row order (all classes; ``active`` selects).
    """

    active: np.ndarray
    shape: tuple
    scale: np.float32
    floor: np.float32
    order: Optional[np.ndarray]
    indptr: np.ndarray
    indices: np.ndarray
    data: np.ndarray
    B: np.ndarray


def residual(change: float, top: float) -> float:
    """The relative change of a step, max|Z_t - Z_{t-1}| / max|Z_t| (0 for an all-zero Z)."""
    return float(change) / float(top) if top > 0 else 0.0


class JacobiBackend:
    """Steps of Eq. 10 ``Z <- P Z + B`` (Z from 0, entries below ``floor`` flushed to 0).

    ``steps(count)`` runs up to ``count`` steps and returns their (done, 2) float32 array of
    (max change, max Z), stopping after the first step whose :func:`residual` is <= ``tol``; a
    backend gives ``step()`` (one step, its (change, top)) or, to run many steps in compiled
    code, its own ``steps``. ``paper_units(out)`` gives Z (N, C) float32 in the caller's order
    and the paper's units (``out``, if given, is filled: its inactive columns must be 0);
    ``close()`` frees threads; ``details()`` says what ran (``info`` of the result).
    """

    name = "?"

    def __init__(self, inputs: IterationInputs, tol: float):
        self.inputs, self.tol = inputs, float(tol)

    @property
    def compiling(self) -> bool:
        """Whether the backend's kernels compile in this run (the progress line says so)."""
        return False

    def details(self) -> dict:
        return {"backend": self.name}

    def report(self) -> dict:
        """What the run's ``info`` adds after the last step (e.g. an approximation's figures)."""
        return {}

    def step(self) -> tuple[float, float]:  # pragma: no cover - interface
        raise NotImplementedError

    def steps(self, count: int) -> np.ndarray:
        out = []
        for _ in range(count):
            change, top = self.step()
            out.append((change, top))
            if residual(change, top) <= self.tol:
                break
        return np.array(out, np.float32).reshape(-1, 2)

    def paper_units(self, out: Optional[np.ndarray] = None) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
