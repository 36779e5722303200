"""The online Diffuser: frames arrive one at a time and the map's labels follow.

Per frame (:meth:`OnlineDiffuser.add_frame`):

1. growing map only: the frame's depth is back-projected (every ``online.depth_stride``-th pixel)
   and merged on a world-anchored voxel grid (:class:`~diffuser_lab.data.voxel_map.VoxelMap`);
   the new points get normals from the depth image, the evidence of the earlier frames
   (:class:`FrameStore`, ``online.revisit``: those that see them within the depth check, as the
   batch run on the final cloud links them), and the kNN graph (Eqs. 3-4) is
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
map the order its points were added in, which is also the system's row order: each frame's new
points are one block of rows in the Morton order of their voxels (memory locality kept by blocks;
the map is never re-sorted: a full re-sort cost a spike of O(N K) per growth step). Everything
public is in the map's order. The iteration runs on Z / lambda.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from diffuser_lab.backends.base import residual, union_rows
from diffuser_lab.backends.evidence import KeptVotes
from diffuser_lab.backends.region import reach
from diffuser_lab.config import FinalPass, OnlineMap, OnlineSolver, SolverBackend
from diffuser_lab.data.geometry import backproject, normals_from_depth
from diffuser_lab.data.scene import IGNORE, Frame, Taxonomy
from diffuser_lab.data.voxel_map import VoxelMap
from diffuser_lab.method.diffusion import System, labels_from_scores
from diffuser_lab.method.evidence import RunEvidence
from diffuser_lab.method.graph import make_graph
from diffuser_lab.method.growing import IncrementalKnnGraph
from diffuser_lab.method.solvers import solve

STEPS_GIVEN = 10
"""Default steps per frame on a given map (``online.steps=null``)."""
STEPS_GROWING = 16
"""... on a growing map: its new points start from Z = 0, not from a warm state."""


ROWS_HINT = 1 << 20
"""The online system's backend is sized (threads) as for this many rows: a map may start small."""


_NO_VOTES = (np.zeros((4, 4)), np.zeros((3, 3)), np.zeros((1, 1), np.float32), np.zeros((1, 1), np.int16))


class FrameStore:
    """Growing map: the frames taken so far, kept for the points added after them (a point is
    added by the first frame whose depth lands in its voxel, but earlier frames may see it within
    ``evidence.depth_tol``; the batch run on the final cloud links them all).

    Each frame is kept as what its evidence reads (K, T_cw, depth, the 2D labels / probabilities /
    features; not the colour) with its projection and the range of its valid depths: a frame whose
    view cannot hold any of the new points (:meth:`seeing`) is skipped without changing any evidence.

    Args:
        limit: frames kept at most (None: all); max_bytes: their arrays' bytes at most; the
            oldest frames go first. depth_tol: metres (``evidence.depth_tol``).
    Attributes:
        dropped: frames let go for ``limit`` or ``max_bytes`` (their evidence is lost for points
            added later). bytes: the kept frames' arrays.
    """

    def __init__(self, limit: Optional[int], max_bytes: float, depth_tol: float):
        self.limit = None if limit is None else int(limit)
        self.max_bytes = float(max_bytes)
        self.depth_tol = float(depth_tol)
        self.frames: list[Frame] = []
        self.fused: list[bool] = []  # the frame's evidence is the compiled pass's: kept in `votes` too
        self.votes = KeptVotes.make()  # the frames again, for that pass over many at once (None: numpy)
        self._proj = np.zeros((0, 3, 4))  # per frame K [R | t]
        self._view = np.zeros((0, 4))  # per frame the image's width and height, its depths' range (+- tol)
        self._sizes: list[int] = []
        self.bytes = 0
        self.dropped = 0

    def __len__(self) -> int:
        return len(self.frames)

    def add(self, frame: Frame, fused: bool = False) -> None:
        """Keep ``frame`` (its arrays are referenced, not copied; ``fused``: its evidence is the
        compiled single pass's, :meth:`~diffuser_lab.method.evidence.RunEvidence.fused`), letting the
        oldest go past the limits."""
        if self.limit == 0:
            self.dropped += 1
            return
        kept = Frame(name=frame.name, K=frame.K, T_cw=frame.T_cw, depth=frame.depth, labels=frame.labels,
                     probs=frame.probs, features=frame.features)
        valid = frame.depth[frame.depth > 0]
        if valid.size == 0:
            return
        T = np.asarray(frame.T_cw, np.float64)
        proj = np.asarray(frame.K, np.float64) @ T[:3]  # (3, 4): world -> (u z, v z, z)
        h, w = frame.shape
        view = np.array([w, h, float(valid.min()) - self.depth_tol, float(valid.max()) + self.depth_tol])
        size = sum(a.nbytes for a in (kept.depth, kept.labels, kept.probs, kept.features) if a is not None)
        fused = bool(fused) and self.votes is not None
        self.frames.append(kept)
        self.fused.append(fused)
        if self.votes is not None:  # every frame a place, so that the indices match (the others never read)
            self.votes.add(*((frame.T_cw, frame.K, frame.depth, frame.labels) if fused else _NO_VOTES))
        self._sizes.append(size)
        self._proj = np.concatenate([self._proj, proj[None]])
        self._view = np.concatenate([self._view, view[None]])
        self.bytes += size
        while self.frames and ((self.limit is not None and len(self.frames) > self.limit)
                               or self.bytes > self.max_bytes):
            self.frames.pop(0)
            self.fused.pop(0)
            if self.votes is not None:
                self.votes.drop_oldest()
            self.bytes -= self._sizes.pop(0)
            self._proj, self._view = self._proj[1:], self._view[1:]
            self.dropped += 1

    def seeing(self, points: np.ndarray) -> list[int]:
        """The kept frames (their places in :attr:`frames`), oldest first, that may see some of
        ``points`` (m, 3) world metres: the box around the points is not wholly behind the camera,
        beyond its valid depths (widened by the depth check's tolerance), or (wholly in front of it)
        past one edge of its image (widened by a pixel against rounding). A convex box projects
        inside its corners' projections and a point's depth is affine, so no frame that can link one
        of the points is left out."""
        if not self.frames or points.shape[0] == 0:
            return []
        lo, hi = points.min(0).astype(np.float64), points.max(0).astype(np.float64)
        corners = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        uvz = np.einsum("fij,cj->fic", self._proj, corners)  # (F, 3, 8)
        z = uvz[:, 2]
        w, h, z_lo, z_hi = self._view.T
        far = (z.max(1) < z_lo) | (z.min(1) > z_hi) | (z.max(1) <= 1e-6)
        front = z.min(1) > 1e-6
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = uvz[:, 0] / z, uvz[:, 1] / z
        off = front & ((u.max(1) < -1.5) | (u.min(1) > w[:] + 0.5) | (v.max(1) < -1.5) | (v.min(1) > h + 0.5))
        return np.flatnonzero(~(far | off)).tolist()


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
    map_ms: float = 0.0  # growing: back-projection, voxel merge, normals
    graph_ms: float = 0.0  # growing: the kNN graph extended (Eqs. 3-4), the system's rows appended
    evidence_ms: float = 0.0  # evidence (the new points' from earlier frames too) and renormalised rows
    steps_ms: float = 0.0  # the Jacobi steps and the labels
    points: int = 0  # points in the map after the frame
    new_points: int = 0
    seen: int = 0  # points that passed the frame's visibility check
    graph_rows: int = 0  # rows whose edges changed (growing)
    steps: int = 0  # Jacobi steps run
    residual: float = 0.0  # the last step's max |Z_t - Z_{t-1}| / max Z_t
    changed: int = 0  # points whose label changed
    region_rows: int = 0  # rows the frame's steps took (online.region)
    sweep_residual: Optional[float] = None  # a step on every row (the sweep, idle steps): its relative change
    error_bound: Optional[float] = None  # then: max |Z - Z*| / max Z <= this, Z* the system's discounted fixed point
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
        self.final = FinalPass(oc.final)
        self.region = bool(oc.region) and OnlineSolver(oc.solver) == OnlineSolver.jacobi
        self.frontier = self.steps if oc.frontier is None else int(oc.frontier)
        self.sweep = int(oc.sweep)
        self.lam = float(cfg.evidence.pixel_weight)
        self.solver = OnlineSolver(oc.solver)
        self.frames_seen = 0
        self._taken = 0  # frames taken (not skipped): the sweep's turn, the same whatever was skipped between
        self.history: list[FrameStats] = []
        # growing: the earlier frames (new points get their evidence)
        self.store = FrameStore(oc.revisit, oc.revisit_mb * 2**20, cfg.evidence.depth_tol)
        # per point, in the map's order: points, evidence, Bayesian labels (arrays with room to grow);
        # per row of the system: the Diffuser's labels; growing: each map point's row of the system
        self._n = 0
        self._cap = 0
        self._labels = np.zeros(0, np.int16)
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
                                             invariant_normals=False, rho_tol=None)
            self.map_index = None
            self.rho = self.sigma_d = 0.0
            # the system's rows: the map's points, in the order they were added
            self.system = System(np.zeros((0, k), np.int32), np.zeros((0, k), np.float32), np.zeros(0),
                                 self.ev.mass_store, self.lam, gamma=self.gamma, normalised=False)
        else:
            if points is None:
                raise ValueError("online.map=given needs the scene's points")
            self._init_given(np.asarray(points, np.float32), normals)
        name = cfg.solver.backend if backend in ("auto", SolverBackend.auto) else backend
        self.system.start(backend=name, tol=self.tol, scale=self.lam, device=device,
                          sparse_classes=cfg.solver.sparse_classes, classes_per_point=cfg.solver.classes_per_point,
                          rows_hint=ROWS_HINT)
        self.backend_name = self.system.backend.name
        self.region = self.region and self.system.backend.regions  # a backend without regions steps every row

    # -- state -----------------------------------------------------------------------------------
    def _alloc(self, need: int) -> None:
        """Room for ``need`` map points in the per-point arrays (capacity doubles; new rows are zero)."""
        if need <= self._cap and self._cap:
            return
        cap = max(need, 2 * self._cap, 1024)

        def grow(name, shape, dtype, fill=0):
            out = np.zeros(shape, dtype) if fill == 0 else np.full(shape, fill, dtype)  # zeros: pages touched as used
            old = getattr(self, name, None)
            if old is not None:
                out[: self._n] = old[: self._n]
            setattr(self, name, out)

        grow("_pts", (cap, 3), np.float32)
        self.ev.grow(self._n, cap)
        grow("_bayes", (cap,), np.int16, IGNORE)
        grow("_labels", (cap,), np.int16, IGNORE)
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
        edges = moved = np.zeros(0, np.int64)  # system rows: whose edges changed; what the points changed
        n0 = self._n
        if self.growing:
            new_pts, new_nrm = self._map(frame, st)
            t1 = time.perf_counter()
            edges, moved = self._extend(new_pts, new_nrm, st)
            t2 = time.perf_counter()
            self._revisit(n0, self._n - n0)
            self.store.add(frame, self.ev.fused(frame))
        else:
            t1 = t2 = t0
        n = self._n
        seen = self._add_evidence(frame, 0, n) if n else np.zeros(0, np.int64)
        st.seen = int(seen.size)
        if self.growing:
            rows, moved = union_rows(seen, edges, n), union_rows(seen, moved, n)
        else:
            rows = moved = seen
        if rows.size:
            self.system.renormalise(rows)
        t3 = time.perf_counter()
        if rows.size:  # a frame that adds nothing (no evidence, no point) changes nothing
            self._settled = False
            self._diffuse(st, self._region(moved))
        t4 = time.perf_counter()
        st.points = n
        st.map_ms, st.graph_ms = (t1 - t0) * 1e3, (t2 - t1) * 1e3
        st.evidence_ms, st.steps_ms = (t3 - t2) * 1e3, (t4 - t3) * 1e3
        st.latency_ms = (t4 - t0) * 1e3
        self.frames_seen += 1
        self._taken += 1
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
    def _add_evidence(self, frame: Frame, lo: int, hi: int, checked: bool = False) -> np.ndarray:
        """The frame's evidence (the method's and the Bayesian baseline's) for map points lo..hi-1;
        their Bayesian labels (``checked``: a kept frame, its label ids checked). Returns the map
        rows that passed the visibility check."""
        seen, seen_base = self.ev.add(self._pts[lo:hi], frame, lo, checked)
        if seen_base.size:
            self._bayes[seen_base] = labels_from_scores(self.ev.baseline.mass[seen_base])
        return seen

    def _map(self, frame: Frame, st: FrameStats) -> tuple[np.ndarray, Optional[np.ndarray]]:
        """Back-project the frame's depth and merge it on the voxel map. Returns the new map points
        (m, 3) float32 world metres (Morton order of their voxels) and their (m, 3) unit normals or None."""
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
        st.new_points = new_pts.shape[0]
        return new_pts, new_nrm

    def _extend(self, new_pts: np.ndarray, new_nrm: Optional[np.ndarray], st: FrameStats
                ) -> tuple[np.ndarray, np.ndarray]:
        """Append the new points to the map, the graph and the system. Returns the system rows whose
        edges changed (sorted, new rows included) and, of those, the ones the new points changed
        (they differ when the weights were all refreshed: rho moved)."""
        m = new_pts.shape[0]
        if m == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        n0 = self._n
        self._alloc(n0 + m)
        self.ev.grow(n0 + m)
        self._pts[n0 : n0 + m] = new_pts  # new map rows n0.. are system rows n0.. (the end): a block in Morton order
        self._n = n0 + m
        sysm = self.system
        sysm.resize(n0 + m)
        g = self.graph
        changed = np.asarray(g.add(new_pts, new_nrm), np.int64)  # sorted
        sysm.sorted_neighbors[changed] = g.neighbors[changed]
        # sigma_d follows the map's spacing rho: new and changed rows take it now, the others in turn (the
        # sweep's slice of rows every frame: a row's weights are at most `sweep` frames old)
        part = -(-self._n // self.sweep)
        lo = (self._taken % self.sweep) * part
        turn = np.arange(lo, min(lo + part, n0))
        g.reweigh(turn)
        edges = union_rows(changed, turn, self._n)
        sysm.edge_weights[edges] = g.weights[edges]
        sysm.edge_sums[edges] = g.row_sums[edges]
        self.rho, self.sigma_d = g.rho, g.sigma_d
        st.graph_rows = int(changed.size)
        return edges, changed

    def _revisit(self, n0: int, m: int) -> None:
        """Give the new points n0..n0+m-1 the evidence of the kept frames before this one (:class:`FrameStore`;
        those that see them pass the same depth check), oldest first, as the batch adds them."""
        pts = self._pts[n0 : n0 + m]
        st = self.store
        which = st.seeing(pts)
        self.ev.add_kept(pts, st.votes, np.array([i for i in which if st.fused[i]], np.int64), n0)  # one call
        for i in which:
            if not st.fused[i]:
                self._add_evidence(st.frames[i], n0, n0 + m, checked=True)
        if m:
            self._bayes[n0 : n0 + m] = labels_from_scores(self.ev.baseline.mass[n0 : n0 + m])

    def _region(self, rows: np.ndarray) -> Optional[np.ndarray]:
        """The system rows a frame's steps take (``online.region``, ``online.frontier``): ``rows``
        (the rows the frame changed) and every row within ``frontier`` hops of them along the
        rows' neighbours (:func:`~diffuser_lab.backends.region.reach`); None: every row. With
        frontier = the frame's steps, its steps equal steps on every row wherever the rest of the
        map has settled (a change moves one hop a step)."""
        if not self.region:
            return None
        return reach(self.system.sorted_neighbors, rows, self.frontier)

    def _diffuse(self, st: FrameStats, region: Optional[np.ndarray] = None) -> None:
        """The frame's steps (``online.solver``; ``region``: those rows alone, :meth:`_region`; every
        ``online.sweep``-th frame one more step on every row: :meth:`_bound`) and labels, into ``st``."""
        if len(self.system.active) == 0:  # no evidence anywhere yet: Z stays 0
            return
        n = self._n
        if self.solver == OnlineSolver.gmres:
            st.steps, st.residual = self.steps, self.system.krylov(self.steps)
        else:
            # online.solver=jacobi: up to `steps` warm-started steps of Z <- gamma P Z + B (the paper's
            # iteration, discounted), stopping once a step changes Z by <= solver.tol of its largest entry
            out = self.system.steps(self.steps, region)
            st.steps = len(out)
            st.region_rows = n if region is None else int(region.size)
            self._settled = st.steps < self.steps and region is None
            st.residual = residual(*out[-1])
            if region is None:
                self._bound(st, st.residual)
            elif self._taken % self.sweep == 0:
                self._bound(st, residual(*self.system.steps(1)[-1]))
                st.steps += 1
        st.changed = self.system.labels(self._labels[:n])

    def _bound(self, st: FrameStats, r: float) -> None:
        """A step on every row changed Z by ``r`` of its largest entry: the discounted iteration is a
        contraction by gamma in the max norm, so Z is within gamma r / (1 - gamma) (relative to max Z)
        of the fixed point its system has now, wherever the frames' regions left it (``st``'s
        ``sweep_residual`` and ``error_bound``)."""
        st.sweep_residual = float(r)
        st.error_bound = float(self.gamma * r / (1.0 - self.gamma)) if self.gamma < 1 else float("inf")

    def idle(self, budget_s: float, chunk: int = 4) -> int:
        """Extra Jacobi steps in the time the sensor leaves before its next frame: ``chunk`` steps
        at a time while another chunk fits in ``budget_s`` seconds (at the last chunk's pace) and
        Z still moves by more than ``solver.tol``; then the labels. Counted in the last frame's
        :class:`FrameStats` (``idle_steps``, ``idle_ms``), not in its latency. Returns the steps
        done (none with ``online.solver=gmres``, before any evidence, or once settled)."""
        t0 = time.perf_counter()
        if budget_s <= 0 or self.solver != OnlineSolver.jacobi or self._settled or len(self.system.active) == 0:
            return 0
        done, pace, last = 0, 0.0, None
        while time.perf_counter() - t0 + pace <= budget_s:
            ts = time.perf_counter()
            out = self.system.steps(chunk)
            done += len(out)
            last = out[-1]
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
                self._bound(st, residual(*last))
        return done

    def finish(self, max_steps: int, observer=None) -> dict:
        """After the last frame (``online.final``), with ``observer``
        (:data:`~diffuser_lab.method.diffusion.Observer`: iteration = the pass's step, Z in the
        map's order; statistics when it asks):

        - ``batch``: the batch method on the map built online: the paper's iteration (gamma = 1)
          from Z = 0, ``horizon`` steps with the solver's early stop (the solver registry's, as a
          batch run: :func:`~diffuser_lab.method.solvers.solve`), a growing map's weights first
          refreshed with its final rho. The discounted iteration the frames track has a fixed
          point near, not at, the early-stopped result (docs/online.md); this pass ends there.
        - ``settle``: Jacobi steps of the discounted iteration until one changes Z by <=
          ``solver.tol`` of its largest entry, at most ``max_steps``.

        Returns {steps, ms, residual, changed} (steps 0 with ``online.solver=gmres``, before any
        evidence, when ``max_steps`` is 0, or (settle) when already settled)."""
        t0 = time.perf_counter()
        done, r, changed = 0, 0.0, 0
        jacobi = self.solver == OnlineSolver.jacobi and len(self.system.active) and max_steps > 0
        if jacobi and self.final == FinalPass.batch:
            res = self._batch_pass(observer)
            done, r = res.iterations, res.residual
            self._settled = True
            self._final = res.Z
            n = self._n
            order = self.system.order
            new = labels_from_scores(res.Z if order is None else res.Z[order])
            changed = int(np.count_nonzero(new != self._labels[:n]))
            self._labels[:n] = new
        elif jacobi and not self._settled:
            res = self.system.run(max_steps, observer)
            done, r = res.iterations, res.residual
            self._settled = res.converged
            changed = self.system.labels(self._labels[: self._n])
        return {"steps": done, "ms": (time.perf_counter() - t0) * 1e3, "residual": r, "changed": int(changed),
                "final": self.final.value}

    def _batch_pass(self, observer):
        """``online.final=batch``: the batch iteration on the final map (see :meth:`finish`); the
        system is the paper's afterwards (gamma = 1: no frame can follow)."""
        sysm = self.system
        if self.growing:
            g, n = self.graph, self._n
            g.refresh_weights()  # sigma_d = 2 rho of the final map, as build_graph on the final cloud
            sysm.edge_weights[:n] = g.weights
            sysm.edge_sums[:n] = g.row_sums
            self.rho, self.sigma_d = g.rho, g.sigma_d
        sysm.close()
        sysm.gamma = 1.0
        sysm.renormalise()
        scfg = dataclasses.replace(self.cfg.solver, backend=self.backend_name, max_iter=self.horizon)
        return solve(sysm, scfg, observer)

    def close(self) -> None:
        """Release the working memory and threads (the state stays readable)."""
        if self._final is None and self.system._backend is not None:
            self._final = self.system.scores()
        self.system.close()


def _ro(a: np.ndarray) -> np.ndarray:
    v = a.view()
    v.flags.writeable = False
    return v
