"""The one interface between the diffusion core and a Jacobi backend.

:class:`diffuser_lab.method.diffusion.System` owns the normalised system (Eqs. 14-15), the
iteration loop, the observer calls, the progress line and the early stop; a backend only runs
steps of ``Z <- P Z + B`` (Eq. 10; an online run's discount gamma is folded into P) on what
:class:`IterationInputs` gives it, keeps Z between calls (a warm start is the state it has) and
hands Z back in the paper's units. A backend never imports the method that dispatches to it.
The stopping rule is :func:`residual` <= tol, checked after every step (the compiled backends
evaluate the same rule inside their compiled steps).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from .stats import NONE, no_truth, step_statistics, width  # NONE (-1): a row nothing reached (IGNORE)


@dataclass
class IterationInputs:
    """What every Jacobi backend iterates on (rows in the iteration's order).

    Attributes:
        active: (A,) int64 ascending classes some evidence named; the other columns of Z stay exactly 0.
        shape: (N, C) of Z.
        scale: float32; the iteration runs on Z / scale (returned in paper units): max(B) for a
            batch run, lambda for an online one (whose B changes between calls).
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


def union_rows(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    """Sorted union of two sets of row indices in [0, n) (int64): ``np.union1d`` through a mask
    (measured: 0.1 instead of 1.6 ms on a growing map's ~60k rows, three times a frame)."""
    mask = np.zeros(n, bool)
    mask[a] = True
    mask[b] = True
    return np.flatnonzero(mask)


def row_runs(rows: np.ndarray, chunk: int) -> np.ndarray:
    """Sorted rows (R,) int64 -> (runs, 2) int64 ``[lo, hi)`` ranges of consecutive rows covering
    exactly them, in order, every range cut into pieces of at most ``chunk`` rows."""
    if rows.size == 0:
        return np.zeros((0, 2), np.int64)
    rows = np.asarray(rows, np.int64)
    brk = np.flatnonzero(np.diff(rows) > 1) + 1
    starts = rows[np.r_[0, brk]]
    ends = rows[np.r_[brk - 1, rows.size - 1]] + 1
    pieces = (ends - starts + chunk - 1) // chunk
    which = np.repeat(np.arange(starts.size), pieces)
    lo = starts[which] + chunk * (np.arange(which.size) - np.repeat(np.cumsum(pieces) - pieces, pieces))
    return np.stack([lo, np.minimum(lo + chunk, ends[which])], 1)


def residual(change: float, top: float) -> float:
    """The relative change of a step, max|Z_t - Z_{t-1}| / max|Z_t| (0 for an all-zero Z)."""
    return float(change) / float(top) if top > 0 else 0.0


def moved_state(Z: np.ndarray, old_active: np.ndarray, inputs: IterationInputs,
                moved: Optional[np.ndarray]) -> np.ndarray:
    """A state (n_old, A_old) carried to a changed system: (N, A) float32 whose rows are the old
    rows (re-ordered by ``moved``: new row s = old row moved[s]) followed by new rows at 0, and
    whose columns follow ``inputs.active`` (new classes at 0)."""
    n, na = inputs.shape[0], len(inputs.active)
    out = np.zeros((n, na), np.float32)
    cols = np.searchsorted(inputs.active, old_active)
    src = Z if moved is None else Z[moved]
    out[: src.shape[0], cols] = src
    return out


def argmax_labels(Z: np.ndarray, active: np.ndarray, labels: np.ndarray) -> int:
    """Eq. 16 on a state: labels (N,) int16 <- active[argmax_c Z[:, c]] (the first of equal
    maxima), NONE where the row is all <= 0; returns how many labels changed."""
    if Z.shape[1] == 0:
        new = np.full(labels.shape, NONE, np.int16)
    else:
        best = np.argmax(Z, axis=1)
        new = np.where(Z[np.arange(Z.shape[0]), best] > 0, active[best], NONE).astype(np.int16)
    changed = int(np.count_nonzero(new != labels))
    labels[:] = new
    return changed


class Tracking:
    """What a backend keeps while it computes per-step statistics (:meth:`JacobiBackend.track`):
    ``truth`` (:class:`~diffuser_lab.backends.stats.Truth`), ``labels`` (capacity,) int16 the last
    step's labels in row order (the first N in use), ``width`` the statistics rows' columns."""

    def __init__(self, truth, labels: np.ndarray, width: int):
        self.truth, self.labels, self.width = truth, labels, int(width)


class JacobiBackend:
    """Steps of Eq. 10 ``Z <- P Z + B`` (entries below ``floor`` flushed to 0) from Z = 0, or from
    the state it has (warm start).

    ``steps(count)`` runs up to ``count`` steps and returns their (done, 2) float32 array of
    (max change, max Z), stopping after the first step whose :func:`residual` is <= ``tol``; a
    backend gives ``step()`` (one step, its (change, top)) or, to run many steps in compiled
    code, its own ``steps``. After ``track(truth)`` every ``steps`` call also leaves its steps'
    statistics in :attr:`stats` (:mod:`diffuser_lab.backends.stats`: labels changed, labelled
    rows, confidence, correct and predicted counts per class; a compiled backend computes them in
    its step, this class beside each ``step()`` on the row-order state). ``paper_units(out)`` gives Z (N, C) float32 in the caller's order
    and the paper's units (``out``, if given, is filled: its inactive columns must be 0);
    ``state()`` / ``load(Z)`` read and set Z / scale (N, A) in row order; ``update(inputs, rows,
    moved)`` takes a changed system (rows renormalised, new rows, new classes, re-ordered rows:
    an online run) keeping Z; ``labels(out)`` is Eq. 16 in row order; ``close()`` frees threads;
    ``details()`` says what ran (``info`` of the result). ``rows_hint``: the number of rows the
    system may grow to (thread pools are sized for it).
    """

    name = "?"

    tracking: Optional[Tracking] = None
    stats: Optional[np.ndarray] = None
    """(done, width) float64 the statistics of the last ``steps`` call's steps while tracking, else None."""

    def __init__(self, inputs: IterationInputs, tol: float, rows_hint: int = 0):
        self.tol, self.rows_hint = float(tol), int(rows_hint)
        self.setup(inputs)

    def track(self, truth) -> None:
        """From the next step on, compute each step's statistics (:mod:`diffuser_lab.backends.stats`)
        against ``truth`` (a :class:`~diffuser_lab.backends.stats.Truth` in row order; None: no
        ground truth) into :attr:`stats`; labels changed count from the current state's labels."""
        n, c = self.inputs.shape
        if truth is None:
            truth = no_truth(n, c)
        labels = np.full(max(n, self.rows_hint), NONE, np.int16)
        self.labels(labels[:n])
        self.tracking = Tracking(truth, labels, width(c))

    def untrack(self) -> None:
        """No more statistics."""
        self.tracking, self.stats = None, None

    def setup(self, inputs: IterationInputs) -> None:
        """Take ``inputs`` (a new system); Z starts at 0."""
        self.inputs = inputs

    @property
    def compiling(self) -> bool:
        """Whether the backend's kernels compile in this run (the progress line says so)."""
        return False

    def details(self) -> dict:
        return {"backend": self.name}

    def report(self) -> dict:
        """What the run's ``info`` adds after the last step (e.g. an approximation's figures)."""
        return {}

    regions = False
    """Whether :meth:`steps` can step a region (some rows) alone; a backend without it steps every row."""

    def step(self) -> tuple[float, float]:  # pragma: no cover - interface
        raise NotImplementedError

    def region(self, rows: np.ndarray):  # pragma: no cover - interface of a backend with regions
        """What :meth:`step_region` steps for the sorted rows (R,) int64 (made once per :meth:`steps` call)."""
        raise NotImplementedError

    def step_region(self, region) -> tuple[float, float]:  # pragma: no cover - interface
        """One step of the region's rows alone; (max change, max Z) over them."""
        raise NotImplementedError

    def steps(self, count: int, rows: Optional[np.ndarray] = None) -> np.ndarray:
        """Up to ``count`` steps (class doc); ``rows`` (R,) int64 sorted: a region's steps, where
        the backend has them (:attr:`regions`): those rows alone are stepped (the others read,
        never written) and the early stop looks at them alone; no statistics are tracked then."""
        out = []
        t = self.tracking
        if rows is not None and self.regions:
            if t is not None:
                raise ValueError("a region's steps track no statistics")
            region = self.region(rows)
            step = lambda: self.step_region(region)  # noqa: E731
        else:
            step = self.step
        rows = np.zeros((count, t.width), np.float64) if t is not None else None
        n = self.inputs.shape[0]
        for s in range(count):
            change, top = step()
            out.append((change, top))
            if t is not None:  # beside the step, on the state in row order
                step_statistics(self.state(), self.inputs.active, t.labels[:n], t.truth, rows[s])
            if residual(change, top) <= self.tol:
                break
        if t is not None:
            self.stats = rows[:len(out)]
        return np.array(out, np.float32).reshape(-1, 2)

    def state(self) -> np.ndarray:  # pragma: no cover - interface
        """(N, A) float32 Z / scale in row order, columns ``inputs.active`` (a copy or a view)."""
        raise NotImplementedError

    def load(self, Z: np.ndarray) -> None:  # pragma: no cover - interface
        """Set Z / scale (N, A) in row order (a warm start)."""
        raise NotImplementedError

    def update(self, inputs: IterationInputs, rows: Optional[np.ndarray] = None,
               moved: Optional[np.ndarray] = None) -> None:
        """The system changed: P and B in ``rows`` (None: anywhere), rows appended (they start at
        Z = 0), classes activated (their columns start at 0), rows re-ordered (new row s = old
        row ``moved[s]``); ``inputs`` keeps ``scale`` and ``floor``. Z is kept. This default
        re-takes the whole system; backends override it where a part is cheaper."""
        Z = moved_state(self.state(), self.inputs.active, inputs, moved)
        self.setup(inputs)
        self.load(Z)

    def labels(self, out: np.ndarray) -> int:
        """Eq. 16 in row order: ``out`` (N,) int16 <- the class of each row's largest score
        (NONE where nothing reached it); returns how many labels changed."""
        return argmax_labels(self.state(), self.inputs.active, out)

    def krylov(self, m: int) -> float:
        """GMRES(m) on (I - P) Z = B from the current Z, each class column on its own, Z clamped
        at 0 after it (``online.solver=gmres``); returns the relative residual |B - (I - P) Z|
        / |B| of the least-squares solution (max over columns)."""
        raise ValueError(f"online.solver=gmres runs on the numba or scipy backend, not {self.name}")

    def paper_units(self, out: Optional[np.ndarray] = None) -> np.ndarray:
        """Z (N, C) float32 in the caller's order and the paper's units."""
        inp = self.inputs
        Z_full = np.zeros(inp.shape, np.float32) if out is None else out
        z = self.state() * inp.scale
        if inp.order is None:
            Z_full[:, inp.active] = z
        else:
            tmp = np.zeros(inp.shape, np.float32)
            tmp[:, inp.active] = z
            Z_full[inp.order] = tmp
        return Z_full

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
