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
from diffuser_lab.config import Config, DepthNoiseConfig, GraphAffinity, SceneConfig
from diffuser_lab.data import inputs, sources, validate
from diffuser_lab.data.frames import FrameLoop, KeyframeRule, LazyFrames, follow_of, keyframes, read_ahead, without
from diffuser_lab.data.geometry import VoxelGrid
from diffuser_lab.data.predictions import describe as describe_predictions
from diffuser_lab.data.predictions import reads_rgb, with_predictions
from diffuser_lab.data.scene import IGNORE, SCANNET20, Frame, Scene, Taxonomy
from diffuser_lab.data.sensor import noisy_frames, sensor_model
from diffuser_lab.data.taxonomy import resolve_taxonomy
from diffuser_lab.hooks import RunHooks
from diffuser_lab.method import calibration, fusion
from diffuser_lab.method import evidence as evidence_mod
from diffuser_lab.method.diffusion import DiffusionResult, Observer
from diffuser_lab.method.evidence import Evidence
from diffuser_lab.method.fusion import graph_variant
from diffuser_lab.method.graph import KnnGraph, graph_stage, make_graph
from diffuser_lab.method.metrics import confusion_matrix, score, scores_from_confusion
from diffuser_lab.method.space import Classes, Features, frame_order
from diffuser_lab.method.space import of_frame as label_space

from .resolve import resolve
from .work import sparse_classes, to_original, work_cloud, work_colors


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
    space: Optional[Classes | Features] = None  # the run's label space, set by the run (a features run's queries and per-point features)
    # (M, C) the method's class scores on the work points (Z, pixel mass, a features run's query
    # scores): a point's class distribution is its row normalised (calibration.stored); None
    # without ground truth or output.scores
    scores: Optional[np.ndarray] = None
    confidence: Optional[np.ndarray] = None  # output.scores: (N, 3) float32 top score, margin, entropy (nats)


class _Graph:
    """The run's kNN graph of the work points, built when the method asks for it
    (:meth:`~diffuser_lab.method.fusion.FusionMethod.label`), with what ``graph.affinity`` and
    ``solver.tikhonov`` change of it and of the evidence (:func:`~diffuser_lab.method.fusion.graph_variant`);
    ``normals``: the work points' (estimated with the graph where the cloud has none)."""

    def __init__(self, cfg: Config, scene: Scene, points: np.ndarray, normals: Optional[np.ndarray],
                 grid: Optional[VoxelGrid], space, t: dict):
        self.cfg, self.scene, self.points, self.normals, self.grid, self.space, self.t = \
            cfg, scene, points, normals, grid, space, t
        self.graph: Optional[KnnGraph] = None

    def __call__(self, ev: Evidence) -> tuple[KnnGraph, Evidence]:
        tg = time.perf_counter()
        gc = self.cfg.graph
        with graph_stage(self.points.shape[0], gc, gc.use_normals and self.normals is None):
            self.normals, self.graph = make_graph(self.points, self.normals, gc)
            colors = work_colors(self.scene, self.grid) if gc.affinity == GraphAffinity.colour else None
            ev = graph_variant(self.graph, ev, self.cfg, colors=colors, average=self.space.average)
        self.t["graph"] = time.perf_counter() - tg
        return self.graph, ev


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
    """load -> the frame loop (evidence) -> the method's labels -> the result; what differs between
    methods is their registry entry's (:mod:`~diffuser_lab.method.fusion`), between labels and
    features the label space's (:mod:`~diffuser_lab.method.space`)."""
    # colour is read only when something reads it: the predictions (a network on RGB) or the hooks (records)
    colour = reads_rgb(cfg.predictions) or (hooks is not None and hooks.reads_rgb)
    hooks = hooks or RunHooks()
    t: dict = {}
    t0 = time.perf_counter()
    if scene is None:
        scene = load_scene(cfg.scene, resolve_taxonomy(cfg), cfg.depth)
    tax = scene.taxonomy
    validate.check_points(scene)
    t["load"] = time.perf_counter() - t0
    hooks.on_scene(scene)
    frames = with_predictions(scene.frames if colour else without(scene.frames, "rgb"), cfg.predictions, tax,
                              scene_name=scene.name)
    pts, nrm, grid = work_cloud(scene, cfg.scene.voxel_size)
    validate.check_memory(scene.n_points, pts.shape[0], tax.num_classes, cfg.graph.k, cfg.memory_budget_gb,
                          sparse_classes(cfg.solver, pts.shape[0], tax.num_classes))
    method = fusion.get(cfg.method.name)  # what the method needs; cfg already has what it fixes
    method.check(cfg, pts.shape[0])
    space, pred2d = _frame_loop(cfg, method, scene, frames, pts, hooks, t)
    bayes_work = space.labels(space.evidence.baseline.mass)
    hooks.on_evidence(pts, grid, space.observed_evidence(space.evidence.method), bayes_work)
    graph = _Graph(cfg, scene, pts, nrm, grid, space, t)
    out = _label(cfg, method, space, frames, pts, graph, hooks, observer, t)
    res = _result(cfg, scene, frames, pts, grid, graph, space, out, bayes_work, pred2d, t)
    if scene.gt_labels is not None:
        _score(res, cfg, space, t)
    t["total"] = time.perf_counter() - t0
    res.timings_s = t
    hooks.on_result(res)
    return res


def _frame_loop(cfg: Config, method: fusion.FusionMethod, scene: Scene, frames: Sequence[Frame], pts: np.ndarray,
                hooks: RunHooks, t: dict) -> tuple[Classes | Features, Optional[dict]]:
    """One pass over the frames: each is loaded (and its predictions made) once, scored in 2D
    against its ground truth, and added to the evidence; memory stays independent of their number.
    Returns the run's label space (made at the first frame; its evidence and the method's lifting
    rule made and fed) and the 2D predictions' scores (None without)."""
    tax, n = scene.taxonomy, pts.shape[0]
    space, conf2d, centres, inverted = None, None, [], []
    t["predictions"] = t["evidence"] = 0.0
    loop = FrameLoop(frames, f"frames: {describe_predictions(cfg.predictions)} + evidence",
                     targets=frame_order(cfg, method, len(frames)))  # a features run: its basis' frames first
    for i, f in loop:
        tp = time.perf_counter()
        if loop.bar.enabled and "cached_frames" in getattr(frames, "stats", {}):  # a network's outputs
            loop.bar.note(f"{frames.stats['cached_frames']} from cache")
        validate.check_frame(f)
        if i == 0 and not getattr(scene.frames, "info", {}).get("depth_unit_checked"):
            validate.check_depth_unit(f)
        centres.append(validate.camera_centre(f))
        inverted.append(np.asarray(f.T_cw, float)[:3, 3])  # the centre if T_cw were camera-to-world
        space = space or label_space(f, cfg, tax, method, len(frames))  # the first frame's: labels or features
        space.check_frame(f)
        conf2d = _add_2d(conf2d, space, f, tax.num_classes)
        ta = time.perf_counter()
        ready = space.admit(i, f, cfg, method, n, hooks)  # a features run holds its basis' frames until it is fitted
        tp += time.perf_counter() - ta
        for j, g in ready:
            hooks.on_frame(j, g)
            te = time.perf_counter()
            space.evidence.add(pts, g)
            t["evidence"] += time.perf_counter() - te
            tp += time.perf_counter() - te
        t["predictions"] += time.perf_counter() - tp
    t["predictions"] += loop.read_s
    space = space or Classes(tax.num_classes)
    t.update(space.timings)
    ev = space.run_evidence(cfg, method, n).method
    validate.check_pose_convention(pts, np.array(centres).reshape(-1, 3), np.array(inverted).reshape(-1, 3))
    if not ev.seen.any():
        warnings.warn(f"no frame sees any point ({len(frames)} frames): nothing is labelled; check the poses "
                      f"(world-to-camera), intrinsics and evidence.depth_tol", stacklevel=3)
    return space, None if conf2d is None else scores_from_confusion(conf2d, tax.names)


def _add_2d(conf2d: Optional[np.ndarray], space, f: Frame, num_classes: int) -> Optional[np.ndarray]:
    """The frame's 2D prediction (as labels: :meth:`~diffuser_lab.method.space.Classes.label_image`)
    scored against its ground truth, added to ``conf2d``."""
    pred = space.label_image(f) if f.gt_labels is not None else None
    if pred is None:
        return conf2d
    c = confusion_matrix(pred, f.gt_labels, num_classes)
    return c if conf2d is None else conf2d + c


def _label(cfg: Config, method: fusion.FusionMethod, space, frames: Sequence[Frame], pts: np.ndarray, graph: _Graph,
           hooks: RunHooks, observer: Optional[Observer], t: dict) -> fusion.Labelled:
    """The method's labelling of the work points: the evidence it reads, diffused over ``graph`` (a
    graph method) or as it is, in the run's label space; the space's baselines beside it."""
    evidence = space.evidence
    chosen = method.reads(evidence, space.rule, frames, cfg, pts)
    space.add_baselines(evidence)  # before the method's sums may be diffused in place
    td = time.perf_counter()
    out = method.label(space, chosen, rule=space.rule, graph=graph, solver=space.solver(cfg.solver),
                       lam=cfg.evidence.pixel_weight, observer=space.observer(hooks, observer))
    if out.diffusion is not None:
        t["diffusion"] = time.perf_counter() - td - t.get("graph", 0.0)
    out.keep()
    space.finish(evidence)
    return out


def _result(cfg: Config, scene: Scene, frames: Sequence[Frame], pts: np.ndarray, grid: Optional[VoxelGrid],
            graph: _Graph, space, out: fusion.Labelled, bayes_work: np.ndarray, pred2d: Optional[dict],
            t: dict) -> RunResult:
    """The labels on the scene's points, and the run's result; the method's class distribution per point
    (Diffuser, LDLS: Z; the others: their pixel mass; a features run's from the queries' cosines) where
    there is ground truth or ``output.scores``."""
    tl = time.perf_counter()
    with progress.stage(f"labels to the {scene.n_points:,} original points"):  # instant without voxels
        rows = to_original(scene, grid, np.arange(pts.shape[0]))  # each point's work point
        labels = out.labels[rows].astype(np.int16)
        bayes = bayes_work[rows].astype(np.int16)
    t["labels"] = time.perf_counter() - tl
    res = RunResult(scene=scene, frames=frames, method=cfg.method.name, labels=labels, bayesian_labels=bayes,
                    work_points=pts, work_normals=graph.normals, evidence=space.evidence.method, voxels=grid,
                    graph=graph.graph, diffusion=out.diffusion, predictions_2d=pred2d,
                    predictions_stats=dict(getattr(frames, "stats", {})), rows=rows, space=space)
    if scene.gt_labels is not None or cfg.output.scores:
        res.scores = out.scores
    if cfg.output.scores:
        ts = time.perf_counter()
        res.confidence = calibration.point_confidence(res.scores, rows)
        t["scores"] = time.perf_counter() - ts
    return res


def _score(res: RunResult, cfg: Config, space, t: dict) -> None:
    """The labels' and the baselines' scores against the scene's ground truth, and their calibration."""
    tm = time.perf_counter()
    gt, tax = res.scene.gt_labels, res.scene.taxonomy
    res.metrics = score(res.labels, gt, tax.names)
    res.baseline["bayesian"] = score(res.bayesian_labels, gt, tax.names)
    res.baseline.update(space.baseline_metrics(res.rows, gt, tax.names))
    post = {res.method: res.scores}
    post.update({name: s() for name, s in space.baseline_scores(space.evidence.baseline.mass).items()
                 if name not in post})
    res.metrics["calibration"] = calibration.of_methods(post, gt, res.rows, tax.num_classes,
                                                        cfg.calibration.temperature, cfg.calibration.bins)
    t["metrics"] = time.perf_counter() - tm


__all__ = ["RunResult", "run", "load_scene", "IGNORE"]
