"""Reduced label diffusion (paper Eqs. 10, 14-16): the one diffusion core.

With G the kNN weights (Eq. 3-4) and E the per-point pixel mass before lambda (Eq. 12):
    d_i        = Sum_j G_ij + lambda * Sum_c E_ic                      (denominator of Eqs. 14-15)
    P_ij       = G_ij / d_i                                           (Eq. 14)
    B_ic       = lambda * E_ic / d_i                                  (Z^{I->X}, Eq. 15)
    Z <- P Z + B, starting from Z = 0                                 (Eq. 10)
Rows of [P | B] sum to 1, so the iteration is the paper's full-graph diffusion with the
pixel nodes held fixed.

:class:`System` holds that system over fixed-K rows and runs the iteration on a Jacobi backend
(:mod:`diffuser_lab.backends`). Every user of the method is a user of it: a batch run
(:func:`normalise` + :func:`diffuse`: all rows, Z0 = 0, gamma = 1, observers, early stop), the
single-frame protocol (the same, per target frame) and the online mode
(:mod:`diffuser_lab.method.online`: the rows a frame changed renormalised, a few warm-started
steps of the discounted iteration Z <- gamma P Z + B per frame, a map that may grow and be
re-ordered); a tiled diffusion is one more (a System per tile).

Numerical floor: float32 denormals (|x| < 1.2e-38) make every sparse product several times
slower, and they arise from numerically nil weights (e.g. exp(-25) across a crease) chained
over hops. So transition weights P_ij < EDGE_FLOOR are dropped, and the iteration runs on Z
scaled so that max(B) = 1 (batch; lambda for an online run, whose B changes) with entries below
SCORE_FLOOR flushed to zero; Z is returned in the paper's units. Both floors are many orders of
magnitude below any mass that can change an argmax. Label = argmax_c Z_ic (Eq. 16); a point
whose row of Z is still all zero (no evidence reached it) is IGNORE, never class 0.
"""
from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
import scipy.sparse as sp

from diffuser_lab import progress
from diffuser_lab.backends import make_backend, resolve_backend
from diffuser_lab.backends.base import IterationInputs, JacobiBackend, residual
from diffuser_lab.backends.normalise import normalise_rows
from diffuser_lab.backends.sparse import neighbourhood_classes
from diffuser_lab.backends.stats import StatsRequest, StepTable, Truth, truth_rows
from diffuser_lab.config import SolverBackend, SparseClasses
from diffuser_lab.data.scene import IGNORE

from .graph import KnnGraph, SortedKnnGraph

Observer = Callable[[int, np.ndarray, dict], None]
"""Called as observer(iteration, Z, stats) after each iteration; Z (N, C) is read-only, valid
during the call only (the next observed iteration reuses its memory: copy what you keep), and
stats holds ``residual`` (relative, see :func:`diffuse`). Observers must not change anything.
An observer with a ``wants(iteration) -> bool`` method is called only where it returns True
(building Z in the paper's units for an iteration nobody records costs a full copy).

An observer with a ``statistics()`` method that returns a
:class:`~diffuser_lab.backends.stats.StatsRequest` (None: none) gets every step's statistics,
computed by the backend in its step (:mod:`diffuser_lab.backends.stats`: labels changed,
confidence, correct and predicted counts per class against the request's ground truth), through
``on_statistics(table)``: a :class:`~diffuser_lab.backends.stats.StepTable` of consecutive
iterations, before the ``observer`` call of the table's last iteration (when it wants it)."""


def observes(observer: Optional[Observer], iteration: int) -> bool:
    """Whether ``observer`` is to be called after ``iteration`` (see :data:`Observer`)."""
    return observer is not None and (not hasattr(observer, "wants") or observer.wants(iteration))


def statistics_request(observer: Optional[Observer]) -> Optional[StatsRequest]:
    """The :class:`~diffuser_lab.backends.stats.StatsRequest` of ``observer`` (see :data:`Observer`), or None."""
    ask = getattr(observer, "statistics", None)
    return ask() if ask is not None else None


STATS_SEGMENT = 256
"""While statistics are tracked the compiled Jacobi returns to Python at least every this many
steps (their per-thread rows are kept per step until then: 256 x threads x (3 + 2 C) float64)."""


def show(observer: Observer, iteration: int, Z: np.ndarray, residual: float) -> None:
    """Call ``observer`` with a read-only view of ``Z`` (N, C) in the paper's units."""
    view = Z.view()
    view.flags.writeable = False
    observer(iteration, view, {"residual": residual})


EDGE_FLOOR = 1e-12
"""Transition weights below this (of a row summing to 1) are dropped."""
SCORE_FLOOR = 1e-18
"""Scores below this fraction of the iteration's scale are flushed to zero during the iteration."""


@dataclass
class DiffusionResult:
    """Z (N, C) float32 after ``iterations`` updates; residual is the last relative change
    (jacobi) or the relative residual |B - (I - P) Z| / |B| (exact). ``info`` says how the
    result was computed (solver, backend, ...)."""

    Z: np.ndarray
    iterations: int
    converged: bool
    residual: float
    residuals: list[float] = field(default_factory=list)
    info: dict = field(default_factory=dict)


SPARSE_ABOVE = 32
"""``sparse_classes=auto`` considers the sparse class set above this many active classes (the
dense numba kernels step 32-wide class blocks beyond it, all in one compiled call)."""
SPARSE_DENSE_BYTES = 2 * 1024**3
"""... and only where the dense iteration state (B, Z, Z_new: 3 x N x C float32) exceeds this:
measured on 30k-300k points the sparse set is not faster than the dense kernels (docs/many-classes.md),
it saves memory."""


def sparse_by_size(n_points: int, n_classes: int) -> bool:
    """The size part of ``sparse_classes=auto`` (also what the memory check assumes)."""
    return n_classes > SPARSE_ABOVE and 3 * 4 * n_points * n_classes > SPARSE_DENSE_BYTES


def sparse_choice(inputs: IterationInputs, mode: SparseClasses, per_point: int, backend: str) -> bool:
    """Whether the Jacobi steps run on the sparse per-point class set (:mod:`diffuser_lab.backends.sparse`).

    ``on``: always (numba or scipy); ``off``: never; ``auto``: on the numba backend when
    :func:`sparse_by_size` (more than :data:`SPARSE_ABOVE` active classes and a dense state over
    :data:`SPARSE_DENSE_BYTES`) and a point's 1-hop neighbourhood sees on average at most
    ``per_point / 2`` classes (:func:`~diffuser_lab.backends.sparse.neighbourhood_classes`), so
    that little is dropped."""
    try:
        mode = SparseClasses(mode)
    except ValueError:
        raise ValueError(f"solver.sparse_classes={mode}: expected auto, on or off") from None
    if mode == SparseClasses.on and backend == "torch":
        raise ValueError("solver.sparse_classes=on runs on the numba or scipy backend, not solver.backend=torch")
    if mode != SparseClasses.auto:
        return mode == SparseClasses.on
    if backend != "numba" or not sparse_by_size(inputs.shape[0], len(inputs.active)):
        return False
    return neighbourhood_classes(inputs) <= per_point / 2


SEGMENT_ROW_STEPS = 20_000_000
"""The compiled Jacobi runs at most this many row updates (~0.5-1 s) before returning to Python,
so that Ctrl-C and observers are never far away."""


def progress_chunk(max_iter: int) -> int:
    """Iterations between two updates of the diffusion's progress line (only while it is shown:
    the compiled Jacobi then returns to Python this often; the result does not change)."""
    return max(10, max_iter // 20)


def _grown(a: np.ndarray, rows: int, fill=0) -> np.ndarray:
    """``a`` with room for ``rows`` rows (the used ones copied, the new ones ``fill``). Zero fill
    takes the system's zeroed pages (``np.zeros``): a page is touched when its rows are first
    written, not all at once (measured: growing a 36k-row system to 65k took 52 ms in ``np.full``,
    a page fault at a time)."""
    out = np.zeros((rows,) + a.shape[1:], a.dtype) if fill == 0 else np.full((rows,) + a.shape[1:], fill, a.dtype)
    out[: a.shape[0]] = a
    return out


class System:
    """The normalised system of Eqs. 14-15 over fixed-K rows, and the iteration of Eq. 10 on it.

    Rows are in the iteration's order: row s is the caller's point ``order[s]`` (the graph's
    Morton order; ``order`` None: point s). Everything is in that order except ``mass`` (the
    caller's) and what the properties :attr:`B`, :attr:`P`, :meth:`scores` give (the caller's).

    Args:
        neighbors: (N, K) int32 row indices of each row's neighbours; weights: (N, K) float32
            their G (Eq. 4; 0 for padding); edge_sums: (N,) float64 Sum_j G_sj.
        mass: (M, C) the caller's pixel mass E before lambda (Eq. 12), read at ``order[s]``;
            the caller may change it (then :meth:`renormalise` the rows whose point changed).
        pixel_weight: lambda. gamma: the discount folded into P (1: the paper's system).
        order: (N,) int64 or None. normalised: False leaves P and B at 0 (call :meth:`renormalise`).

    Attributes:
        sorted_neighbors, sorted_P: (N, K) the neighbours and P_sj (dropped = 0) of the rows;
        B_rows: (N, C) float32 B of the rows; active: (A,) int64 the classes some B row holds.
    """

    def __init__(self, neighbors: np.ndarray, weights: np.ndarray, edge_sums: np.ndarray, mass: np.ndarray,
                 pixel_weight: float, *, order: Optional[np.ndarray] = None, gamma: float = 1.0,
                 normalised: bool = True):
        n, k = neighbors.shape
        self.n = int(n)
        self._nbr = np.ascontiguousarray(neighbors, np.int32)
        self._w = np.ascontiguousarray(weights, np.float32)
        self._wsum = np.ascontiguousarray(edge_sums, np.float64)
        self._order = None if order is None else np.ascontiguousarray(order, np.int64)
        self.mass = mass
        self.pixel_weight = float(pixel_weight)
        self.gamma = float(gamma)
        self._P = np.zeros((n, k), np.float32)
        self._B = np.zeros((n, mass.shape[1]), np.float32)
        self.active = np.zeros(0, np.int64)
        self._backend: Optional[JacobiBackend] = None
        self._scale = np.float32(1.0)
        self._csr: Optional[sp.csr_matrix] = None
        if normalised:
            self.renormalise()

    @classmethod
    def from_graph(cls, graph: KnnGraph, mass: np.ndarray, pixel_weight: float, gamma: float = 1.0) -> "System":
        """Eqs. 14-15 of ``graph`` (its Morton order, if sorted) and the (N, C) pixel mass."""
        if isinstance(graph, SortedKnnGraph):
            return cls(graph.sorted_neighbors, graph.sorted_weights, graph.sorted_row_sums, mass, pixel_weight,
                       order=graph.order, gamma=gamma)
        return cls(graph.neighbors, graph.weights, graph.weights.sum(1, dtype=np.float64), mass, pixel_weight,
                   gamma=gamma)

    # -- the rows ------------------------------------------------------------------------------
    @property
    def k(self) -> int:
        return int(self._nbr.shape[1])

    @property
    def num_classes(self) -> int:
        return int(self._B.shape[1])

    @property
    def order(self) -> Optional[np.ndarray]:
        """(N,) int64 the caller's point of row s, or None (row s is point s)."""
        return None if self._order is None else self._order[: self.n]

    @property
    def sorted_neighbors(self) -> np.ndarray:
        return self._nbr[: self.n]

    @property
    def edge_weights(self) -> np.ndarray:
        """(N, K) float32 G of the rows (writable: a growing graph sets its changed rows here)."""
        return self._w[: self.n]

    @property
    def edge_sums(self) -> np.ndarray:
        return self._wsum[: self.n]

    @property
    def sorted_P(self) -> np.ndarray:
        return self._P[: self.n]

    @property
    def B_rows(self) -> np.ndarray:
        return self._B[: self.n]

    @property
    def B(self) -> np.ndarray:
        """(N, C) float32 B in the caller's order (a copy unless ``order`` is None)."""
        if self._order is None:
            return self.B_rows
        out = np.empty_like(self.B_rows)
        out[self.order] = self.B_rows
        return out

    @property
    def P(self) -> sp.csr_matrix:
        """(N, N) CSR float32 P in the caller's order (zeros dropped; built on first use)."""
        if self._csr is None:
            n, k = self.n, self.k
            if self._order is None:
                data, cols = self.sorted_P.ravel().copy(), self.sorted_neighbors.ravel().copy()
            else:
                order = self.order
                inv = np.empty_like(order)
                inv[order] = np.arange(n)
                data = self.sorted_P[inv].ravel()
                cols = order[self.sorted_neighbors[inv]].ravel().astype(np.int32)
            P = sp.csr_matrix((data, cols, np.arange(0, n * k + 1, k, dtype=np.int64)), shape=(n, n))
            P.eliminate_zeros()
            self._csr = P
        return self._csr

    @property
    def row_sums(self) -> np.ndarray:
        """(N,) Sum_j P_ij + Sum_c B_ic in the caller's order: 1 for every point with any edge
        (0 for isolated ones; gamma for an online system's)."""
        return np.asarray(self.P.sum(1)).ravel() + self.B.sum(1)

    def sorted_csr(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(indptr, indices, data) of P in row order (fixed K per row, zeros kept)."""
        n, k = self.n, self.k
        return np.arange(0, n * k + 1, k, dtype=np.int64), self.sorted_neighbors.reshape(-1), self.sorted_P.reshape(-1)

    def __repr__(self) -> str:
        return f"System(n={self.n}, k={self.k}, classes={self.num_classes}, gamma={self.gamma:g})"

    # -- Eqs. 14-15 ----------------------------------------------------------------------------
    def renormalise(self, rows: Optional[np.ndarray] = None) -> None:
        """Eqs. 14-15 of ``rows`` (sorted int64; None: every row) after their evidence or edges
        changed; classes they name become active; a running iteration takes the change."""
        normalise_rows(rows, self.order, self.edge_weights, self.edge_sums, self.mass, self.pixel_weight,
                       self.gamma, EDGE_FLOOR, self.sorted_P, self.B_rows)
        self._csr = None
        named = np.flatnonzero(self.B_rows.any(0) if rows is None else self.B_rows[rows].any(0))
        self.active = named if rows is None else np.union1d(self.active, named)
        if self._backend is not None:
            self._backend.update(self.inputs(), rows)

    def resize(self, n: int) -> None:
        """Room for ``n`` >= N rows (a growing map; capacity doubles). The new rows have no edges
        and no evidence until the caller sets them (:attr:`sorted_neighbors`, :attr:`edge_weights`,
        :attr:`edge_sums`, ``order``) and renormalises them."""
        if n > self._nbr.shape[0]:
            cap = max(n, 2 * self._nbr.shape[0], 1024)
            self._nbr, self._w, self._wsum = _grown(self._nbr, cap), _grown(self._w, cap), _grown(self._wsum, cap)
            self._P, self._B = _grown(self._P, cap), _grown(self._B, cap)
            if self._order is not None:
                self._order = _grown(self._order, cap)
        self.n = int(n)
        self._csr = None

    def set_order(self, rows: np.ndarray, points: np.ndarray) -> None:
        """Row ``rows[i]`` is the caller's point ``points[i]`` (after :meth:`resize`)."""
        if self._order is None:
            self._order = np.arange(self._nbr.shape[0], dtype=np.int64)
        self._order[rows] = points

    def move(self, moved: np.ndarray) -> None:
        """Re-order the rows: new row s = old row ``moved[s]`` (the same system; a running
        iteration keeps its Z, re-ordered)."""
        n = self.n
        inv = np.empty(n, np.int64)
        inv[moved] = np.arange(n)
        for a in (self._w, self._wsum, self._P, self._B):
            a[:n] = a[:n][moved]
        self._nbr[:n] = inv[self._nbr[:n][moved]]
        if self._order is not None:
            self._order[:n] = self._order[:n][moved]
        self._csr = None
        if self._backend is not None:
            self._backend.update(self.inputs(), None, moved)

    # -- Eq. 10 on a backend -------------------------------------------------------------------
    def inputs(self, scale: Optional[float] = None) -> IterationInputs:
        """What the backend iterates on (:class:`~diffuser_lab.backends.base.IterationInputs`),
        on Z / ``scale`` (default: the running iteration's)."""
        indptr, indices, data = self.sorted_csr()
        return IterationInputs(self.active, (self.n, self.num_classes),
                               self._scale if scale is None else np.float32(scale), np.float32(SCORE_FLOOR),
                               self.order, indptr, indices, data, self.B_rows)

    def default_scale(self) -> np.float32:
        """max(B) (1 where B is all 0): the batch iteration's scale."""
        b_max = float(self.B_rows.max()) if self.B_rows.size else 0.0
        return np.float32(b_max if b_max > 0 else 1.0)

    def start(self, *, backend: SolverBackend | str = SolverBackend.auto, tol: float = 1e-4,
              scale: Optional[float] = None, device: Optional[str] = None,
              sparse_classes: SparseClasses | str = SparseClasses.auto, classes_per_point: int = 16,
              sparse_rel: float = 0.0, sparse_refresh: int = 1, rows_hint: int = 0) -> JacobiBackend:
        """Z = 0 on a backend (``auto`` = numba when available; ``sparse_classes``:
        :func:`sparse_choice`) iterating on Z / ``scale`` (None: :meth:`default_scale`);
        ``rows_hint``: the rows a growing system may reach. Replaces a running iteration."""
        self.close()
        name = resolve_backend(backend)
        self._scale = self.default_scale() if scale is None else np.float32(scale)
        inputs = self.inputs()
        sparse = int(classes_per_point) if sparse_choice(inputs, sparse_classes, classes_per_point, name) else 0
        self._backend = make_backend(name, inputs, tol, device=device, sparse=sparse, rel=sparse_rel,
                                     refresh=sparse_refresh, rows_hint=rows_hint)
        return self._backend

    @property
    def backend(self) -> JacobiBackend:
        if self._backend is None:
            raise RuntimeError("System: no iteration running (call start() first)")
        return self._backend

    def steps(self, count: int, rows: Optional[np.ndarray] = None) -> np.ndarray:
        """Up to ``count`` steps from the current Z, stopping after the first step whose relative
        change is <= the backend's tol; (done, 2) float32 (max change, max Z) per step. ``rows``
        (R,) int64 sorted: a region's steps (those rows alone, on a backend that has them:
        :attr:`~diffuser_lab.backends.base.JacobiBackend.regions`; the others step every row)."""
        b = self.backend
        return b.steps(count) if rows is None or not b.regions else b.steps(count, rows)

    def run(self, max_iter: int, observer: Optional[Observer] = None, label: Optional[str] = None) -> DiffusionResult:
        """Up to ``max_iter`` steps from the current Z with observers (:data:`Observer`) and the
        early stop (a step changing Z by <= tol of its largest entry), a progress line named
        ``label`` (None: none); the result's Z in the caller's order and the paper's units."""
        steps = self.backend
        tol = steps.tol
        n = self.n
        residuals: list[float] = []
        converged = False
        it = 0
        r = 0.0
        seen_buf: Optional[np.ndarray] = None  # what observers see (valid during their call only)
        info = {"solver": "jacobi", **steps.details()}
        if label is not None:
            label = f"{label} (jacobi, {' '.join(str(v) for v in steps.details().values())}, {n:,} points)"
            if progress.enabled() and steps.compiling:  # a look at numba's cache only when a line can show it
                label += progress.COMPILING
        request = statistics_request(observer)
        truth = None
        if request is not None:  # every step's statistics, computed by the backend in its step
            truth = self.truth(request)
            steps.track(truth)
        try:
            shown = (progress.stage(label, total=max_iter, unit="it") if label is not None
                     else nullcontext(progress.Stage()))
            with shown as bar:
                # run up to the next iteration an observer wants to see without returning to Python, at most
                # SEGMENT_ROW_STEPS row updates (and, while a progress line is shown, progress_chunk() steps)
                # at a time: the steps and their stopping rule do not depend on where the run is split
                segment = max(1, SEGMENT_ROW_STEPS // max(n, 1))
                if bar.enabled:
                    segment = min(segment, progress_chunk(max_iter))
                if request is not None:
                    segment = min(segment, STATS_SEGMENT)
                while it < max_iter:
                    stop = it + 1
                    last = min(max_iter, it + segment)
                    while stop < last and not observes(observer, stop):
                        stop += 1
                    first = it + 1
                    for change, top in steps.steps(stop - it):
                        it += 1
                        r = residual(change, top)
                        residuals.append(r)
                    if request is not None:
                        observer.on_statistics(StepTable(np.arange(first, it + 1),
                                                         np.asarray(residuals[first - 1:], np.float64), steps.stats,
                                                         None if truth is None else truth.total))
                    if bar.enabled:
                        bar.note(f"{'converged, ' if r <= tol else ''}residual {r:.1e}")
                        bar.set(it)
                    if observes(observer, it):
                        if seen_buf is None:  # one buffer for all observed iterations: no fresh pages each time
                            seen_buf = np.zeros((n, self.num_classes), np.float32)
                        show(observer, it, steps.paper_units(seen_buf), r)
                    if r <= tol:
                        converged = True
                        break
        finally:
            if request is not None:
                steps.untrack()
        Z = steps.paper_units()
        info.update(steps.report())
        return DiffusionResult(Z=Z, iterations=it, converged=converged, residual=residuals[-1] if residuals else 0.0,
                               residuals=residuals, info=info)

    def truth(self, request: StatsRequest) -> Optional[Truth]:
        """The request's ground truth on the rows (:func:`~diffuser_lab.backends.stats.truth_rows`:
        through ``to_work`` to the caller's points, through :attr:`order` to the rows), or None."""
        if request.gt is None:
            return None
        return truth_rows(request.gt, request.to_work, self.order, self.n, self.num_classes)

    def labels(self, out: np.ndarray) -> int:
        """Eq. 16 in row order into ``out`` (N,) int16 (IGNORE where nothing reached a row);
        returns how many labels changed."""
        return self.backend.labels(out)

    def scores(self, out: Optional[np.ndarray] = None) -> np.ndarray:
        """(N, C) float32 Z in the caller's order and the paper's units (``out``: zero-filled)."""
        return self.backend.paper_units(out)

    def krylov(self, m: int) -> float:
        """GMRES(m) on (I - P) Z = B from the current Z (:mod:`diffuser_lab.backends.krylov`);
        the relative residual."""
        return self.backend.krylov(m)

    def close(self) -> None:
        """Stop the iteration (threads freed; the system stays)."""
        if self._backend is not None:
            self._backend.close()
            self._backend = None


SortedSystem = System
"""The name of :class:`System` when its rows were always the graph's Morton order."""


def normalise(graph: KnnGraph, mass: np.ndarray, pixel_weight: float) -> System:
    """Eqs. 14-15 from the graph and the (N, C) pixel mass (before lambda)."""
    return System.from_graph(graph, mass, pixel_weight)


def iteration_inputs(system: System) -> IterationInputs:
    """What a batch iteration of ``system`` runs on (:class:`~diffuser_lab.backends.base.IterationInputs`):
    the classes any pixel voted for, the scale max(B), the score floor, the Morton order or None,
    the CSR arrays and the B rows in that order."""
    return system.inputs(system.default_scale())


def diffuse(system: System, *, max_iter: int = 200, tol: float = 1e-4,
            observer: Optional[Observer] = None, backend: SolverBackend | str = SolverBackend.auto,
            device: Optional[str] = None, sparse_classes: SparseClasses | str = SparseClasses.auto,
            classes_per_point: int = 16, sparse_rel: float = 0.0, sparse_refresh: int = 1) -> DiffusionResult:
    """Iterate Eq. 10 from Z = 0 until max|Z_t - Z_{t-1}| <= tol * max|Z_t| or ``max_iter``.

    The change is measured relative to Z's scale because Z carries lambda-sized values.
    ``backend``: ``numba`` (compiled, threaded), ``scipy`` (CSR products), ``torch`` (CUDA;
    ``device`` another torch device), ``auto`` = numba when installed. The system is iterated
    in its Morton order. ``sparse_classes`` (auto | on | off, :func:`sparse_choice`) keeps at
    most ``classes_per_point`` classes per point (:mod:`diffuser_lab.backends.sparse`: the
    approximation, its bound and ``info``'s figures of it). The loop, the observer calls and the
    early stop are :meth:`System.run`'s; a backend only runs the steps.
    """
    system.start(backend=backend, tol=tol, device=device, sparse_classes=sparse_classes,
                 classes_per_point=classes_per_point, sparse_rel=sparse_rel, sparse_refresh=sparse_refresh)
    try:
        return system.run(max_iter, observer, label="diffusion")
    finally:
        system.close()


def labels_from_scores(Z: np.ndarray) -> np.ndarray:
    """Eq. 16: (N, C) scores -> (N,) int16 argmax; IGNORE where the row is all zero."""
    lab = np.argmax(Z, axis=1).astype(np.int16)
    lab[Z.max(1) <= 0] = IGNORE
    return lab
