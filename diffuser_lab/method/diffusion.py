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

from diffuser_lab import progress
from diffuser_lab.backends.base import IterationInputs, JacobiBackend, residual
from diffuser_lab.data.scene import IGNORE

from .graph import KnnGraph, SortedKnnGraph

Observer = Callable[[int, np.ndarray, dict], None]
"""Called as observer(iteration, Z, stats) after each iteration; Z (N, C) is read-only, valid
during the call only (the next observed iteration reuses its memory: copy what you keep), and
stats holds ``residual`` (relative, see :func:`diffuse`). Observers must not change anything.
An observer with a ``wants(iteration) -> bool`` method is called only where it returns True
(building Z in the paper's units for an iteration nobody records costs a full copy)."""


def observes(observer: Optional[Observer], iteration: int) -> bool:
    """Whether ``observer`` is to be called after ``iteration`` (see :data:`Observer`)."""
    return observer is not None and (not hasattr(observer, "wants") or observer.wants(iteration))


def show(observer: Observer, iteration: int, Z: np.ndarray, residual: float) -> None:
    """Call ``observer`` with a read-only view of ``Z`` (N, C) in the paper's units."""
    view = Z.view()
    view.flags.writeable = False
    observer(iteration, view, {"residual": residual})


@dataclass
class System:
    """The normalised system of Eqs. 14-15: P (N, N) CSR float32 and B (N, C) float32."""

    P: sp.csr_matrix
    B: np.ndarray

    @property
    def row_sums(self) -> np.ndarray:
        """(N,) Sum_j P_ij + Sum_c B_ic: 1 for every point with any edge (0 for isolated ones)."""
        return np.asarray(self.P.sum(1)).ravel() + self.B.sum(1)


class SortedSystem(System):
    """A :class:`System` whose P is kept as fixed-length rows in the graph's Morton order
    (:class:`~diffuser_lab.method.graph.SortedKnnGraph`); ``P`` in the caller's order is built on first
    access. ``B`` is in the caller's order.

    Attributes:
        order: (N,) int64 caller's index of sorted point s.
        sorted_neighbors: (N, K) int32; sorted_P: (N, K) float32 transition weights (dropped = 0).
    """

    def __init__(self, order: np.ndarray, sorted_neighbors: np.ndarray, sorted_P: np.ndarray, B: np.ndarray):
        self.order = order
        self.sorted_neighbors = sorted_neighbors
        self.sorted_P = sorted_P
        self.B = B
        self._P: sp.csr_matrix | None = None

    @property
    def P(self) -> sp.csr_matrix:  # type: ignore[override]
        if self._P is None:
            n, k = self.sorted_neighbors.shape
            inv = np.empty_like(self.order)
            inv[self.order] = np.arange(n)
            data = self.sorted_P[inv].ravel()
            cols = self.order[self.sorted_neighbors[inv]].ravel().astype(np.int32)
            P = sp.csr_matrix((data, cols, np.arange(0, n * k + 1, k, dtype=np.int64)), shape=(n, n))
            P.eliminate_zeros()
            self._P = P
        return self._P

    def sorted_csr(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(indptr, indices, data) of P in sorted order (fixed K per row, zeros kept)."""
        n, k = self.sorted_neighbors.shape
        return (np.arange(0, n * k + 1, k, dtype=np.int64), self.sorted_neighbors.reshape(-1),
                self.sorted_P.reshape(-1))

    def __repr__(self) -> str:
        return f"SortedSystem(n={self.B.shape[0]}, k={self.sorted_neighbors.shape[1]}, classes={self.B.shape[1]})"


EDGE_FLOOR = 1e-12
"""Transition weights below this (of a row summing to 1) are dropped."""
SCORE_FLOOR = 1e-18
"""Scores below this fraction of max(B) are flushed to zero during the iteration."""


def normalise(graph: KnnGraph, mass: np.ndarray, pixel_weight: float) -> System:
    """Eqs. 14-15 from the graph and the (N, C) pixel mass (before lambda)."""
    if isinstance(graph, SortedKnnGraph):
        from diffuser_lab.backends import numba as nb

        if nb.available():
            from diffuser_lab.backends.numba.normalise import normalise_sorted

            # the numpy lines below fused into three compiled passes (same float32 results)
            res = normalise_sorted(graph.order, graph.sorted_weights, graph.sorted_row_sums, mass, pixel_weight,
                                   EDGE_FLOOR)
            if res is not None:
                return SortedSystem(graph.order, graph.sorted_neighbors, *res)
    pix = mass.astype(np.float32) * np.float32(pixel_weight)
    if isinstance(graph, SortedKnnGraph):
        # Row sums come with the graph; the rows stay in its Morton order for the diffusion.
        order = graph.order
        wsum = np.empty(graph.n, np.float32)
        wsum[order] = graph.sorted_row_sums
        denom = wsum + pix.sum(1)
        inv = np.divide(1.0, denom, out=np.zeros_like(denom), where=denom > 1e-30).astype(np.float32)
        Ps = graph.sorted_weights * inv[order][:, None]
        Ps[Ps < EDGE_FLOOR] = 0.0
        return SortedSystem(order, graph.sorted_neighbors, Ps, pix * inv[:, None])
    denom = graph.weights.sum(1, dtype=np.float32) + pix.sum(1)
    # a point whose edges all underflowed and that has no pixel mass is isolated: zero row
    inv = np.divide(1.0, denom, out=np.zeros_like(denom), where=denom > 1e-30).astype(np.float32)
    P = graph.matrix(row_scale=inv)
    P.data[P.data < EDGE_FLOOR] = 0.0
    P.eliminate_zeros()
    return System(P=P, B=pix * inv[:, None])


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


def _resolve_backend(backend: str) -> str:
    from diffuser_lab.backends import numba as nb

    backend = getattr(backend, "value", backend)
    if backend == "auto":
        return "numba" if nb.available() else "scipy"
    if backend == "numba" and not nb.available():
        raise RuntimeError("solver.backend=numba: numba is not importable (it is a dependency: pip install numba) "
                           "or DIFFUSER_LAB_NUMBA=0 is set")
    if backend not in ("numba", "scipy", "torch"):
        raise ValueError(f"solver.backend={backend}: expected auto, scipy, numba or torch")
    return backend


def iteration_inputs(system: System) -> IterationInputs:
    """What every Jacobi backend iterates on (:class:`~diffuser_lab.backends.base.IterationInputs`):
    the classes any pixel voted for, the scale max(B) the iteration divides out and the score
    floor (see module doc), the Morton order or None, the CSR arrays and the B rows in that order."""
    active = np.flatnonzero(system.B.any(0))
    b_max = float(system.B.max()) if system.B.size else 0.0
    scale = np.float32(b_max if b_max > 0 else 1.0)
    floor = np.float32(SCORE_FLOOR)
    if isinstance(system, SortedSystem):
        indptr, indices, data = system.sorted_csr()
        return IterationInputs(active, system.B.shape, scale, floor, system.order, indptr, indices, data,
                               system.B[system.order])
    P = system.P.tocsr()
    return IterationInputs(active, system.B.shape, scale, floor, None, P.indptr.astype(np.int64),
                           P.indices.astype(np.int32), P.data.astype(np.float32), system.B)


SPARSE_ABOVE = 32
"""``sparse_classes=auto`` considers the sparse class set above this many active classes (the
dense numba kernels go one step at a time in class blocks beyond it)."""
SPARSE_DENSE_BYTES = 2 * 1024**3
"""... and only where the dense iteration state (B, Z, Z_new: 3 x N x C float32) exceeds this:
measured on 30k-300k points the sparse set is not faster than the dense kernels (docs/many-classes.md),
it saves memory."""


def sparse_by_size(n_points: int, n_classes: int) -> bool:
    """The size part of ``sparse_classes=auto`` (also what the memory check assumes)."""
    return n_classes > SPARSE_ABOVE and 3 * 4 * n_points * n_classes > SPARSE_DENSE_BYTES


def sparse_choice(inputs: IterationInputs, mode: str, per_point: int, backend: str) -> bool:
    """Whether the Jacobi steps run on the sparse per-point class set (:mod:`diffuser_lab.backends.sparse`).

    ``on``: always (numba or scipy); ``off``: never; ``auto``: on the numba backend when
    :func:`sparse_by_size` (more than :data:`SPARSE_ABOVE` active classes and a dense state over
    :data:`SPARSE_DENSE_BYTES`) and a point's 1-hop neighbourhood sees on average at most
    ``per_point / 2`` classes (:func:`~diffuser_lab.backends.sparse.neighbourhood_classes`), so
    that little is dropped."""
    mode = getattr(mode, "value", mode)
    if mode not in ("auto", "on", "off"):
        raise ValueError(f"solver.sparse_classes={mode}: expected auto, on or off")
    if mode == "on" and backend == "torch":
        raise ValueError("solver.sparse_classes=on runs on the numba or scipy backend, not solver.backend=torch")
    if mode != "auto":
        return mode == "on"
    if backend != "numba" or not sparse_by_size(inputs.shape[0], len(inputs.active)):
        return False
    from diffuser_lab.backends.sparse import neighbourhood_classes

    return neighbourhood_classes(inputs) <= per_point / 2


def _backend(name: str, inputs: IterationInputs, tol: float, device: Optional[str],
             sparse: int = 0, rel: float = 0.0, refresh: int = 1) -> JacobiBackend:
    if sparse:
        if name == "numba":
            from diffuser_lab.backends.numba.sparse import NumbaSparseJacobi

            return NumbaSparseJacobi(inputs, tol, sparse, rel, refresh)
        from diffuser_lab.backends.sparse import SparseClassesJacobi

        return SparseClassesJacobi(inputs, tol, sparse, rel)
    if name == "numba":
        from diffuser_lab.backends.numba.jacobi import NumbaJacobi

        return NumbaJacobi(inputs, tol)
    if name == "torch":
        from diffuser_lab.backends.torch import TorchJacobi

        return TorchJacobi(inputs, tol, device=device)
    from diffuser_lab.backends.scipy import ScipyJacobi

    return ScipyJacobi(inputs, tol)


SEGMENT_ROW_STEPS = 20_000_000
"""The compiled Jacobi runs at most this many row updates (~0.5-1 s) before returning to Python,
so that Ctrl-C and observers are never far away."""


def progress_chunk(max_iter: int) -> int:
    """Iterations between two updates of the diffusion's progress line (only while it is shown:
    the compiled Jacobi then returns to Python this often; the result does not change)."""
    return max(10, max_iter // 20)


def diffuse(system: System, *, max_iter: int = 200, tol: float = 1e-4,
            observer: Optional[Observer] = None, backend: str = "auto", device: Optional[str] = None,
            sparse_classes: str = "auto", classes_per_point: int = 16, sparse_rel: float = 0.0,
            sparse_refresh: int = 1) -> DiffusionResult:
    """Iterate Eq. 10 from Z = 0 until max|Z_t - Z_{t-1}| <= tol * max|Z_t| or ``max_iter``.

    The change is measured relative to Z's scale because Z carries lambda-sized values.
    ``backend``: ``numba`` (compiled, threaded), ``scipy`` (CSR products), ``torch`` (CUDA;
    ``device`` another torch device), ``auto`` = numba when installed. A :class:`SortedSystem`
    is iterated in its Morton order. ``sparse_classes`` (auto | on | off, :func:`sparse_choice`)
    keeps at most ``classes_per_point`` classes per point (:mod:`diffuser_lab.backends.sparse`:
    the approximation, its bound and ``info``'s figures of it). The loop, the observer calls and
    the early stop are here, once; a backend (:class:`~diffuser_lab.backends.base.JacobiBackend`)
    only runs the steps.
    """
    name = _resolve_backend(backend)
    inputs = iteration_inputs(system)
    sparse = int(classes_per_point) if sparse_choice(inputs, sparse_classes, classes_per_point, name) else 0
    n = inputs.shape[0]
    residuals: list[float] = []
    converged = False
    it = 0
    seen_buf: Optional[np.ndarray] = None  # what observers see (valid during their call only)
    with _backend(name, inputs, tol, device, sparse, sparse_rel, sparse_refresh) as steps:
        info = {"solver": "jacobi", **steps.details()}
        label = f"diffusion (jacobi, {' '.join(str(v) for v in steps.details().values())}, {n:,} points)"
        if progress.enabled() and steps.compiling:  # a look at numba's cache only when a line can show it
            label += progress.COMPILING
        with progress.stage(label, total=max_iter, unit="it") as bar:
            # run up to the next iteration an observer wants to see without returning to Python, at most
            # SEGMENT_ROW_STEPS row updates (and, while a progress line is shown, progress_chunk() steps)
            # at a time: the steps and their stopping rule do not depend on where the run is split
            segment = max(1, SEGMENT_ROW_STEPS // max(n, 1))
            if bar.enabled:
                segment = min(segment, progress_chunk(max_iter))
            while it < max_iter:
                stop = it + 1
                last = min(max_iter, it + segment)
                while stop < last and not observes(observer, stop):
                    stop += 1
                for change, top in steps.steps(stop - it):
                    it += 1
                    r = residual(change, top)
                    residuals.append(r)
                if bar.enabled:
                    bar.note(f"{'converged, ' if r <= tol else ''}residual {r:.1e}")
                    bar.set(it)
                if observes(observer, it):
                    if seen_buf is None:  # one buffer for all observed iterations: no fresh pages each time
                        seen_buf = np.zeros(inputs.shape, np.float32)
                    show(observer, it, steps.paper_units(seen_buf), r)
                if r <= tol:
                    converged = True
                    break
        Z = steps.paper_units()
        info.update(steps.report())
    return DiffusionResult(Z=Z, iterations=it, converged=converged, residual=residuals[-1] if residuals else 0.0,
                           residuals=residuals, info=info)


def labels_from_scores(Z: np.ndarray) -> np.ndarray:
    """Eq. 16: (N, C) scores -> (N,) int16 argmax; IGNORE where the row is all zero."""
    lab = np.argmax(Z, axis=1).astype(np.int16)
    lab[Z.max(1) <= 0] = IGNORE
    return lab


def solve(system: System, cfg, observer: Optional[Observer] = None) -> DiffusionResult:
    """Dispatch on ``cfg`` (:class:`~diffuser_lab.config.SolverConfig`): the solver and backend."""
    name = getattr(cfg.name, "value", cfg.name)
    backend = getattr(cfg.backend, "value", cfg.backend)
    if name == "jacobi":
        return diffuse(system, max_iter=cfg.max_iter, tol=cfg.tol, observer=observer, backend=backend,
                       sparse_classes=cfg.sparse_classes, classes_per_point=cfg.classes_per_point)
    if name == "exact":
        from .exact import solve_exact

        return solve_exact(system, max_iter=cfg.max_iter, tol=cfg.tol, observer=observer, backend=backend)
    raise ValueError(f"solver.name={name}: expected jacobi or exact")
