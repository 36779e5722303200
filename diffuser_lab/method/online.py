"""The online Diffuser: frames arrive one at a time and the map's labels follow.

Per frame (:meth:`OnlineDiffuser.add_frame`):

1. growing map only: the frame's depth is back-projected (every ``online.depth_stride``-th pixel)
   and merged on a world-anchored voxel grid (:class:`~diffuser_lab.data.voxel_map.VoxelMap`);
   the new points get normals from the depth image, the evidence of the ``online.revisit``
   frames before (those that see them within the depth check), and the kNN graph (Eqs. 3-4) is
   extended for them and for the old rows they enter
   (:class:`~diffuser_lab.method.growing.IncrementalKnnGraph`), never rebuilt;
2. the frame's pixel-to-point evidence is added (Eqs. 1-2, 11-13) for the points it sees
   (:class:`~diffuser_lab.method.evidence.RunEvidence`, as in batch runs), and only those rows
   (and the rows whose edges changed) of Eqs. 14-15 are renormalised;
3. ``online.steps`` steps warm-started from the previous Z: Jacobi steps of Z <- gamma P Z + B
   (default; they stop early once a step changes Z by <= ``solver.tol`` of its largest entry) or
   GMRES(steps) on (I - gamma P) Z = B (``online.solver=gmres``); a frame that adds no evidence
   and no point changes nothing;
4. labels = argmax (Eq. 16), IGNORE where nothing reached a point.

Steps 2-4 are the one diffusion core's (:class:`~diffuser_lab.method.diffusion.System`, the
discount folded into P) on the backend ``solver.backend`` names, as a batch run's: compiled for
any number of classes, ``solver.sparse_classes``, torch.

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
map the order its points were added in (points and evidence are kept in it). A growing map's
system rows are re-sorted along the Morton curve as the map grows (memory locality:
:meth:`OnlineDiffuser._resort`, :meth:`~diffuser_lab.method.diffusion.System.move`); everything
public is in the map's order. The iteration runs on Z / lambda.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from diffuser_lab.backends.base import union_rows
from diffuser_lab.backends.morton import spatial_order
from diffuser_lab.config import OnlineMap, OnlineSolver, SolverBackend
from diffuser_lab.data.geometry import backproject, normals_from_depth
from diffuser_lab.data.scene import IGNORE, Frame, Taxonomy
from diffuser_lab.data.voxel_map import VoxelMap
from diffuser_lab.method.diffusion import System, labels_from_scores
from diffuser_lab.method.evidence import RunEvidence
from diffuser_lab.method.graph import make_graph
from diffuser_lab.method.growing import IncrementalKnnGraph

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
ROWS_HINT = 1 << 20
"""The online system's backend is sized (threads) as for this many rows: a map may start small."""


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
    idle_steps: int = 0  # extra steps in the time the sensor left before the next frame (not in latency_ms)
    idle_ms: float = 0.0


class OnlineDiffuser:
    """The online Diffuser (module doc) on a given cloud or a growing map.

    Args:
        cfg: the run's :class:`~diffuser_lab.config.Config` (``online``, ``graph``, ``evidence``,
            ``solver``, ``method.bayesian_mode`` are read).
        taxonomy: the class set (C classes).
        points: (N, 3) float32 world metres, the given cloud (``online.map=given``); None for a
            growing map. normals: (N, 3) unit normals of the given cloud or None (estimated).
        backend: ``auto`` (``solver.backend``: compiled kernels when numba is available) or a
            backend name (``scipy``: the numpy/scipy path); device: the torch backend's device
            (None: CUDA).
    """

    def __init__(self, cfg, taxonomy: Taxonomy, points: Optional[np.ndarray] = None,
                 normals: Optional[np.ndarray] = None, backend: SolverBackend | str = "auto",
                 device: Optional[str] = None):
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
        self.solver = OnlineSolver(oc.solver)
        self.frames_seen = 0
        self.history: list[FrameStats] = []
        self.revisit = int(oc.revisit)
        self._sorted_at = 0
        self._recent: list[Frame] = []  # growing: the last `revisit` frames (new points get their evidence)
        # per point, in the map's order: points, evidence, Bayesian labels (arrays with room to grow);
        # per row of the system: the Diffuser's labels; growing: each map point's row of the system
        self._n = 0
        self._cap = 0
        self._labels = np.zeros(0, np.int16)
        self._pos = np.zeros(0, np.int64)
        self._final: Optional[np.ndarray] = None  # Z after close()
        self._settled = False  # a step has changed Z by <= solver.tol since the last frame's evidence
        self.ev = RunEvidence.of(cfg, 0, self.C)  # the method's and the Bayesian baseline's evidence
        self._alloc(0)
        k = int(cfg.graph.k)
        if self.growing:
            g = cfg.graph
            self.voxels = VoxelMap(oc.voxel_size)
            self.graph = IncrementalKnnGraph(g.k, sigma_s=g.sigma_s, sigma_d=g.sigma_d,
                                             sigma_d_factor=g.sigma_d_factor,
                                             invariant_normals=False, rho_tol=RHO_TOL)
            self.map_index = None
            self.rho = self.sigma_d = 0.0
            # the system's rows: the map's points re-sorted along the Morton curve as the map grows
            self.system = System(np.zeros((0, k), np.int32), np.zeros((0, k), np.float32), np.zeros(0),
                                 self.ev.mass_store,
                                 self.lam, order=np.zeros(0, np.int64), gamma=self.gamma, normalised=False)
        else:
            if points is None:
                raise ValueError("online.map=given needs the scene's points")
            self._init_given(np.asarray(points, np.float32), normals)
        name = cfg.solver.backend if backend in ("auto", SolverBackend.auto) else backend
        self.system.start(backend=name, tol=self.tol, scale=self.lam, device=device,
                          sparse_classes=cfg.solver.sparse_classes, classes_per_point=cfg.solver.classes_per_point,
                          rows_hint=ROWS_HINT)
        self.backend_name = self.system.backend.name

    # -- state -----------------------------------------------------------------------------------
    def _alloc(self, need: int) -> None:
        """Room for ``need`` map points in the per-point arrays (capacity doubles; new rows are zero)."""
        if need <= self._cap and self._cap:
            return
        cap = max(need, 2 * self._cap, 1024)

        def grow(name, shape, dtype, fill=0):
            out = np.full(shape, fill, dtype)
            old = getattr(self, name, None)
            if old is not None:
                out[: self._n] = old[: self._n]
            setattr(self, name, out)

        grow("_pts", (cap, 3), np.float32)
        self.ev.grow(self._n, cap)
        grow("_bayes", (cap,), np.int16, IGNORE)
        grow("_labels", (cap,), np.int16, IGNORE)
        grow("_pos", (cap,), np.int64)
        if hasattr(self, "system"):
            self.system.mass = self.ev.mass_store
        self._cap = cap

    def _init_given(self, points: np.ndarray, normals: Optional[np.ndarray]) -> None:
        nrm, graph = make_graph(points, normals, self.cfg.graph)
        n = points.shape[0]
        self.order = graph.order  # map row s = work point order[s]
        self.map_index = np.empty(n, np.int64)
        self.map_index[graph.order] = np.arange(n)  # work point i -> map row
        self._alloc(n)
        self._n = n
        self.ev.grow(n)
        self._pts[:n] = points[graph.order]
        self._normals = None if nrm is None else np.asarray(nrm, np.float32)[graph.order]
        # the system's rows are the map's (the graph's Morton order)
        self.system = System(graph.sorted_neighbors, graph.sorted_weights, graph.sorted_row_sums, self.ev.mass_store,
                             self.lam, gamma=self.gamma)
        self.rho, self.sigma_d = graph.rho, graph.sigma_d

    # -- public views ----------------------------------------------------------------------------
    @property
    def n(self) -> int:
        """Points in the map."""
        return self._n

    @property
    def points(self) -> np.ndarray:
        """(n, 3) float32 map points, world metres, in the map's order (read-only)."""
        return _ro(self._pts[: self._n])

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
        if self.growing:
            return _ro(self._labels[self._pos[: self._n]])
        return _ro(self._labels[: self._n])

    @property
    def bayesian_labels(self) -> np.ndarray:
        """(n,) int16 the online Bayesian baseline: argmax of each point's running evidence sum
        (likelihoods or votes, ``method.bayesian_mode``), IGNORE where no frame saw it."""
        return _ro(self._bayes[: self._n])

    def scores(self) -> np.ndarray:
        """(n, C) float32 Z in the paper's units, map order (a copy; classes no evidence named are 0)."""
        if self._final is not None:
            return self._final.copy()
        return self.system.scores()

    @property
    def mass(self) -> np.ndarray:
        """(capacity, C) float32 the method's running evidence sums (Eq. 12 before lambda), map
        order; the first :attr:`n` rows are the map's."""
        return self.ev.mass_store

    @property
    def links(self) -> np.ndarray:
        """(n,) int32 each map point's pixel links so far."""
        return self.ev.method.links

    def base_evidence(self) -> np.ndarray:
        """(n, C) float32 the Bayesian baseline's running evidence sums, map order."""
        return _ro(self.ev.baseline.mass)

    def evidence(self) -> np.ndarray:
        """(n, C) float32 the method's running evidence sums (Eq. 12 before lambda), map order."""
        return _ro(self.ev.method.mass)

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
        seen = np.zeros(0, np.int64)
        if n:
            seen = self._add_evidence(frame, 0, n)
        st.seen = int(seen.size)
        rows = self._pos[seen] if self.growing else seen  # the system's rows
        if changed_rows.size:
            rows = union_rows(rows, changed_rows, self._n)
        elif self.growing:
            rows = np.sort(rows)
        if rows.size:
            self.system.renormalise(rows)
        t2 = time.perf_counter()
        if rows.size:  # a frame that adds nothing (no evidence, no point) changes nothing
            self._settled = False
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
    def _add_evidence(self, frame: Frame, lo: int, hi: int) -> np.ndarray:
        """The frame's evidence (the method's and the Bayesian baseline's) for map points lo..hi-1;
        their Bayesian labels. Returns the map rows that passed the visibility check."""
        seen, seen_base = self.ev.add(self._pts[lo:hi], frame, lo)
        if seen_base.size:
            self._bayes[seen_base] = labels_from_scores(self.ev.baseline.mass[seen_base])
        return seen

    def _grow(self, frame: Frame, st: FrameStats) -> np.ndarray:
        """Back-project and merge the frame's depth; extend the graph. Returns the system rows
        whose edges changed (new rows included), sorted."""
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
            nrm = normals_from_depth(small, K, pix, frame.T_cw, window=3 if st_px > 1 else 5)
            nrm[~nrm.any(1)] = (0.0, 0.0, 1.0)  # no depth around the pixel: a normal of no direction
            nrm = nrm.astype(np.float32)
        new_pts, new_nrm = self.voxels.insert(pts, nrm)
        m = new_pts.shape[0]
        st.new_points = m
        if m == 0:
            return np.zeros(0, np.int64)
        n0 = self._n
        self._alloc(n0 + m)
        self.ev.grow(n0 + m)
        new = np.arange(n0, n0 + m)
        self._pts[n0 : n0 + m] = new_pts  # new map rows n0.. go to system rows n0.. (the end)
        self._pos[n0 : n0 + m] = new
        self._n = n0 + m
        sysm = self.system
        sysm.resize(n0 + m)
        sysm.set_order(new, new)
        changed = np.asarray(self.graph.add(new_pts, new_nrm), np.int64)
        g, pos = self.graph, self._pos
        srows = pos[changed]  # the changed rows in the system
        sysm.sorted_neighbors[srows] = pos[g.neighbors[changed]]
        sysm.edge_weights[srows] = g.weights[changed]
        sysm.edge_sums[srows] = g.row_sums[changed]
        self.rho, self.sigma_d = g.rho, g.sigma_d
        st.graph_rows = int(changed.size)
        self._revisit(n0, m)
        self._recent.append(frame)
        if len(self._recent) > self.revisit:
            self._recent.pop(0)
        return np.sort(srows)

    def _resort(self) -> None:
        """Growing map: re-order the system's rows along the Morton curve of the points (rows appended
        frame by frame lose memory locality; measured: 16 Jacobi steps on 81k points 29.7 -> 16.4 ms).
        The map's own order (and everything public) stays as it is."""
        n = self._n
        moved = spatial_order(self._pts[:n][self.system.order])  # new system row s = old row moved[s]
        self.system.move(moved)
        self._labels[:n] = self._labels[:n][moved]
        inv = np.empty(n, np.int64)
        inv[moved] = np.arange(n)
        self._pos[:n] = inv[self._pos[:n]]
        self._sorted_at = n

    def _revisit(self, n0: int, m: int) -> None:
        """Give the new points n0..n0+m-1 the evidence of the ``online.revisit`` frames before this one
        (those that see them pass the same depth check): a point is added by the first frame whose
        depth lands in its voxel, but earlier frames may see it within ``evidence.depth_tol``."""
        for f in self._recent:
            self._add_evidence(f, n0, n0 + m)

    def _diffuse(self) -> tuple[int, float, int]:
        """The frame's steps (``online.solver``) and labels. Returns (steps done, relative residual
        after them, labels changed)."""
        if len(self.system.active) == 0:  # no evidence anywhere yet: Z stays 0
            return 0, 0.0, 0
        n = self._n
        if self.solver == OnlineSolver.gmres:
            done, r = self.steps, self.system.krylov(self.steps)
        else:
            # online.solver=jacobi: up to `steps` warm-started steps of Z <- gamma P Z + B (the paper's
            # iteration, discounted), stopping once a step changes Z by <= solver.tol of its largest entry
            out = self.system.steps(self.steps)
            done = len(out)
            self._settled = done < self.steps
            r = float(out[-1, 0] / out[-1, 1]) if out[-1, 1] > 0 else 0.0
        return done, r, self.system.labels(self._labels[:n])

    def idle(self, budget_s: float, chunk: int = 4) -> int:
        """Extra Jacobi steps in the time the sensor leaves before its next frame: ``chunk`` steps
        at a time while another chunk fits in ``budget_s`` seconds (at the last chunk's pace) and
        Z still moves by more than ``solver.tol``; then the labels. Counted in the last frame's
        :class:`FrameStats` (``idle_steps``, ``idle_ms``), not in its latency. Returns the steps
        done (none with ``online.solver=gmres``, before any evidence, or once settled)."""
        t0 = time.perf_counter()
        if budget_s <= 0 or self.solver != OnlineSolver.jacobi or self._settled or len(self.system.active) == 0:
            return 0
        done, pace = 0, 0.0
        while time.perf_counter() - t0 + pace <= budget_s:
            ts = time.perf_counter()
            out = self.system.steps(chunk)
            done += len(out)
            pace = time.perf_counter() - ts
            if len(out) < chunk:  # a step changed Z by <= solver.tol
                self._settled = True
                break
        if done:
            changed = self.system.labels(self._labels[: self._n])
            if self.history:
                st = self.history[-1]
                st.idle_steps += done
                st.idle_ms += (time.perf_counter() - t0) * 1e3
                st.changed += changed
        return done

    def finish(self, max_steps: int, observer=None) -> dict:
        """After the last frame: Jacobi steps until one changes Z by <= ``solver.tol`` of its
        largest entry, at most ``max_steps`` (the online iteration's fixed point, which the frames'
        few steps only track): the core's loop (:meth:`~diffuser_lab.method.diffusion.System.run`)
        with ``observer`` (:data:`~diffuser_lab.method.diffusion.Observer`: iteration = the pass's
        step, Z in the map's order; statistics when it asks). Returns {steps, ms, residual,
        changed} (steps 0 with ``online.solver=gmres``, before any evidence, or when already settled)."""
        t0 = time.perf_counter()
        done, r = 0, 0.0
        if self.solver == OnlineSolver.jacobi and len(self.system.active) and not self._settled:
            res = self.system.run(max_steps, observer)
            done, r = res.iterations, res.residual
            self._settled = res.converged
        changed = self.system.labels(self._labels[: self._n]) if done else 0
        return {"steps": done, "ms": (time.perf_counter() - t0) * 1e3, "residual": r, "changed": int(changed)}

    def close(self) -> None:
        """Release the working memory and threads (the state stays readable)."""
        if self._final is None:
            self._final = self.system.scores()
        self.system.close()


def _ro(a: np.ndarray) -> np.ndarray:
    v = a.view()
    v.flags.writeable = False
    return v
