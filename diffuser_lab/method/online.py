"""The online Diffuser: frames arrive one at a time and the map's labels follow.

Per frame (:meth:`OnlineDiffuser.add_frame`):

1. growing map only: the frame's depth is back-projected (every ``online.depth_stride``-th pixel)
   and merged on a world-anchored voxel grid (:class:`~diffuser_lab.method.growing.VoxelMap`);
   the new points get normals from the depth image, the evidence of the ``online.revisit``
   frames before (those that see them within the depth check), and the kNN graph (Eqs. 3-4) is
   extended for them and for the old rows they enter
   (:class:`~diffuser_lab.method.growing.IncrementalKnnGraph`), never rebuilt;
2. the frame's pixel-to-point evidence is added (Eqs. 1-2, 11-13) for the points it sees, and
   only those rows (and the rows whose edges changed) of Eqs. 14-15 are renormalised;
3. ``online.steps`` steps warm-started from the previous Z: Jacobi steps of Z <- gamma P Z + B
   (default; on the batch Jacobi's compiled row kernels and threads; they stop early once a step
   changes Z by <= ``solver.tol`` of its largest entry) or GMRES(steps) on (I - gamma P) Z = B
   (``online.solver=gmres``); a frame that adds no evidence and no point changes nothing;
4. labels = argmax (Eq. 16), IGNORE where nothing reached a point.

Why the discount gamma: the batch method stops early (T = ``solver.max_iter`` steps from Z = 0,
Z_T = Sum_{t<T} P^t B), and that early stop is part of it: P is nearly stochastic, so the
undiscounted iteration's fixed point smooths the labels over the whole scene (79 instead of 94
mIoU on scene0470). Warm-started steps frame after frame add up to far more than T, so the plain
iteration drifts towards that fixed point as frames accumulate. The online iteration instead
has the fixed point Sum_t gamma^t P^t B with gamma = 2^(-2/T): half of its weight is on t < T/2,
as for the batch's uniform weight on t < T, and it does not move however many frames come; the
steps of each frame track it (measured on scene0470: its labels equal the batch Z_T's on 99.9%
of the points; docs/online.md).

The map's order: for a given cloud the graph's Morton order (the map's points are the work cloud
re-ordered; :attr:`OnlineDiffuser.map_index` maps the work cloud's rows to them), for a growing
map the order its points were added in. A growing map's state is stored apart from that order,
re-sorted along the Morton curve as the map grows (memory locality: :meth:`OnlineDiffuser._resort`);
everything public is in the map's order. Z is held divided by lambda.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import scipy.sparse as sp

from diffuser_lab.config import BayesianMode, OnlineMap
from diffuser_lab.data.scene import IGNORE, Frame, Taxonomy
from diffuser_lab.method import evidence as evidence_mod
from diffuser_lab.method.diffusion import EDGE_FLOOR, SCORE_FLOOR, labels_from_scores

FLOOR = np.float32(SCORE_FLOOR)
"""Scores (divided by lambda, so of order 1 where evidence is) below this are flushed to zero."""


STEPS_GIVEN = 10
"""Default steps per frame on a given map (``online.steps=null``)."""
STEPS_GROWING = 16
"""... on a growing map: its new points start from Z = 0, not from a warm state."""


RESORT_GROWTH = 1.25
"""Growing map: storage is re-sorted along the Morton curve when the map has grown by this factor
since the last time (and has at least :data:`RESORT_MIN` points)."""
RESORT_MIN = 4096
RHO_TOL = 0.05
"""Growing map: every weight is recomputed (sigma_d = sigma_d_factor * rho) when the map's mean
spacing rho has moved this much (relative) since the last time; new rows use the current sigma_d."""


def discount(horizon: int) -> float:
    """gamma = 2^(-2 / horizon): the discounted fixed point puts half its weight on the first
    horizon / 2 powers of P, as the batch's ``horizon`` steps from Z = 0 do."""
    return float(2.0 ** (-2.0 / max(int(horizon), 1)))


@dataclass
class FrameStats:
    """What one :meth:`OnlineDiffuser.add_frame` did. Times in milliseconds (wall)."""

    index: int
    name: str
    latency_ms: float = 0.0  # the whole update: map, graph, evidence, steps, labels
    map_ms: float = 0.0  # growing: back-projection, voxel merge, normals, graph extension
    evidence_ms: float = 0.0  # evidence and renormalised rows
    steps_ms: float = 0.0  # the Jacobi steps and the labels
    points: int = 0  # points in the map after the frame
    new_points: int = 0
    seen: int = 0  # points that passed the frame's visibility check
    graph_rows: int = 0  # rows whose edges changed (growing)
    steps: int = 0  # Jacobi steps run
    residual: float = 0.0  # the last step's max |Z_t - Z_{t-1}| / max Z_t
    changed: int = 0  # points whose label changed
    skipped: Optional[str] = None  # why the frame was skipped (a bad frame), else None


class OnlineDiffuser:
    """The online Diffuser (module doc) on a given cloud or a growing map.

    Args:
        cfg: the run's :class:`~diffuser_lab.config.Config` (``online``, ``graph``, ``evidence``,
            ``solver``, ``method.bayesian_mode`` are read).
        taxonomy: the class set (C classes).
        points: (N, 3) float32 world metres, the given cloud (``online.map=given``); None for a
            growing map. normals: (N, 3) unit normals of the given cloud or None (estimated).
        backend: ``auto`` (compiled kernels when numba is available) or ``scipy``.
    """

    def __init__(self, cfg, taxonomy: Taxonomy, points: Optional[np.ndarray] = None,
                 normals: Optional[np.ndarray] = None, backend: str = "auto"):
        from diffuser_lab.backends import numba as nb

        self.cfg = cfg
        self.taxonomy = taxonomy
        self.C = taxonomy.num_classes
        oc = cfg.online
        self.growing = oc.map == OnlineMap.growing
        self.horizon = int(oc.horizon or cfg.solver.max_iter)
        self.gamma = float(oc.discount) if oc.discount is not None else discount(self.horizon)
        self.steps = int(oc.steps) if oc.steps is not None else (STEPS_GROWING if self.growing else STEPS_GIVEN)
        self.tol = float(cfg.solver.tol)
        self.lam = float(cfg.evidence.pixel_weight)
        self.depth_tol = float(cfg.evidence.depth_tol)
        self.radius = int(cfg.evidence.pixel_radius)
        self.votes = cfg.method.bayesian_mode == BayesianMode.votes
        self.separate_base = self.votes or self.radius != 0
        self.use_nb = backend != "scipy" and nb.available() and self.C <= 32
        self.solver = getattr(oc.solver, "value", oc.solver)
        self.runner = None
        if self.use_nb:  # products with P on the batch Jacobi's row kernels and threads
            from diffuser_lab.backends.numba.jacobi import StepRunner

            self.runner = StepRunner(1 << 20)
        # Z and B hold only the classes some evidence has named so far (ascending class ids, as the
        # batch's active classes): fewer columns, faster steps; a new class widens them (rare)
        self.active = np.zeros(0, np.int64)
        self.slot = np.full(self.C, -1, np.int64)  # class -> column of Z, B (-1: not active)
        self.width = 0
        self.frames_seen = 0
        self.history: list[FrameStats] = []
        self._n = 0
        self._cap = 0
        self._alloc(0)
        self.revisit = int(getattr(oc, "revisit", 0))
        self._sorted_at = 0
        self._recent: list[Frame] = []  # growing: the last `revisit` frames (new points get their evidence)
        if self.growing:
            from diffuser_lab.data.voxel_map import VoxelMap
            from diffuser_lab.method.growing import IncrementalKnnGraph

            g = cfg.graph
            self.voxels = VoxelMap(oc.voxel_size)
            self.graph = IncrementalKnnGraph(g.k, sigma_s=g.sigma_s, sigma_d=g.sigma_d,
                                             sigma_d_factor=g.sigma_d_factor,
                                             invariant_normals=False, rho_tol=RHO_TOL)
            self.map_index = None
        else:
            if points is None:
                raise ValueError("online.map=given needs the scene's points")
            self._init_given(np.asarray(points, np.float32), normals)

    # -- state -----------------------------------------------------------------------------------
    def _alloc(self, need: int) -> None:
        """Grow the per-point arrays to hold ``need`` rows (capacity doubles; new rows are zero)."""
        if need <= self._cap and self._cap:
            return
        cap = max(need, 2 * self._cap, 1024)
        k = int(self.cfg.graph.k)

        def grow(a, shape, dtype, fill=0):
            out = np.full(shape, fill, dtype)
            if a is not None:
                out[: self._n] = a[: self._n]
            return out

        get = lambda name: getattr(self, name, None)  # noqa: E731
        self._pts = grow(get("_pts"), (cap, 3), np.float32)
        self.mass = grow(get("mass"), (cap, self.C), np.float32)
        self.links = grow(get("links"), (cap,), np.int32)
        if self.separate_base:
            self.base_mass = grow(get("base_mass"), (cap, self.C), np.float32)
            self.base_links = grow(get("base_links"), (cap,), np.int32)
        self.P = grow(get("P"), (cap, k), np.float32)
        self.Pneg = grow(get("Pneg"), (cap, k), np.float32) if self.use_nb else None
        self.B = grow(get("B"), (cap, max(self.width, 1)), np.float32)
        self.Z = grow(get("Z"), (cap, max(self.width, 1)), np.float32)
        self.Zb = np.zeros((cap, max(self.width, 1)), np.float32)  # the compiled Jacobi's second buffer
        self._U = None  # the GMRES basis, (steps + 1, cap, width), made on first use
        self._labels = grow(get("_labels"), (cap,), np.int16, IGNORE)
        self._bayes = grow(get("_bayes"), (cap,), np.int16, IGNORE)
        if self.growing:  # the graph in storage rows, and the map row <-> storage row permutation
            self.nbr = grow(get("nbr"), (cap, k), np.int32)
            self.W = grow(get("W"), (cap, k), np.float32)
            self.wsum = grow(get("wsum"), (cap,), np.float64)
            self._pos = grow(get("_pos"), (cap,), np.int64)
            self._pub = grow(get("_pub"), (cap,), np.int64)
        self._cap = cap

    def _init_given(self, points: np.ndarray, normals: Optional[np.ndarray]) -> None:
        from diffuser_lab.method.graph import SortedKnnGraph, make_graph

        nrm, graph = make_graph(points, normals, self.cfg.graph)
        n = points.shape[0]
        if isinstance(graph, SortedKnnGraph):
            order = graph.order
            nbr, W, wsum = graph.sorted_neighbors, graph.sorted_weights, graph.sorted_row_sums
        else:  # pragma: no cover - build_graph always sorts
            order = np.arange(n)
            nbr, W, wsum = graph.neighbors, graph.weights, graph.weights.sum(1, dtype=np.float64)
        self.order = order  # map row s = work point order[s]
        self.map_index = np.empty(n, np.int64)
        self.map_index[order] = np.arange(n)  # work point i -> map row
        self._alloc(n)
        self._n = n
        self._pts[:n] = points[order]
        self._normals = None if nrm is None else np.asarray(nrm, np.float32)[order]
        self.nbr = np.ascontiguousarray(nbr, np.int32)
        self.W = np.ascontiguousarray(W, np.float32)
        self.wsum = np.ascontiguousarray(wsum, np.float64)
        self.rho, self.sigma_d = graph.rho, graph.sigma_d
        self._renormalise(np.arange(n, dtype=np.int64))

    # -- public views ----------------------------------------------------------------------------
    @property
    def n(self) -> int:
        """Points in the map."""
        return self._n

    def _public(self, a: np.ndarray) -> np.ndarray:
        """Rows of a storage array in the map's order (a read-only view, or a copy on a growing map)."""
        if self.growing:
            return _ro(a[self._pos[: self._n]])
        return _ro(a[: self._n])

    @property
    def points(self) -> np.ndarray:
        """(n, 3) float32 map points, world metres, in the map's order (read-only)."""
        return _ro(self.graph.points) if self.growing else _ro(self._pts[: self._n])

    @property
    def normals(self) -> Optional[np.ndarray]:
        """(n, 3) float32 unit normals of the map points (growing: from the depth images, towards
        the camera that added the point), or None."""
        if self.growing:
            return self.graph.normals
        return self._normals

    @property
    def labels(self) -> np.ndarray:
        """(n,) int16 current labels (IGNORE = nothing reached the point), map order, read-only."""
        return self._public(self._labels)

    @property
    def bayesian_labels(self) -> np.ndarray:
        """(n,) int16 the online Bayesian baseline: argmax of each point's running evidence sum
        (likelihoods or votes, ``method.bayesian_mode``), IGNORE where no frame saw it."""
        return self._public(self._bayes)

    def scores(self) -> np.ndarray:
        """(n, C) float32 Z in the paper's units (a copy; classes no evidence named are 0)."""
        out = np.zeros((self._n, self.C), np.float32)
        na = len(self.active)
        rows = self._pos[: self._n] if self.growing else slice(0, self._n)
        out[:, self.active] = self.Z[rows, :na] * np.float32(self.lam)
        return out

    def base_evidence(self) -> np.ndarray:
        """(n, C) float32 the Bayesian baseline's running evidence sums, map order."""
        return self._public(self.base_mass if self.separate_base else self.mass)

    def evidence(self) -> np.ndarray:
        """(n, C) float32 the method's running evidence sums (Eq. 12 before lambda), map order."""
        return self._public(self.mass)

    # -- one frame -------------------------------------------------------------------------------
    def add_frame(self, frame: Frame, index: Optional[int] = None) -> np.ndarray:
        """Take one frame (its ``labels`` or ``probs`` set: the 2D predictions) and update the
        map; returns the current labels (:attr:`labels`). The frame's checks are the caller's
        (:func:`diffuser_lab.data.validate.check_frame`). :attr:`history` gets its
        :class:`FrameStats`."""
        st = FrameStats(index=self.frames_seen if index is None else int(index), name=str(frame.name))
        t0 = time.perf_counter()
        changed_rows = np.zeros(0, np.int64)
        if self.growing:
            changed_rows = self._grow(frame, st)
        t1 = time.perf_counter()
        n = self._n
        pts = self._pts[:n]
        seen = np.zeros(0, np.int64)
        if n:
            ev = evidence_mod.Evidence(mass=self.mass[:n], links=self.links[:n])
            seen = evidence_mod.add_frame(ev, pts, frame, depth_tol=self.depth_tol, pixel_radius=self.radius)
            if self.separate_base:
                base = evidence_mod.Evidence(mass=self.base_mass[:n], links=self.base_links[:n])
                seen_b = evidence_mod.add_frame(base, pts, frame, depth_tol=self.depth_tol, hard=self.votes)
            else:
                seen_b = seen
            self._update_bayes(seen_b)
        st.seen = int(seen.size)
        if seen.size:
            self._activate(np.flatnonzero((self.mass[seen] > 0).any(0) & (self.slot < 0)))
        rows = np.union1d(seen, changed_rows) if changed_rows.size else seen
        if rows.size:
            self._renormalise(rows)
        t2 = time.perf_counter()
        if rows.size:  # a frame that adds nothing (no evidence, no point) changes nothing
            st.steps, st.residual, st.changed = self._diffuse()
        t3 = time.perf_counter()
        if self.growing and n >= RESORT_GROWTH * max(self._sorted_at, RESORT_MIN):
            self._resort()  # counted in this frame's latency
            t3 = time.perf_counter()
        st.points = n
        st.map_ms, st.evidence_ms, st.steps_ms = (t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3
        st.latency_ms = (t3 - t0) * 1e3
        self.frames_seen += 1
        self.history.append(st)
        return self.labels

    def skip_frame(self, frame_name: str, why: str, index: Optional[int] = None) -> FrameStats:
        """Note a frame that was not taken (a bad frame); nothing changes."""
        st = FrameStats(index=self.frames_seen if index is None else int(index), name=str(frame_name),
                        points=self._n, skipped=why)
        self.frames_seen += 1
        self.history.append(st)
        return st

    # -- the parts -------------------------------------------------------------------------------
    def _grow(self, frame: Frame, st: FrameStats) -> np.ndarray:
        """Back-project and merge the frame's depth; extend the graph. Returns the rows whose
        edges changed (new rows included)."""
        from diffuser_lab.data.geometry import backproject

        oc = self.cfg.online
        depth = frame.depth
        if oc.max_depth is not None:
            depth = np.where(depth <= oc.max_depth, depth, 0).astype(np.float32)
        # the strided image (every depth_stride-th pixel) with its own intrinsics: the same points as
        # backproject(..., stride) and normals at a quarter of the cost at stride 2
        st_px = int(oc.depth_stride)
        small = np.ascontiguousarray(depth[::st_px, ::st_px])
        K = np.asarray(frame.K, np.float64).copy()
        K[:2] /= st_px
        pts, pix = backproject(small, K, frame.T_cw)
        fresh = ~self.voxels.occupied(pts)  # the others are dropped by the merge: no normals for them
        pts, pix = pts[fresh], pix[fresh]
        nrm = None
        if pts.shape[0] and self.cfg.graph.use_normals:
            nrm = frame_normals(small, K, frame.T_cw, pix, window=3 if st_px > 1 else 5)
        new_pts, new_nrm = self.voxels.insert(pts, nrm)
        m = new_pts.shape[0]
        st.new_points = m
        if m == 0:
            return np.zeros(0, np.int64)
        n0 = self._n
        self._alloc(n0 + m)
        self._pts[n0 : n0 + m] = new_pts  # new map rows n0.. go to storage rows n0.. (the end)
        self._pos[n0 : n0 + m] = np.arange(n0, n0 + m)
        self._pub[n0 : n0 + m] = np.arange(n0, n0 + m)
        self._n = n0 + m
        changed = np.asarray(self.graph.add(new_pts, new_nrm), np.int64)
        g, pos = self.graph, self._pos
        srows = pos[changed]  # the changed rows in storage
        self.nbr[srows] = pos[g.neighbors[changed]]
        self.W[srows] = g.weights[changed]
        self.wsum[srows] = g.row_sums[changed]
        self.rho, self.sigma_d = g.rho, g.sigma_d
        st.graph_rows = int(changed.size)
        self._revisit(n0, m)
        self._recent.append(frame)
        if len(self._recent) > self.revisit:
            self._recent.pop(0)
        return np.sort(srows)

    def _resort(self) -> None:
        """Growing map: re-order storage along the Morton curve of the points (rows appended frame
        by frame lose memory locality; measured: 16 Jacobi steps on 81k points 29.7 -> 16.4 ms). The
        map's own order (and everything public) stays as it is."""
        from diffuser_lab.data.geometry import spatial_order

        n = self._n
        order = spatial_order(self._pts[:n])  # new storage row s = old storage row order[s]
        inv = np.empty(n, np.int64)
        inv[order] = np.arange(n)
        arrays = ["_pts", "mass", "links", "P", "B", "Z", "_labels", "_bayes", "W", "wsum", "_pub"]
        arrays += ["base_mass", "base_links"] if self.separate_base else []
        arrays += ["Pneg"] if self.Pneg is not None else []
        for name in arrays:
            a = getattr(self, name)
            a[:n] = a[:n][order]
        self.nbr[:n] = inv[self.nbr[:n][order]]
        self._pos[:n] = inv[self._pos[:n]]
        self._sorted_at = n

    def _revisit(self, n0: int, m: int) -> None:
        """Give the new rows n0..n0+m-1 the evidence of the ``online.revisit`` frames before this one
        (those that see them pass the same depth check): a point is added by the first frame whose
        depth lands in its voxel, but earlier frames may see it within ``evidence.depth_tol``."""
        if not self._recent or m == 0:
            return
        pts = self._pts[n0 : n0 + m]
        ev = evidence_mod.Evidence(mass=self.mass[n0 : n0 + m], links=self.links[n0 : n0 + m])
        base = (evidence_mod.Evidence(mass=self.base_mass[n0 : n0 + m], links=self.base_links[n0 : n0 + m])
                if self.separate_base else None)
        for f in self._recent:
            seen = evidence_mod.add_frame(ev, pts, f, depth_tol=self.depth_tol, pixel_radius=self.radius)
            if base is not None:
                evidence_mod.add_frame(base, pts, f, depth_tol=self.depth_tol, hard=self.votes)
            if seen.size:
                self._activate(np.flatnonzero((self.mass[n0 + seen] > 0).any(0) & (self.slot < 0)))
        self._update_bayes(np.arange(n0, n0 + m))

    def _activate(self, new: np.ndarray) -> None:
        """Give the classes ``new`` columns in Z and B (kept in ascending class order)."""
        if new.size == 0:
            return
        old_active, old_slot = self.active, self.slot
        self.active = np.union1d(old_active, new).astype(np.int64)
        self.slot = np.full(self.C, -1, np.int64)
        self.slot[self.active] = np.arange(len(self.active))
        na = len(self.active)
        width = na
        if self.use_nb:  # the row kernels' class-block widths (8, 16, 24, 32)
            from diffuser_lab.backends.numba.jacobi import blocks_of

            width = blocks_of(na)[0][2]
        cols = self.slot[old_active]  # where the old columns go
        cap = self._cap
        Z, B = np.zeros((cap, width), np.float32), np.zeros((cap, width), np.float32)
        n = self._n
        if len(old_active):
            Z[:n, cols] = self.Z[:n, : len(old_active)]
            B[:n, cols] = self.B[:n, : len(old_active)]
        self.Z, self.B, self.Zb, self._U = Z, B, np.zeros((cap, width), np.float32), None
        self.width = width

    def _update_bayes(self, rows: np.ndarray) -> None:
        if rows.size == 0:
            return
        self._bayes[rows] = labels_from_scores((self.base_mass if self.separate_base else self.mass)[rows])

    def _renormalise(self, rows: np.ndarray) -> None:
        """Rows ``rows`` of Eqs. 14-15 (P with the discount folded in, B divided by lambda)."""
        n = self._n
        if self.use_nb:
            from diffuser_lab.backends.numba.online import renormalise_rows

            renormalise_rows(rows, self.W, self.wsum, self.mass[:n], self.lam, self.gamma, np.float32(EDGE_FLOOR),
                             self.slot, self.P[:n], self.B[:n], self.Pneg[:n])
            return
        m = self.mass[rows]
        den = self.wsum[rows].astype(np.float32) + np.float32(self.lam) * m.sum(1)
        inv = np.divide(1.0, den, out=np.zeros_like(den), where=den > 1e-30).astype(np.float32)
        p = self.W[rows] * inv[:, None]
        self.P[rows] = np.where(p >= np.float32(EDGE_FLOOR), p * np.float32(self.gamma), 0).astype(np.float32)
        na = len(self.active)
        if na:
            self.B[rows, :na] = m[:, self.active] * inv[:, None]

    def _diffuse(self) -> tuple[int, float, int]:
        """The frame's steps (``online.solver``); labels. Returns (steps done, relative residual
        of (I - gamma P) Z = B after them, labels changed)."""
        if len(self.active) == 0:  # no evidence anywhere yet: Z stays 0
            return 0, 0.0, 0
        if self.solver == "jacobi":
            return self._jacobi()
        return self._gmres()

    def _parts(self) -> int:
        """Fixed row chunks of the compiled passes (sums add up in the same order every run)."""
        return max(1, min(64, self._n // 2048 + 1))

    def _gmres(self) -> tuple[int, float, int]:
        """GMRES(m), m = ``online.steps``, warm-started from Z, on (I - gamma P) Z = B, each class
        column on its own (m + 1 products with P, classical Gram-Schmidt, float64 sums); Z is
        clamped at 0 after it. GMRES minimises the residual over the m-step Krylov space, so it
        gets closer to the fixed point in m products than m Jacobi steps (measured, docs/online.md).

        The basis is stored unnormalised: v_i = s_i U_i (per column), U_{j+1} = A U_j minus its
        projections, so each product is one call of the row kernel (A U = U + (-P) U)."""
        n, m, W = self._n, self.steps, self.width
        na = len(self.active)
        if self._U is None or self._U.shape[1] < self._cap:
            self._U = np.zeros((m + 1, self._cap, W), np.float32)
        U = self._U[:, :n]
        nbr, P, Z, B = self.nbr[:n], self.P[:n], self.Z[:n], self.B[:n]
        s = np.zeros((m + 1, W))
        H = np.zeros((W, m + 1, m))
        nofloor = np.float32(-np.inf)
        if self.use_nb:
            from diffuser_lab.backends.numba import online as kern

            parts = self._parts()
            sq = np.zeros((parts, W))
            dots = np.zeros((parts, m + 1, W))
            Pneg = self.Pneg[:n]
            self.runner.run(W, nbr, P, Z, U[0], B - Z, nofloor, -1.0, 1)  # R = P Z + (B - Z)
            beta = np.sqrt(np.square(U[0], dtype=np.float64).sum(0))
        else:
            A = self._csr(n)
            U[0] = B - Z + A @ Z
            beta = np.sqrt(np.square(U[0], dtype=np.float64).sum(0))
        s[0] = np.divide(1.0, beta, out=np.zeros(W), where=beta > 0)
        tiny = 1e-7 * beta
        for j in range(m):
            if self.use_nb:
                self.runner.run(W, nbr, Pneg, U[j], U[j + 1], U[j], nofloor, -1.0, 1)  # X = A U_j
                kern.gmres_dots(U[j + 1], U, j, parts, dots)
                g = dots[:, : j + 1].sum(0)  # <X, U_i>
            else:
                U[j + 1] = U[j] - A @ U[j]
                g = np.einsum("rc,irc->ic", U[j + 1], U[: j + 1], dtype=np.float64)
            # h_ij = <A v_j, v_i> = s_j s_i <X, U_i>; X -= Sum_i (h_ij s_i / s_j) U_i = Sum_i s_i^2 g_i U_i
            h = s[j] * s[: j + 1] * g
            coef = np.square(s[: j + 1]) * g
            if self.use_nb:
                kern.gmres_orthogonalise(U, j, coef, n, parts, sq)
                xn = np.sqrt(sq.sum(0))
            else:
                U[j + 1] -= np.einsum("ic,irc->rc", coef.astype(np.float32), U[: j + 1])
                xn = np.sqrt(np.square(U[j + 1], dtype=np.float64).sum(0))
            hn = s[j] * xn  # |A v_j - projections|
            H[:, : j + 1, j] = h.T
            H[:, j + 1, j] = hn
            s[j + 1] = np.divide(1.0, xn, out=np.zeros(W), where=hn > tiny)
        e1 = np.zeros((W, m + 1))
        e1[:, 0] = beta
        y = (np.linalg.pinv(H) @ e1[:, :, None])[:, :, 0]  # (W, m): least squares, rank-deficient safe
        res = np.linalg.norm(e1 - (H @ y[:, :, None])[:, :, 0], axis=1)
        bn = np.sqrt(np.square(B, dtype=np.float64).sum(0))
        rel = float(res.max() / bn.max()) if bn.max() > 0 else 0.0
        ys = np.ascontiguousarray(y.T * s[:m])  # (m, W): coefficients of the stored basis
        if self.use_nb:
            changed = int(kern.gmres_combine(Z, U, ys, m, self.active, self._labels[:n], parts))
        else:
            Z += np.einsum("jc,jrc->rc", ys.astype(np.float32), U[:m])
            np.maximum(Z, 0, out=Z)
            changed = self._labels_numpy(n)
        return m, rel, changed

    def _csr(self, n: int) -> sp.csr_matrix:
        k = self.nbr.shape[1]
        return sp.csr_matrix((self.P[:n].ravel(), self.nbr[:n].ravel(), np.arange(0, n * k + 1, k)), shape=(n, n))

    def _labels_numpy(self, n: int) -> int:
        lab = labels_from_scores(self.Z[:n, : len(self.active)])  # column ids, IGNORE where nothing came
        lab = np.where(lab == IGNORE, IGNORE, self.active[np.maximum(lab, 0)]).astype(np.int16)
        changed = int(np.count_nonzero(lab != self._labels[:n]))
        self._labels[:n] = lab
        return changed

    def _jacobi(self) -> tuple[int, float, int]:
        """``online.solver=jacobi``: up to ``steps`` warm-started steps of Z <- gamma P Z + B (the
        paper's iteration, discounted), stopping once a step changes Z by <= ``solver.tol`` of its
        largest entry; on the batch Jacobi's compiled threads, or scipy products."""
        n = self._n
        Z, B = self.Z[:n], self.B[:n]
        if self.use_nb:
            from diffuser_lab.backends.numba import online as kern

            out = self.runner.run(self.width, self.nbr[:n], self.P[:n], Z, self.Zb[:n], B, FLOOR, self.tol, self.steps)
            if len(out) % 2:  # the last state is in the second buffer
                self.Z, self.Zb = self.Zb, self.Z
                Z = self.Z[:n]
            r = float(out[-1, 0] / out[-1, 1]) if out[-1, 1] > 0 else 0.0
            changed = int(kern.argmax_rows(Z, len(self.active), self.active, self._labels[:n]))
            return len(out), r, changed
        A = self._csr(n)
        done, r = 0, 0.0
        for _ in range(self.steps):
            Zn = A @ Z + B
            Zn[Zn < FLOOR] = 0
            top = float(Zn.max()) if Zn.size else 0.0
            r = float(np.abs(Zn - Z).max()) / top if top > 0 else 0.0
            Z[:] = Zn
            done += 1
            if r <= self.tol:
                break
        return done, r, self._labels_numpy(n)

    def close(self) -> None:
        """Release the working memory and threads (the state stays readable)."""
        self._U = None
        if self.runner is not None:
            self.runner.close()
            self.runner = None


def frame_normals(depth: np.ndarray, K: np.ndarray, T_cw: np.ndarray, pix: np.ndarray, window: int = 5) -> np.ndarray:
    """(P, 3) float32 unit world normals at the pixels ``pix`` (P, 2) (row, col) of a (H, W) depth
    image (metres, 0 = none) with intrinsics K and world-to-camera T_cw: central differences (one-
    sided where a neighbour has no depth) of the depth box-smoothed over ``window`` pixels, as
    :func:`diffuser_lab.data.sensor.normals_from_depth` computes them, but only at ``pix``; turned
    towards the camera."""
    from diffuser_lab.data.sensor import box_smoothed_depth

    smooth = box_smoothed_depth(np.asarray(depth, np.float32), window)
    h, w = smooth.shape
    r, c = pix[:, 0].astype(np.int64), pix[:, 1].astype(np.int64)
    K = np.asarray(K, np.float64)

    def point(rr, cc):  # camera-frame point at (rr, cc) (clipped to the image) and whether it has depth
        rr, cc = np.clip(rr, 0, h - 1), np.clip(cc, 0, w - 1)
        z = smooth[rr, cc].astype(np.float64)
        P = np.stack([(cc - K[0, 2]) / K[0, 0] * z, (rr - K[1, 2]) / K[1, 1] * z, z], 1)
        return P, z > 0

    P0, ok0 = point(r, c)

    def diff(dr, dc, size):
        pos = r + dr if dr else c + dc
        Pf, okf = point(r + dr, c + dc)
        Pb, okb = point(r - dr, c - dc)
        okf &= ok0 & (pos < size)
        okb &= ok0 & ((r - dr if dr else c - dc) >= 0)
        g = np.where((okf & okb)[:, None], 0.5 * (Pf - Pb), np.where(okf[:, None], Pf - P0, P0 - Pb))
        return np.where((okf | okb)[:, None], g, 0.0)

    n_cam = np.cross(diff(0, 1, w), diff(1, 0, h))
    n_cam *= np.where(n_cam[:, 2:3] > 0, -1.0, 1.0)  # towards the camera (it looks along +z)
    R_wc = np.asarray(T_cw, np.float64)[:3, :3].T
    out = n_cam @ R_wc.T
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.where(norm > 0, out / np.maximum(norm, 1e-30), np.array([0.0, 0.0, 1.0])).astype(np.float32)


def _ro(a: np.ndarray) -> np.ndarray:
    v = a.view()
    v.flags.writeable = False
    return v
