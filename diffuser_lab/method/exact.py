"""The exact fixed point of Eq. 10, (I - P) Z = B (``solver=exact``): what the diffusion would
reach with no early stop. It scores far below the paper's early-stopped iteration (on scene0470
79 against 94 mIoU): the early stop is part of the method; this is the yardstick.

With ``solver.tikhonov`` (:func:`tikhonov_scale`) the system carries Splat Feature Solver's
Tikhonov term toward each point's own average: lifting as a sparse linear inverse problem solved
in closed form."""
from __future__ import annotations

from typing import Optional

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla

from diffuser_lab import progress
from diffuser_lab.backends import resolve_backend

from .diffusion import DiffusionResult, Observer, System, observes, show

def tikhonov_scale(graph, links: np.ndarray, pixel_weight: float, t: float) -> np.ndarray:
    """(N,) float32 row factors that put a Tikhonov term toward each point's per-point average into
    Eqs. 14-15: Splat Feature Solver (Xiong et al., ICLR 2026, arXiv 2508.12216), Sec. 3, the lifting
    as a sparse linear inverse problem with its Tikhonov guidance, (A^T A + mu I) x = A^T b + mu x_0
    ("soft diagonal dominance"), here with A^T A the graph's Laplacian plus the pixel term and x_0 the
    per-point average of the pixel vectors.

    The fixed point of Eq. 10 minimises (for a symmetric G)
        1/2 Sum_ij G_ij |z_i - z_j|^2 + lambda Sum_i Sum_(p -> i) |z_i - y_p|^2 ;
    the term t d_i |z_i - mean_i|^2 with d_i = Sum_j G_ij + lambda n_i (row i's diagonal; n_i its pixel
    links, mean_i = E_i / n_i) adds t d_i to the diagonal and t d_i mean_i to the right-hand side:
    row i becomes (1 + t) d_i z_i - Sum_j G_ij z_j = lambda E_i + t d_i E_i / n_i. That is Eqs. 14-15
    with the pixel mass E_i and count n_i both multiplied by

        alpha_i = 1 + t d_i / (lambda n_i)     (1 where n_i = 0: no average to pull toward),

    so the core solves it unchanged (features: :func:`~diffuser_lab.method.features.encode` of alpha F
    and alpha n is alpha times the encoded row). t = 0: Eq. 10's fixed point; t -> inf: each point's
    average (the Bayesian evidence, where a point has evidence)."""
    links = np.asarray(links, np.float64)
    if hasattr(graph, "sorted_row_sums"):
        wsum = np.empty(graph.n, np.float64)
        wsum[graph.order] = graph.sorted_row_sums
    else:
        wsum = graph.weights.sum(1, dtype=np.float64)
    lam = float(pixel_weight)
    d = wsum + lam * links
    alpha = np.ones(links.shape[0], np.float64)
    seen = links > 0
    alpha[seen] = 1.0 + float(t) * d[seen] / (lam * links[seen])
    return alpha.astype(np.float32)


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
    backend = resolve_backend(backend)
    if backend == "torch":
        raise RuntimeError("solver=exact runs on the CPU (scipy); use solver.backend=auto with it")
    active = system.active
    full_shape = (system.n, system.num_classes)
    n = full_shape[0]
    scale = float(system.default_scale())
    order = np.arange(n) if system.order is None else system.order
    indptr, indices, data = system.sorted_csr()
    P = sp.csr_matrix((data.astype(np.float64), indices.copy(), indptr.copy()), shape=(n, n))
    P.eliminate_zeros()
    B = system.B_rows[:, active].astype(np.float64) / scale
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
