"""One run, in the order the data flows: load -> evidence + graph -> diffusion -> labels -> metrics.

Nothing here writes files; :mod:`diffuser_lab.cli.main` turns a :class:`RunResult` into records.
"""
from __future__ import annotations

import collections
import dataclasses
import time
import warnings
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import numpy as np

from diffuser_lab import progress
from diffuser_lab.backends import resolve_backend
from diffuser_lab.config import Config, DepthNoiseConfig, GraphAffinity, SceneConfig, SolverName, SparseClasses
from diffuser_lab.data import inputs, sources, validate
from diffuser_lab.data.frames import FrameLoop, KeyframeRule, LazyFrames, follow_of, keyframes, read_ahead, without
from diffuser_lab.data.geometry import VoxelGrid, nearest_transfer, voxel_downsample, voxel_edge
from diffuser_lab.data.embeddings import prototypes
from diffuser_lab.data.predictions import describe as describe_predictions
from diffuser_lab.data.predictions import reads_rgb, with_predictions
from diffuser_lab.data.scene import IGNORE, SCANNET20, Frame, Scene, Taxonomy
from diffuser_lab.data.sensor import noisy_frames, sensor_model
from diffuser_lab.data.taxonomy import resolve_taxonomy
from diffuser_lab.hooks import RunHooks
from diffuser_lab.method import affinity, calibration, fusion, lifters
from diffuser_lab.method import evidence as evidence_mod
from diffuser_lab.method import features as features_mod
from diffuser_lab.method.diffusion import DiffusionResult, Observer, labels_from_scores, normalise, sparse_by_size
from diffuser_lab.method.evidence import Evidence, RunEvidence
from diffuser_lab.method.basis import BasisFeatures, FeatureBasis, fit_basis, query_span
from diffuser_lab.method.exact import tikhonov_scale
from diffuser_lab.method.queries import Queries, labels_of_cosines, query_classes, query_labels, similarity
from diffuser_lab.method.graph import KnnGraph, graph_stage, make_graph
from diffuser_lab.method.metrics import confusion_matrix, score, scores_from_confusion

from .resolve import resolve


class _SceneReuse:
    """The scenes :func:`load_scene` made last, kept for the next calls with the same keys while
    :func:`reuse_scenes` is on: a sweep's jobs in one process (seed the innermost of its loops)
    load each scene once per seed, not once per job. At most :attr:`MAX_SCENES` scenes of
    :attr:`MAX_POINTS` points in all (the least recently used goes first; a larger one is not kept)."""

    MAX_SCENES = 4
    MAX_POINTS = 4_000_000

    def __init__(self) -> None:
        self.on = False
        self.kept: collections.OrderedDict[tuple, Scene] = collections.OrderedDict()
        self.read: dict[tuple, list] = {}  # the input files each kept scene's load read (data/inputs.py)

    @staticmethod
    def key_of(cfg: SceneConfig, taxonomy: Taxonomy, depth: Optional[DepthNoiseConfig]) -> tuple:
        cfg = dataclasses.replace(cfg, keyframe_translation=None, keyframe_rotation_deg=None, read_ahead=None)
        return (repr(cfg), taxonomy.name, taxonomy.names, taxonomy.colors.tobytes(), taxonomy.ids,
                taxonomy.ignore_ids, repr(depth))

    def get(self, key: tuple, load: Callable[[], Scene]) -> Scene:
        scene = self.kept.get(key)
        if scene is None:
            with inputs.collecting() as got:
                scene = load()
            if scene.n_points <= self.MAX_POINTS:
                self.read[key] = got.rows()
                self._keep(key, scene)
        else:  # this job reads the files the kept scene was loaded from: its summary lists them
            inputs.merge(self.read.get(key, ()))
            self.kept.move_to_end(key)
        return self._handout(scene)

    def _keep(self, key: tuple, scene: Scene) -> None:
        # read-only: a job that wrote into the shared arrays would change a later job's scene
        arrays = [scene.points, scene.normals, scene.colors, scene.gt_labels]
        if isinstance(scene.frames, list):
            arrays += [a for f in scene.frames for a in (f.K, f.T_cw, f.depth, f.labels, f.probs, f.gt_labels, f.rgb)]
        for a in arrays:
            if isinstance(a, np.ndarray):
                a.setflags(write=False)
        self.kept[key] = scene
        while len(self.kept) > self.MAX_SCENES or sum(x.n_points for x in self.kept.values()) > self.MAX_POINTS:
            self.read.pop(self.kept.popitem(last=False)[0], None)

    @staticmethod
    def _handout(s: Scene) -> Scene:
        """A new Scene (and new Frames when they are a list) over the scene's arrays: a job may set
        their attributes without touching the kept one."""
        frames = [dataclasses.replace(f) for f in s.frames] if isinstance(s.frames, list) else s.frames
        return dataclasses.replace(s, frames=frames)


_REUSE = _SceneReuse()


def reuse_scenes(on: bool = True) -> None:
    """Keep the scenes loaded last for the next :func:`load_scene` calls with the same scene,
    taxonomy and depth keys (the command line turns this on for a multirun's jobs; results are the
    same: a scene is a function of those keys). Their arrays are read-only while kept. Off: they are dropped."""
    _REUSE.on = bool(on)
    if not on:
        _REUSE.kept.clear()
        _REUSE.read.clear()


def load_scene(cfg: SceneConfig, taxonomy: Taxonomy = SCANNET20, depth: Optional[DepthNoiseConfig] = None) -> Scene:
    """The configured source (the scene sources' registry entry ``cfg.source``) -> :class:`Scene`
    in ``taxonomy`` (the run's: ``resolve_taxonomy(cfg)``) whose frames carry ground-truth labels
    when known. Relative paths are taken from the current directory.

    ``depth`` (the run's ``cfg.depth``; None = perfect): the sensor model applied to rendered depth
    (demo, mesh_views) and, with ``depth.apply_to_real``, to the real sources' depth frames.
    With :func:`reuse_scenes` on, the same keys give the scene loaded last (new Scene and Frame
    objects over the same, read-only arrays)."""
    cfg = sources.typed_options(cfg)  # a library caller's dict of options: typed and checked here
    with read_ahead(cfg.read_ahead):
        if _REUSE.on:
            scene = _REUSE.get(_REUSE.key_of(cfg, taxonomy, depth), lambda: _load_scene(cfg, taxonomy, depth))
        else:
            scene = _load_scene(cfg, taxonomy, depth)
        scene.frames = keyframes_of(scene.frames, cfg)
    return scene


def keyframes_of(frames: Sequence[Frame], cfg: SceneConfig) -> Sequence[Frame]:
    """The frames ``scene.keyframe_translation`` / ``scene.keyframe_rotation_deg`` keep
    (:func:`~diffuser_lab.data.frames.keyframes`: a frame whose camera moved or turned that much since
    the last kept one), as a subset that keeps each frame's index (its simulated predictions, its seeds);
    ``info["keyframes"]`` says what was kept (summary.json's ``keyframes``). Both null: ``frames``.
    A capture followed as it is written keeps its frames: the rule marks the keyframes that its
    ``newest`` policy takes from a backlog (:meth:`~diffuser_lab.data.frames.Follow.schedule`)."""
    t, r = cfg.keyframe_translation, cfg.keyframe_rotation_deg
    if t is None and r is None:
        return frames
    follow = follow_of(frames)
    if follow is not None:
        follow.rule = KeyframeRule(t, r)
        follow.info["keyframes"] = {"translation_m": t, "rotation_deg": r}
        return frames
    keep = keyframes(frames, t, r)
    names = getattr(frames, "names", None) or ([f.name for f in frames] if isinstance(frames, list) else None)
    info = dict(getattr(frames, "info", None) or {})
    info["keyframes"] = {"translation_m": t, "rotation_deg": r, "kept": len(keep), "of": len(frames),
                         "kept_frames": [names[k] for k in keep] if names is not None else keep}
    return LazyFrames.subset(frames, keep, info=info)


def _load_scene(cfg: SceneConfig, taxonomy: Taxonomy, depth: Optional[DepthNoiseConfig]) -> Scene:
    source, sensor = sources.get(cfg.source), sensor_model(depth) if depth is not None else None
    with progress.stage(f"loading scene ({cfg.source})"):  # its own steps show inside
        scene = source.load(cfg, taxonomy, sensor)
    scene.frames = _real_depth(scene.frames, source, sensor, depth)
    if cfg.name:
        scene.name = cfg.name
    return scene


def load_frames(cfg: SceneConfig, taxonomy: Taxonomy = SCANNET20, depth: Optional[DepthNoiseConfig] = None
                ) -> Sequence[Frame]:
    """The frames of :func:`load_scene`'s scene, without its cloud where the source can (its
    ``frames`` entry: the city); otherwise the scene is loaded and its frames kept."""
    cfg = sources.typed_options(cfg)
    source, sensor = sources.get(cfg.source), sensor_model(depth) if depth is not None else None
    if source.frames is None:
        return load_scene(cfg, taxonomy, depth).frames
    return keyframes_of(_real_depth(source.frames(cfg, taxonomy, sensor), source, sensor, depth), cfg)


def _real_depth(frames, source, sensor, depth):
    if sensor is not None and depth.apply_to_real and not source.rendered:
        return noisy_frames(frames, sensor)  # the cloud stays the loader's
    return frames


@dataclass
class RunResult:
    """Everything a run produced. Arrays on the original points have N rows; ``work_*`` arrays
    are on the (possibly voxel-downsampled) cloud the diffusion ran on, M rows."""

    scene: Scene
    frames: Sequence[Frame]  # frames with their predictions attached
    method: str
    labels: np.ndarray  # (N,) int16, IGNORE = unlabeled
    bayesian_labels: np.ndarray  # (N,) int16
    work_points: np.ndarray  # (M, 3) float32 world metres
    work_normals: Optional[np.ndarray]  # (M, 3) float32
    evidence: evidence_mod.Evidence  # on the work points
    voxels: Optional[VoxelGrid]
    graph: Optional[KnnGraph] = None
    diffusion: Optional[DiffusionResult] = None
    metrics: Optional[dict] = None
    baseline: dict = field(default_factory=dict)  # {"bayesian": scores}
    predictions_2d: Optional[dict] = None
    predictions_stats: dict = field(default_factory=dict)  # e.g. unmapped pixels of file predictions
    timings_s: dict = field(default_factory=dict)
    rows: Optional[np.ndarray] = None  # (N,) int64 each original point's work point
    lifted: Optional["FeatureLift"] = None  # a features run's queries and per-point features
    # (M, C) the method's class scores on the work points (Z, pixel mass, a features run's query
    # scores): a point's class distribution is its row normalised (calibration.stored); None
    # without ground truth or output.scores
    scores: Optional[np.ndarray] = None
    confidence: Optional[np.ndarray] = None  # output.scores: (N, 3) float32 top score, margin, entropy (nats)


def _work_cloud(scene: Scene, voxel_size) -> tuple[np.ndarray, Optional[np.ndarray], Optional[VoxelGrid]]:
    """The points the graph is built on: ``scene.voxel_size`` (metres, 0 = off, or ``auto``:
    :func:`~diffuser_lab.data.geometry.voxel_edge`) applied to the scene's points."""
    voxel_size = voxel_edge(voxel_size, scene.points)
    if voxel_size <= 0:
        return scene.points, scene.normals, None
    with progress.stage(f"voxel grid ({voxel_size:g} m, {scene.n_points:,} points)"):
        grid = voxel_downsample(scene.points, voxel_size)
        normals = None
        if scene.normals is not None:
            n = grid.mean(scene.normals)
            normals = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return grid.points, normals, grid


def _to_original(scene: Scene, grid: Optional[VoxelGrid], work_labels: np.ndarray) -> np.ndarray:
    if grid is None:
        return work_labels
    return nearest_transfer(grid.points, work_labels, scene.points)


class _Observe:
    """Adapts :class:`RunHooks` (and a plain observer callable) to the diffusion's observer; in a
    features run both see (M, C) class scores (:meth:`FeatureLift.scores` of the decoded Z)."""

    def __init__(self, hooks: RunHooks, fn: Optional[Observer], lift: Optional[FeatureLift] = None):
        self.hooks, self.fn, self.lift = hooks, fn, lift

    def wants(self, it: int) -> bool:
        return self.fn is not None or self.hooks.wants(it)

    def statistics(self):
        """The hooks' request of every step's statistics (a features run: none, its columns are no classes)."""
        return None if self.lift is not None else self.hooks.statistics()

    def on_statistics(self, table) -> None:
        self.hooks.on_statistics(table)

    def __call__(self, it: int, Z: np.ndarray, stats: dict) -> None:
        if self.lift is not None:
            F = features_mod.decode(Z)
            F.flags.writeable = False
            if self.hooks.wants(it):
                self.hooks.observe_features(it, self.lift.observed(F))
            Z = self.lift.scores(F)
            Z.flags.writeable = False
        if self.fn is not None:
            self.fn(it, Z, stats)
        if self.hooks.wants(it):
            self.hooks.observe(it, Z, stats)


@dataclass
class FeatureLift:
    """How a features run (frames with feature maps: :mod:`diffuser_lab.method.features`) turns
    per-point features into labels: the query set, each query's class, the background rule; and
    the work points' features it produced.

    Features are (M, D) arrays (``basis`` None: ``predictions.basis=full``, the single-frame
    protocol) or, with a reduced ``basis`` (:mod:`diffuser_lab.method.basis`), :class:`BasisFeatures`
    (or the (M, k + s) sums they split from): cosines with the queries exact in f.q, divided by the
    estimated |f|.

    Attributes:
        queries: :class:`~diffuser_lab.method.queries.Queries` (Q names, (Q, D) unit embeddings).
        to_class: (Q,) int64 the taxonomy class of each query (-1: none).
        threshold, background: a point whose best cosine is below ``threshold`` gets ``background``.
        basis: the run's :class:`~diffuser_lab.method.basis.FeatureBasis`, or None (full).
        basis_info: summary.json's ``features.basis`` (what the basis is and what it kept).
        method: the method's per-point feature sums (Diffuser: diffused), set by the run: (M, D)
            float32, or :class:`BasisFeatures`.
        average: the averaging baseline's (the mean of the depth-checked pixels' features): (M, D)
            float16 unit rows, or :class:`BasisFeatures` of the sums.
        best_view: the most confident view's unit feature (:class:`~diffuser_lab.method.evidence.BestView`):
            (M, D) float16, or :class:`BasisFeatures` (its residual exact: 1 - |coords|^2).
    """

    queries: Queries
    to_class: np.ndarray
    num_classes: int
    threshold: Optional[float] = None
    background: int = IGNORE
    basis: Optional[FeatureBasis] = None
    basis_info: dict = field(default_factory=lambda: {"kind": "full"})
    method: Optional[np.ndarray | BasisFeatures] = None
    average: Optional[np.ndarray | BasisFeatures] = None
    best_view: Optional[np.ndarray | BasisFeatures] = None

    def _in_basis(self, features) -> Optional[BasisFeatures]:
        if self.basis is None:
            return None
        if isinstance(features, BasisFeatures):
            return features
        if features.shape[1] != self.basis.width:
            raise ValueError(f"features of shape {features.shape}, expected (M, {self.basis.width}): the basis' "
                             f"{self.basis.k} + {self.basis.s} columns")
        return self.basis.split(features)

    def cosines(self, features) -> np.ndarray:
        """(M, Q) float32 cosines with the queries (NaN rows: no feature)."""
        b = self._in_basis(features)
        return similarity(features, self.queries) if b is None else b.cosines(self.basis.queries)

    def unit_confidence(self, features: np.ndarray) -> np.ndarray:
        """(M, D) unit features, or with a basis their (M, k) coordinates -> (M,) float32 the top
        class's probability (softmax over the classes' best cosines at
        :data:`~diffuser_lab.method.features.CLIP_TEMPERATURE`): what picks a point's most confident view."""
        if self.basis is None:
            return self.confidence(features)
        cos = np.asarray(features, np.float32) @ np.ascontiguousarray(self.basis.queries.T)  # |f| = 1 exactly
        return features_mod.top_probability(cos, self.to_class, self.num_classes)

    def confidence(self, features) -> np.ndarray:
        """Features -> (M,) float32 the top class's probability (as :meth:`unit_confidence`)."""
        return features_mod.top_probability(self.cosines(features), self.to_class, self.num_classes)

    def labels(self, features) -> np.ndarray:
        """Features -> (M,) int16 class ids (IGNORE where nothing reached a point)."""
        b = self._in_basis(features)
        if b is None:
            return query_labels(features, self.queries, self.to_class, threshold=self.threshold,
                                background=self.background)
        return labels_of_cosines(b.cosines(self.basis.queries), self.to_class, self.threshold, self.background)

    def scores(self, features) -> np.ndarray:
        """Features -> (M, C) class scores (:func:`~diffuser_lab.method.features.class_scores`)."""
        return features_mod.class_scores(self.cosines(features), self.to_class, self.num_classes)

    def observed(self, features) -> np.ndarray:
        """What the records' feature views see of features: the (M, D) array, or the (M, k) coordinates."""
        b = self._in_basis(features)
        return features if b is None else b.coords

    def unit_rows(self, features, rows: Optional[np.ndarray] = None, out: Optional[np.ndarray] = None) -> np.ndarray:
        """(M', D) float16 unit rows in R^D of ``rows`` (default all) of features (a basis':
        the projections; :meth:`BasisFeatures.unit_float16`), into ``out`` when given."""
        b = self._in_basis(features)
        if b is not None:
            return b.unit_float16(self.basis, rows, out)
        part = features if rows is None else features[rows]
        unit = part if part.dtype == np.float16 else features_mod.unit_float16(part)
        if out is None:
            return unit
        out[...] = unit
        return out


def feature_lift(cfg: Config, taxonomy: Taxonomy, dim: int) -> FeatureLift:
    """The run's queries (``predictions.queries``: a file; ``predictions.encoder``: a text encoder
    on the taxonomy's names; neither: the simulated network's prototypes of them) and their classes."""
    pc = cfg.predictions
    if pc.queries:
        q = Queries.from_file(pc.queries)
    elif pc.encoder:
        q = Queries.from_encoder(list(taxonomy.names), pc.encoder)
    else:
        q = Queries(tuple(taxonomy.names), prototypes(taxonomy.names, dim=dim, seed=pc.embedding_seed))
    if q.embeddings.shape[1] != dim:
        raise ValueError(f"the queries have D = {q.embeddings.shape[1]}, the frames' features D = {dim}")
    to_class = np.asarray(query_classes(q.names, taxonomy.names, pc.query_mapping), np.int64)
    background = IGNORE if pc.background is None else taxonomy.names.index(pc.background)
    return FeatureLift(q, to_class, taxonomy.num_classes, pc.threshold, background)


def basis_frames(n_frames: int, wanted: int) -> list[int]:
    """The frames a run's basis is fitted on: ``wanted`` evenly spaced indices of ``n_frames``
    (all of them when fewer), the first and the last included."""
    m = max(1, min(int(wanted), n_frames))
    return sorted({int(round(x)) for x in np.linspace(0, n_frames - 1, m)})


def feature_basis(cfg: Config, queries: Queries, maps: Sequence[np.ndarray]) -> Optional[FeatureBasis]:
    """``predictions.basis=auto``: the run's :class:`~diffuser_lab.method.basis.FeatureBasis`, fitted on
    the valid cells (unit rows) of ``maps`` ((h, w, D) feature maps of the frames :func:`basis_frames`
    picks) and the queries; None (the full path, exact) when it would not halve the D columns (the
    queries' rank + ``basis_dim`` + ``basis_probes`` > D / 2)."""
    pc = cfg.predictions
    D = queries.dim
    rank = query_span(queries.embeddings).shape[1]
    if 2 * (rank + pc.basis_dim + pc.basis_probes) > D:
        return None
    cells = []
    with progress.stage(f"feature basis: {len(maps)} frames' cells, {rank} queries + {pc.basis_dim} "
                        f"directions + {pc.basis_probes} probes of {D}"):
        for fmap in maps:  # a few frames
            if fmap is None or fmap.ndim != 3 or fmap.shape[2] != D:
                continue  # the evidence reports it
            cells.append(features_mod.normalised(fmap.reshape(-1, D))[0][np.isfinite(fmap).all(2).reshape(-1)])
        sample = np.concatenate(cells) if cells else np.zeros((0, D), np.float32)
        sample = sample[np.einsum("ij,ij->i", sample, sample) > 0]
        return fit_basis(sample, queries.embeddings, pc.basis_dim, pc.basis_probes, cfg.seed)


def _feature_evidence(cfg: Config, lift: FeatureLift, n: int, maps: Sequence[np.ndarray], hooks: RunHooks,
                      auto: bool) -> RunEvidence:
    """A features run's evidence for ``n`` points: in the basis fitted on ``maps`` (``auto``:
    ``predictions.basis=auto`` and a method that diffuses, :func:`feature_basis`) or in all D columns;
    with the most confident view tracked, and the hooks told the queries (in the basis' coordinates
    when there is one)."""
    D = lift.queries.dim
    basis = feature_basis(cfg, lift.queries, maps) if auto else None
    if basis is not None:
        lift.basis, lift.basis_info = basis, basis.record()
    evidence = RunEvidence.of(cfg, n, basis.width if basis else D)
    evidence.basis = basis
    hooks.on_queries(lift.queries.names, lift.queries.embeddings if basis is None else basis.queries,
                     basis=None if basis is None else basis.vectors)
    evidence.best = evidence_mod.BestView(n, basis.k if basis else D, lift.unit_confidence)
    return evidence


def basis_kept(lift: FeatureLift, energy: np.ndarray) -> dict:
    """What a reduced basis kept, for summary.json's ``features.basis``: the share of the linked
    pixels' energy (exact: each pixel's projection, over all links); per point with a feature, the
    share of the method's features' and of the averaging baseline's energy, |P f|^2 / |f|^2
    (``median``, ``p5``), and the relative error of the projection's norm, 1 - |P f| / |f|
    (``median``, ``p95``), |f| estimated with the probes (random: right on average over their draw,
    not for one draw: a few times too large or too small where the residual has few directions)."""
    out = {"energy_pixels": round(float(energy[0] / energy[1]), 6) if energy[1] else None}
    for name, X in (("features", lift.method), ("average", lift.average)):
        share = X.energy_kept()
        share = share[np.isfinite(share)]
        out[f"energy_{name}"] = {"median": round(float(np.median(share)), 6),
                                 "p5": round(float(np.percentile(share, 5)), 6)} if share.size else None
        if name == "features":
            err = 1 - np.sqrt(share)
            out["norm_error"] = {"median": round(float(np.median(err)), 6),
                                 "p95": round(float(np.percentile(err, 95)), 6)} if share.size else None
    return out


def lifting_rule(method: fusion.FusionMethod, cfg: Config, n: int, dim: int, num_classes: int,
                 lift: Optional[FeatureLift] = None) -> lifters.Rule:
    """The streaming rule of a ``evidence=RULE`` method (:mod:`diffuser_lab.method.lifters`) for ``n``
    points of ``dim`` columns (C; D in a features run, whose ``lift`` gives topk its confidence and
    vote its per-view labels)."""
    return lifters.make(method.rule, n, dim, features=lift is not None, num_classes=num_classes,
                        depth_tol=cfg.evidence.depth_tol, top_k=cfg.method.top_k,
                        confidence=lift.confidence if lift is not None else None,
                        classify=lift.labels if lift is not None else None)


def graph_variant(graph: KnnGraph, ev: Evidence, cfg: Config, *, colors: Optional[np.ndarray] = None,
                  average: Optional[np.ndarray] = None) -> Evidence:
    """What ``graph.affinity`` and ``solver.tikhonov`` change of a graph method's inputs: the graph's
    weights (in place: LUDVIG's Eq. 4 x the points' similarity, :mod:`~diffuser_lab.method.affinity`;
    ``colors`` / ``average``: the work points' colours, a features run's averaged features) and the
    evidence the system reads (Splat Feature Solver's Tikhonov term, :func:`~diffuser_lab.method.exact.tikhonov_scale`:
    a new Evidence; ``ev`` is not changed). Both off (the defaults): ``ev`` and the graph as they are."""
    attrs, known = affinity.attributes(cfg.graph.affinity, colors=colors, mass=ev.mass, links=ev.links, average=average)
    if attrs is not None:
        affinity.apply_affinity(graph, attrs, known, cfg.graph.sigma_c)
    if cfg.solver.tikhonov > 0:
        alpha = tikhonov_scale(graph, ev.links, cfg.evidence.pixel_weight, cfg.solver.tikhonov)
        ev = Evidence(mass=ev.mass * alpha[:, None], links=ev.links * alpha)
    return ev


def _work_colors(scene: Scene, grid: Optional[VoxelGrid]) -> Optional[np.ndarray]:
    """(M, 3) the work points' colours (a voxel's mean; [0, 1] float or the scene's uint8), None without."""
    if scene.colors is None:
        return None
    if grid is None:
        return scene.colors
    return grid.mean(np.asarray(scene.colors, np.float32) / (255.0 if scene.colors.dtype == np.uint8 else 1.0))


def _sparse_classes(solver, n_work: int, num_classes: int) -> int:
    """The per-point class count the diffusion will use (0 = dense), for the memory check:
    ``solver.sparse_classes`` on / off, or auto's size rule (diffusion.sparse_by_size)."""
    if solver.name != SolverName.jacobi or solver.sparse_classes == SparseClasses.off:
        return 0
    numba = resolve_backend(solver.backend) == "numba"
    if solver.sparse_classes == SparseClasses.on or (numba and sparse_by_size(n_work, num_classes)):
        return int(solver.classes_per_point)
    return 0


def run(cfg: Config, *, scene: Optional[Scene] = None, observer: Optional[Observer] = None,
        hooks: Optional[RunHooks] = None) -> RunResult:
    """Label ``scene`` (default: the configured source) with ``cfg.method``; Bayesian fusion of
    the same evidence is always computed beside it. ``observer(iteration, Z, stats)`` and
    ``hooks`` (see :mod:`diffuser_lab.hooks`) watch the run without changing it. ``cfg`` is
    resolved first (:func:`~diffuser_lab.runs.resolve.resolve`: registry names, the method's fixed keys)."""
    cfg = resolve(cfg)
    with read_ahead(cfg.scene.read_ahead):  # every frame loop of the run (the loader's too)
        return _run(cfg, scene, observer, hooks)


def _run(cfg: Config, scene: Optional[Scene], observer: Optional[Observer], hooks: Optional[RunHooks]) -> RunResult:
    # colour is read only when something reads it: the predictions (a network on RGB) or the hooks (records)
    colour = reads_rgb(cfg.predictions) or (hooks is not None and hooks.reads_rgb)
    hooks = hooks or RunHooks()
    t = {}
    t0 = time.perf_counter()
    if scene is None:
        scene = load_scene(cfg.scene, resolve_taxonomy(cfg), cfg.depth)
    tax = scene.taxonomy
    validate.check_points(scene)
    t["load"] = time.perf_counter() - t0
    hooks.on_scene(scene)

    # One pass over the frames: each is loaded (and its predictions made) once, scored in 2D
    # against its ground truth, and added to the evidence; memory stays independent of their number.
    frames = with_predictions(scene.frames if colour else without(scene.frames, "rgb"), cfg.predictions, tax,
                              scene_name=scene.name)
    pts, nrm, grid = _work_cloud(scene, cfg.scene.voxel_size)
    validate.check_memory(scene.n_points, pts.shape[0], tax.num_classes, cfg.graph.k, cfg.memory_budget_gb,
                          _sparse_classes(cfg.solver, pts.shape[0], tax.num_classes))
    method = fusion.get(cfg.method.name)  # what the method needs; cfg already has what it fixes
    if method.graph and cfg.graph.k >= pts.shape[0]:
        raise ValueError(f"graph.k={cfg.graph.k} must be smaller than the number of points ({pts.shape[0]})")
    centres, inverted = [], []
    ev_kw = dict(depth_tol=cfg.evidence.depth_tol, pixel_radius=cfg.evidence.pixel_radius)
    evidence: Optional[RunEvidence] = None  # made at the first frame: D columns for feature maps
    feats, lift, rule = False, None, None
    conf2d = None
    t["predictions"] = t["evidence"] = 0.0
    # a features run with predictions.basis=auto reads the frames its basis is fitted on first (evenly
    # spaced) and holds them until it is: their evidence and hooks come after, then the other frames'
    # (a lifting rule sees each link's unit feature in R^D: its run diffuses no basis)
    basis_auto = cfg.predictions.basis == "auto" and method.evidence != fusion.RULE
    sample = basis_frames(len(frames), cfg.predictions.basis_frames) \
        if cfg.predictions.source == "features" and basis_auto and len(frames) else []
    first = set(sample)
    pending: Optional[list] = []
    loop = FrameLoop(frames, f"frames: {describe_predictions(cfg.predictions)} + evidence",
                     targets=sample + [j for j in range(len(frames)) if j not in first] if sample else None)
    for i, f in loop:
        tp = time.perf_counter()
        if loop.bar.enabled and "cached_frames" in getattr(frames, "stats", {}):  # a network's outputs
            loop.bar.note(f"{frames.stats['cached_frames']} from cache")
        validate.check_frame(f)
        if i == 0 and not getattr(scene.frames, "info", {}).get("depth_unit_checked"):
            validate.check_depth_unit(f)
        centres.append(validate.camera_centre(f))
        inverted.append(np.asarray(f.T_cw, float)[:3, 3])  # the centre if T_cw were camera-to-world
        if evidence is None and lift is None:  # the first frame
            feats = f.features is not None
            if feats:
                lift = feature_lift(cfg, tax, f.features.shape[2])
            else:
                evidence = RunEvidence.of(cfg, pts.shape[0], tax.num_classes)
        elif (f.features is not None) != feats:
            raise ValueError(f"frame {f.name}: {'no ' if feats else ''}feature map, unlike the first frame")
        if f.gt_labels is not None and not feats:
            pred = f.labels if f.labels is not None else np.argmax(f.probs, axis=2)
            c = confusion_matrix(pred, f.gt_labels, tax.num_classes)
            conf2d = c if conf2d is None else conf2d + c
        batch = [(i, f)]
        if evidence is None:  # a features run before its basis: the frames it is fitted on are held
            pending.append((i, f))
            if len(pending) < len(sample):
                t["predictions"] += time.perf_counter() - tp
                continue
            tb = time.perf_counter()
            evidence = _feature_evidence(cfg, lift, pts.shape[0], [g.features for _, g in pending], hooks,
                                         basis_auto)
            t["basis"] = time.perf_counter() - tb
            tp += t["basis"]
            batch, pending = pending, None
        if rule is None and method.evidence == fusion.RULE:  # a lifting rule keeps its state from the same links
            rule = evidence.hook = lifting_rule(method, cfg, pts.shape[0], evidence.num_classes, tax.num_classes,
                                                lift)
        for j, g in batch:
            hooks.on_frame(j, g)
            te = time.perf_counter()
            evidence.add(pts, g)
            t["evidence"] += time.perf_counter() - te
            tp += time.perf_counter() - te
        t["predictions"] += time.perf_counter() - tp
    t["predictions"] += loop.read_s
    if evidence is None:
        evidence = RunEvidence.of(cfg, pts.shape[0], tax.num_classes)
    ev, ev_base = evidence.method, evidence.baseline
    pred2d = None if conf2d is None else scores_from_confusion(conf2d, tax.names)
    validate.check_pose_convention(pts, np.array(centres).reshape(-1, 3), np.array(inverted).reshape(-1, 3))
    if not ev.seen.any():
        warnings.warn(f"no frame sees any point ({len(frames)} frames): nothing is labelled; check the poses "
                      f"(world-to-camera), intrinsics and evidence.depth_tol", stacklevel=2)
    bayes_work = labels_from_scores(ev_base.mass) if lift is None else lift.labels(ev_base.mass)
    hooks.on_evidence(pts, grid, ev if lift is None or lift.basis is None else
                      dataclasses.replace(ev, mass=ev.mass[:, :lift.basis.k]), bayes_work)

    graph = diff = system = None
    if method.evidence == fusion.BASELINE:
        chosen = ev_base
    elif method.evidence == fusion.RULE:
        chosen = Evidence(mass=rule.values() if rule is not None else np.zeros_like(ev.mass), links=ev.links)
    elif method.evidence == fusion.ONE_VIEW:
        n_frames = len(frames)
        if not -n_frames <= cfg.method.view < n_frames:
            raise ValueError(f"method.view={cfg.method.view}: the scene has {n_frames} frames")
        chosen = evidence_mod.accumulate(pts, [frames[cfg.method.view]], ev.mass.shape[1], **ev_kw)
    else:
        chosen = ev
    # a features run hands the core its features encoded as class-like masses (method/features.py)
    solver = cfg.solver
    if lift is not None:  # every column is a feature's: no per-point class set
        solver = dataclasses.replace(cfg.solver, sparse_classes=SparseClasses.off)
        if lift.basis is None:
            lift.average = features_mod.unit_float16(ev_base.mass)  # before F is diffused in place
            lift.best_view = evidence.best.features
        else:  # the sums' coordinates (copied: F may be diffused in place); a unit view's residual is exact
            lift.average = lift.basis.split(ev_base.mass.copy())
            c = evidence.best.features
            kept = np.einsum("ij,ij->i", c, c, dtype=np.float32)
            lift.best_view = BasisFeatures(c, np.where(evidence.best.score > -np.inf, np.maximum(1 - kept, 0), 0))
    if method.graph:
        tg = time.perf_counter()
        with graph_stage(pts.shape[0], cfg.graph, cfg.graph.use_normals and nrm is None):
            nrm, graph = make_graph(pts, nrm, cfg.graph)
            colors = _work_colors(scene, grid) if cfg.graph.affinity == GraphAffinity.colour else None
            chosen = graph_variant(graph, chosen, cfg, colors=colors, average=lift.average if lift is not None else None)
            if lift is None:
                system = normalise(graph, chosen.mass, cfg.evidence.pixel_weight)
        t["graph"] = time.perf_counter() - tg
    td = time.perf_counter()
    if lift is None:
        work_labels, diff = method.label(chosen.mass, system=system, solver=solver, observer=_Observe(hooks, observer))
    elif method.graph:  # through the unchanged core, encoded (method/features.py), in blocks when large
        F, diff = features_mod.diffuse_features(graph, chosen.mass, chosen.links, cfg.evidence.pixel_weight,
                                                solver, observer=_Observe(hooks, observer, lift))
        lift.method = F if lift.basis is None else lift.basis.split(F)
        work_labels = lift.labels(lift.method)
        diff = dataclasses.replace(diff, Z=lift.scores(lift.method))  # the class scores its observers saw
    elif rule is not None and rule.classes:  # class votes of the views' query labels (method/lifters.py)
        lift.method = None
        work_labels, diff = labels_from_scores(chosen.mass), None
    else:
        lift.method = chosen.mass if lift.basis is None else lift.basis.split(chosen.mass)
        work_labels, diff = lift.labels(lift.method), None
    if method.graph:
        t["diffusion"] = time.perf_counter() - td
    if lift is not None and lift.basis is not None:
        lift.basis_info.update(basis_kept(lift, evidence.energy))

    tl = time.perf_counter()
    with progress.stage(f"labels to the {scene.n_points:,} original points"):  # instant without voxels
        rows = _to_original(scene, grid, np.arange(pts.shape[0]))  # each point's work point
        labels = work_labels[rows].astype(np.int16)
        bayes = bayes_work[rows].astype(np.int16)
    t["labels"] = time.perf_counter() - tl

    res = RunResult(scene=scene, frames=frames, method=method.name, labels=labels, bayesian_labels=bayes,
                    work_points=pts, work_normals=nrm, evidence=ev, voxels=grid, graph=graph, diffusion=diff,
                    predictions_2d=pred2d, predictions_stats=dict(getattr(frames, "stats", {})), rows=rows,
                    lifted=lift)
    if scene.gt_labels is not None or cfg.output.scores:
        # the method's class distribution (Diffuser, LDLS: Z; the others: their pixel mass) per point;
        # a features run's from the queries' cosines (its diff.Z already is)
        res.scores = diff.Z if diff is not None else chosen.mass if lift is None or lift.method is None \
            else lift.scores(lift.method)
    if cfg.output.scores:
        ts = time.perf_counter()
        res.confidence = calibration.point_confidence(res.scores, rows)
        t["scores"] = time.perf_counter() - ts
    if scene.gt_labels is not None:
        tm = time.perf_counter()
        res.metrics = score(labels, scene.gt_labels, tax.names)
        res.baseline["bayesian"] = score(bayes, scene.gt_labels, tax.names)
        post = {method.name: res.scores}
        if lift is None:
            if method.name != "bayesian":
                post["bayesian"] = ev_base.mass
        else:
            if method.name != "bayesian":
                post["bayesian"] = lift.scores(lift.average)
            post["best_view"] = lift.scores(lift.best_view)
            res.baseline["best_view"] = score(lift.labels(lift.best_view)[rows], scene.gt_labels, tax.names)
        res.metrics["calibration"] = calibration.of_methods(post, scene.gt_labels, rows, tax.num_classes,
                                                            cfg.calibration.temperature, cfg.calibration.bins)
        t["metrics"] = time.perf_counter() - tm
    t["total"] = time.perf_counter() - t0
    res.timings_s = t
    hooks.on_result(res)
    return res


__all__ = ["RunResult", "run", "load_scene", "IGNORE"]
