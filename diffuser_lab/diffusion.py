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

from . import progress
from .graph import KnnGraph, SortedKnnGraph
from .scene import IGNORE

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
    (:class:`~diffuser_lab.graph.SortedKnnGraph`); ``P`` in the caller's order is built on first
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
        from . import kernels

        if kernels.available():
            from .knn import normalise_sorted

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


def _blocks(n_active: int) -> list[tuple[int, int, int]]:
    """Split the active classes into kernel blocks: (first, count, width) with width in WIDTHS."""
    from .kernels import WIDTHS

    out, c = [], 0
    while c < n_active:
        cnt = min(n_active - c, WIDTHS[-1])
        width = next(w for w in WIDTHS if w >= cnt)
        out.append((c, cnt, width))
        c += cnt
    return out


def _resolve_backend(backend: str) -> str:
    from . import kernels

    backend = getattr(backend, "value", backend)
    if backend == "auto":
        return "numba" if kernels.available() else "scipy"
    if backend == "numba" and not kernels.available():
        raise RuntimeError("solver.backend=numba: numba is not installed (pip install 'diffuser-lab[fast]') "
                           "or DIFFUSER_LAB_NUMBA=0 is set")
    if backend not in ("numba", "scipy", "torch"):
        raise ValueError(f"solver.backend={backend}: expected auto, scipy, numba or torch")
    return backend


def iteration_inputs(system: System):
    """What every Jacobi backend iterates on: the classes any pixel voted for (the others stay
    exactly zero), the (N, C) shape, the scale max(B) the iteration divides out (see module doc),
    the Morton order or None, the CSR arrays (int64 indptr, int32 indices, float32 data) in
    that order, and B rows in that order."""
    active = np.flatnonzero(system.B.any(0))
    b_max = float(system.B.max()) if system.B.size else 0.0
    scale = np.float32(b_max if b_max > 0 else 1.0)
    if isinstance(system, SortedSystem):
        return active, system.B.shape, scale, system.order, system.sorted_csr(), system.B[system.order]
    P = system.P.tocsr()
    csr = (P.indptr.astype(np.int64), P.indices.astype(np.int32), P.data.astype(np.float32))
    return active, system.B.shape, scale, None, csr, system.B


SEGMENT_ROW_STEPS = 20_000_000
"""The compiled Jacobi runs at most this many row updates (~0.5-1 s) before returning to Python,
so that Ctrl-C and observers are never far away."""


def progress_chunk(max_iter: int) -> int:
    """Iterations between two updates of the diffusion's progress line (only while it is shown:
    the compiled Jacobi then returns to Python this often; the result does not change)."""
    return max(10, max_iter // 20)


def diffuse(system: System, *, max_iter: int = 200, tol: float = 1e-4,
            observer: Optional[Observer] = None, backend: str = "auto") -> DiffusionResult:
    """Iterate Eq. 10 from Z = 0 until max|Z_t - Z_{t-1}| <= tol * max|Z_t| or ``max_iter``.

    The change is measured relative to Z's scale because Z carries lambda-sized values.
    ``backend``: ``numba`` (compiled, threaded), ``scipy`` (CSR products), ``torch`` (CUDA),
    ``auto`` = numba when installed. A :class:`SortedSystem` is iterated in its Morton order.
    """
    backend = _resolve_backend(backend)
    if backend == "torch":
        from .gpu import diffuse_torch

        return diffuse_torch(system, max_iter=max_iter, tol=tol, observer=observer)
    active, full_shape, scale, order, (indptr, indices, data), B_src = iteration_inputs(system)
    n = full_shape[0]
    floor = np.float32(SCORE_FLOOR)
    residuals: list[float] = []
    converged = False
    it = 0

    runner = None
    name = f"diffusion (jacobi, {backend}, {n:,} points)"
    if backend == "numba":
        from . import kernels

        blocks = []
        for first, cnt, width in _blocks(len(active)):
            Bb = np.zeros((n, width), np.float32)
            Bb[:, :cnt] = B_src[:, active[first:first + cnt]] / scale  # iterate on Z / max(B), see module doc
            blocks.append([first, cnt, width, Bb, np.zeros_like(Bb), np.zeros_like(Bb)])
        nbr, wts = kernels.fixed_rows(indptr, indices, data)
        if progress.enabled() and blocks and kernels.first_compile(
                *{kernels._step_kernels()[b[2]] for b in blocks}):
            name += progress.COMPILING
        runner = kernels.StepRunner(n)
        ident = np.arange(n, dtype=np.int64) if order is None else order

        def paper_units(out: Optional[np.ndarray] = None) -> np.ndarray:
            Z_full = np.zeros(full_shape, np.float32) if out is None else out  # out: inactive columns stay 0
            for first, cnt, width, _, Z, _ in blocks:
                kernels.unpermute_scaled(Z, ident, active[first:first + cnt].astype(np.int64), scale, Z_full)
            return Z_full

        def steps(count: int) -> np.ndarray:
            """Up to ``count`` steps (fewer when converged): (steps done, 2) change, top."""
            if len(blocks) == 1:  # all steps in compiled code, no GIL needed between them
                blk = blocks[0]
                out = runner.run(blk[2], nbr, wts, blk[4], blk[5], blk[3], floor, tol, count)
                if len(out) % 2:
                    blk[4], blk[5] = blk[5], blk[4]
                return out
            out = []
            for _ in range(count):  # several class blocks share one residual: a step at a time
                ct = np.zeros(2, np.float32)
                for blk in blocks:
                    ct = np.maximum(ct, runner.run(blk[2], nbr, wts, blk[4], blk[5], blk[3], floor, -1.0, 1)[0])
                    blk[4], blk[5] = blk[5], blk[4]
                out.append(ct)
                if (float(ct[0]) / float(ct[1]) if ct[1] > 0 else 0.0) <= tol:  # as the residual below
                    break
            return np.array(out, np.float32).reshape(-1, 2)
    else:
        Pm = sp.csr_matrix((data, indices, indptr), shape=(n, n), copy=True)  # never alias the system
        Pm.eliminate_zeros()
        B = np.ascontiguousarray(B_src[:, active]) / scale  # iterate on Z / max(B), see module doc
        state = {"Z": np.zeros_like(B)}

        def paper_units(out: Optional[np.ndarray] = None) -> np.ndarray:
            Z_full = np.zeros(full_shape, np.float32) if out is None else out  # out: inactive columns stay 0
            if order is None:
                Z_full[:, active] = state["Z"] * scale
            else:
                tmp = np.zeros(full_shape, np.float32)
                tmp[:, active] = state["Z"] * scale
                Z_full[order] = tmp
            return Z_full

        def steps(count: int) -> np.ndarray:
            out = []
            for _ in range(count):
                Z = state["Z"]
                Z_new = Pm @ Z
                Z_new += B
                np.multiply(Z_new, Z_new >= floor, out=Z_new)
                top = float(Z_new.max()) if Z_new.size else 0.0  # Z >= 0 throughout
                change = float(np.abs(Z_new - Z).max()) if Z_new.size else 0.0
                state["Z"] = Z_new
                out.append((change, top))
                if (change / top if top > 0 else 0.0) <= tol:
                    break
            return np.array(out, np.float32).reshape(-1, 2)

    seen_buf: Optional[np.ndarray] = None  # what observers see (valid during their call only)
    try:
        with progress.stage(name, total=max_iter, unit="it") as bar:
            # while shown, the run returns to Python every progress_chunk() iterations to update it
            # (the steps and their stopping rule do not depend on where the run is split)
            segment = max(1, SEGMENT_ROW_STEPS // max(n, 1))
            if bar.enabled:
                segment = min(segment, progress_chunk(max_iter))
            while it < max_iter:
                # run up to the next iteration an observer wants to see, without returning to Python
                stop = it + 1
                last = min(max_iter, it + segment)
                while stop < last and not observes(observer, stop):
                    stop += 1
                for change, top in steps(stop - it):
                    it += 1
                    residual = float(change) / float(top) if top > 0 else 0.0
                    residuals.append(residual)
                if bar.enabled:
                    bar.note(f"{'converged, ' if residual <= tol else ''}residual {residual:.1e}")
                    bar.set(it)
                if observes(observer, it):
                    if seen_buf is None:  # one buffer for all observed iterations: no fresh pages each time
                        seen_buf = np.zeros(full_shape, np.float32)
                    show(observer, it, paper_units(seen_buf), residual)
                if residual <= tol:
                    converged = True
                    break
    finally:
        if runner is not None:
            runner.close()
    return DiffusionResult(Z=paper_units(), iterations=it, converged=converged,
                           residual=residuals[-1] if residuals else 0.0, residuals=residuals,
                           info={"solver": "jacobi", "backend": backend})


EXACT_DIRECT_MAX = 1_000_000
"""solver=exact factorises I - P (SuperLU) up to this many reachable points, else GMRES + ILU."""


def solve_exact(system: System, *, max_iter: int = 200, tol: float = 1e-4,
                observer: Optional[Observer] = None, backend: str = "auto") -> DiffusionResult:
    """The fixed point of Eq. 10 directly: (I - P) Z = B, in float64.

    Only points from which some evidence can be reached through the graph are solved for
    (elsewhere the fixed point is Z = 0, as Jacobi leaves it, and I - P is singular). Up to
    :data:`EXACT_DIRECT_MAX` of them the system is factorised once (SuperLU, COLAMD ordering)
    and solved for every class; above, each class is solved by restarted GMRES with an
    incomplete-LU preconditioner to ``tol`` relative residual in at most ``max_iter`` iterations.
    ``residual`` is max over classes of |B_c - (I - P) Z_c| / |B_c|. The observer sees the
    result once, as iteration 1.
    """
    import scipy.sparse.csgraph as csgraph
    import scipy.sparse.linalg as spla

    backend = _resolve_backend(backend)
    if backend == "torch":
        raise RuntimeError("solver=exact runs on the CPU (scipy); use solver.backend=auto with it")
    active = np.flatnonzero(system.B.any(0))
    full_shape = system.B.shape
    n = full_shape[0]
    b_max = float(system.B.max()) if system.B.size else 0.0
    scale = b_max if b_max > 0 else 1.0
    if isinstance(system, SortedSystem):
        order = system.order
        indptr, indices, data = system.sorted_csr()
        P = sp.csr_matrix((data.astype(np.float64), indices.copy(), indptr.copy()), shape=(n, n))
        P.eliminate_zeros()
        B = system.B[order][:, active].astype(np.float64) / scale
    else:
        order = np.arange(n)
        P = system.P.astype(np.float64).tocsr()
        B = system.B[:, active].astype(np.float64) / scale
    with progress.stage(f"diffusion (exact, {n:,} points)"):
        # points that reach evidence: breadth-first search from a virtual node linked to every
        # evidence point, along the reversed edges (j -> i where P_ij > 0)
        src = np.flatnonzero(B.any(1))
        PT = P.T.tocsr()
        virt = sp.csr_matrix((np.ones(src.size), src, [0, src.size]), shape=(1, n + 1))
        G = sp.vstack([sp.hstack([PT, sp.csr_matrix((n, 1))]), virt]).tocsr()
        reach = np.zeros(n, bool)
        if src.size:
            seen = csgraph.breadth_first_order(G, n, directed=True, return_predecessors=False)
            reach[seen[seen < n]] = True
        R = np.flatnonzero(reach)
        A = (sp.identity(R.size, format="csr") - P[R][:, R]).tocsc()
        BR = B[R]
        Z = np.zeros_like(BR)
        info: dict = {"solver": "exact", "backend": "scipy", "points_solved": int(R.size)}
        krylov = 0
        converged = True
        if R.size and active.size:
            if R.size <= EXACT_DIRECT_MAX:
                lu = spla.splu(A, permc_spec="COLAMD")
                Z = lu.solve(BR)
                info["method"] = "splu"
            else:
                ilu = spla.spilu(A, drop_tol=1e-5, fill_factor=10)
                M = spla.LinearOperator(A.shape, ilu.solve)
                Acsr = A.tocsr()
                for c in range(BR.shape[1]):
                    its = [0]

                    def count(_):
                        its[0] += 1

                    z, flag = spla.gmres(Acsr, BR[:, c], rtol=tol, restart=50, maxiter=max_iter, M=M,
                                         callback=count, callback_type="pr_norm")
                    Z[:, c] = z
                    krylov = max(krylov, its[0])
                    converged &= flag == 0
                info["method"] = "gmres+ilu"
                info["krylov_iterations"] = krylov
        Acsr = A.tocsr()
        res = 0.0
        for c in range(BR.shape[1]):
            nb = np.linalg.norm(BR[:, c])
            if nb > 0:
                res = max(res, float(np.linalg.norm(BR[:, c] - Acsr @ Z[:, c]) / nb))
    np.maximum(Z, 0.0, out=Z)  # the fixed point is non-negative; clip round-off
    Z_full = np.zeros(full_shape, np.float32)
    Z_full[np.ix_(order[R], active)] = (Z * scale).astype(np.float32)
    if observes(observer, 1):
        show(observer, 1, Z_full.copy(), res)
    return DiffusionResult(Z=Z_full, iterations=max(krylov, 1), converged=bool(converged), residual=res,
                           residuals=[res], info=info)


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
        return diffuse(system, max_iter=cfg.max_iter, tol=cfg.tol, observer=observer, backend=backend)
    if name == "exact":
        return solve_exact(system, max_iter=cfg.max_iter, tol=cfg.tol, observer=observer, backend=backend)
    raise ValueError(f"solver.name={name}: expected jacobi or exact")
