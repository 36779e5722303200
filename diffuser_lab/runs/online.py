"""protocol=online: a scene's frames one at a time, in sequence order, through the
:class:`~diffuser_lab.method.online.OnlineDiffuser`; per frame the latency (the update alone: the
network and file reading excluded), the map's size, changed labels and, where ground truth is
known, mIoU so far of the online Diffuser and the online Bayesian baseline. After the last frame
the batch Diffuser (and Bayesian) runs on the same frames (growing map: on the final cloud) for
reference. Nothing here writes files; hooks (:mod:`diffuser_lab.hooks`) see every frame.
"""
from __future__ import annotations

import contextlib
import dataclasses
import time
import warnings
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import numpy as np

from diffuser_lab import progress
from diffuser_lab.backends.threads import blas_one_thread
from diffuser_lab.config import BadFrame, Config, OnlineMap
from diffuser_lab.data import validate
from diffuser_lab.data.frames import FrameLoop, LazyFrames
from diffuser_lab.data.predictions import describe as describe_predictions
from diffuser_lab.data.predictions import with_predictions
from diffuser_lab.data.scene import IGNORE, Frame, Scene
from diffuser_lab.data.taxonomy import resolve_taxonomy
from diffuser_lab.hooks import RunHooks
from diffuser_lab.method.diffusion import labels_from_scores
from diffuser_lab.method.metrics import confusion_matrix, score, scores_from_confusion
from diffuser_lab.method.online import FrameStats, OnlineDiffuser
from diffuser_lab.method.space import Observe

from .pipeline import load_scene, run
from .resolve import resolve
from .work import to_original, work_cloud


@dataclass
class OnlineUpdate:
    """What hooks see after each frame (arrays are read-only views, valid during the call).

    Attributes:
        index: the frame's index in the sequence; stats: its :class:`FrameStats`.
        points: (n, 3) float32 map points, world metres, map order; the last
            ``stats.new_points`` rows are the ones this frame added.
        labels, bayesian: (n,) int16 online Diffuser / online Bayesian labels (IGNORE = none).
        gt: (n,) int16 ground truth of the map points, or None.
        metrics: mIoU so far etc. (:func:`frame_metrics`), {} without ground truth.
        scores: call for the (n, C) float32 Z in the paper's units (a copy: only where kept).
    """

    index: int
    stats: FrameStats
    points: np.ndarray
    labels: np.ndarray
    bayesian: np.ndarray
    gt: Optional[np.ndarray]
    metrics: dict
    scores: Callable[[], np.ndarray]


@dataclass
class OnlineResult:
    scene: Scene
    mode: str  # given | growing
    points: np.ndarray  # (n, 3) final map points (map order)
    labels: np.ndarray  # (n,) int16 online Diffuser, map order
    bayesian_labels: np.ndarray  # (n,) int16 online Bayesian
    gt: Optional[np.ndarray]  # (n,) int16 map ground truth, or None
    frames: list[dict]  # per frame: FrameStats fields + metrics so far
    metrics: Optional[dict]  # final online Diffuser scores (given: on the scene's points, as batch runs)
    bayesian: Optional[dict]  # final online Bayesian scores
    batch: dict = field(default_factory=dict)  # the batch runs on the same frames, and the agreement
    settings: dict = field(default_factory=dict)  # steps, gamma, horizon, backend
    latency_ms: dict = field(default_factory=dict)  # median, p95, max, mean over the frames taken
    timings_s: dict = field(default_factory=dict)
    scene_labels: Optional[np.ndarray] = None  # (N,) int16 labels of the scene's points (given map)


def check_online_frame(f: Frame) -> None:
    """The batch pipeline's frame checks plus: a frame without any valid depth is bad."""
    validate.check_frame(f)
    if not np.any(f.depth > 0):
        raise ValueError(f"frame {f.name}: no valid depth (every pixel is 0 or invalid)")


def frame_metrics(labels: np.ndarray, bayes: np.ndarray, gt: Optional[np.ndarray], names) -> dict:
    """mIoU / accuracy so far of the online Diffuser and Bayesian labels against ``gt`` (percent;
    unlabelled points count as misses, as in batch runs), and their coverage."""
    if gt is None:
        return {}
    out = {}
    for key, lab in (("diffuser", labels), ("bayesian", bayes)):
        s = scores_from_confusion(confusion_matrix(lab, gt, len(names)), names)
        out[f"{key}_miou"] = s["miou"]
        out[f"{key}_accuracy"] = s["accuracy"]
    out["coverage"] = float(100.0 * np.mean(labels != IGNORE)) if labels.size else 0.0
    return out


def latency_summary(frames: list[dict]) -> dict:
    lat = np.array([f["latency_ms"] for f in frames if f.get("skipped") is None], float)
    if lat.size == 0:
        return {}
    return {"median": float(np.median(lat)), "p95": float(np.percentile(lat, 95)), "max": float(lat.max()),
            "mean": float(lat.mean()), "frames": int(lat.size)}


def _map_gt(tree, gt_labels: np.ndarray, points: np.ndarray, max_dist: float) -> np.ndarray:
    """Ground truth of map points: the label of the nearest scene point (``tree``: a cKDTree of
    the scene's points) within ``max_dist`` metres, else IGNORE."""
    if points.shape[0] == 0:
        return np.zeros(0, np.int16)
    d, idx = tree.query(points, k=1, workers=-1)
    return np.where(d <= max_dist, gt_labels[idx], IGNORE).astype(np.int16)


def online(cfg: Config, *, scene: Optional[Scene] = None, hooks: Optional[RunHooks] = None,
           backend: str = "auto", predicted: Optional[Sequence[Frame]] = None) -> OnlineResult:
    """Run the online protocol (module doc) on ``scene`` (default: the configured source).
    ``predicted``: the scene's frames with their predictions already attached (else they are
    made as configured, frame by frame). ``cfg`` is resolved first (:func:`~diffuser_lab.runs.resolve.resolve`)."""
    cfg = resolve(cfg)
    hooks = hooks or RunHooks()
    t0 = time.perf_counter()
    t: dict = {}
    if scene is None:
        scene = load_scene(cfg.scene, resolve_taxonomy(cfg), cfg.depth)
    if cfg.online.map != OnlineMap.growing:
        validate.check_points(scene)
    t["load"] = time.perf_counter() - t0
    hooks.on_scene(scene)
    frames = predicted if predicted is not None else with_predictions(scene.frames, cfg.predictions, scene.taxonomy,
                                                                       scene_name=scene.name)
    tm = time.perf_counter()
    m = _Map.of(cfg, scene, backend)
    t["map"] = time.perf_counter() - tm
    history, kept, finished = _take_frames(cfg, frames, m, hooks, t)
    if not kept:
        raise ValueError(f"scene {scene.name}: no frame could be taken ({len(frames)} frames)")
    od = m.od
    res = OnlineResult(scene=scene, mode=cfg.online.map.value, points=od.points.copy(), labels=od.labels.copy(),
                       bayesian_labels=od.bayesian_labels.copy(), gt=m.map_truth(), frames=history, metrics=None,
                       bayesian=None,
                       settings={"steps": od.steps, "gamma": od.gamma, "horizon": od.horizon,
                                 "rate_hz": float(cfg.online.rate), "finish": finished,
                                 "backend": od.backend_name, "rho_m": float(od.rho),
                                 "sigma_d_m": float(od.sigma_d)},
                       latency_ms=latency_summary(history))
    m.score(res)
    if cfg.online.compare_batch:
        tb = time.perf_counter()
        res.batch = compare_with_batch(cfg, scene, kept, od, res, m.rows)
        t["batch"] = time.perf_counter() - tb
    t["total"] = time.perf_counter() - t0
    res.timings_s = t
    hooks.on_result(res)
    return res


@dataclass
class _Map:
    """The online Diffuser's map and its ground truth. A growing map's points take the label of the
    nearest labelled scene point (``tree``: a cKDTree of the scene's points) within ``dist`` metres as
    they come (``gt``); a given map's rows are scored through the scene's points (``rows``: each scene
    point's map row; ``gt``: the scene's), as batch runs."""

    od: OnlineDiffuser
    scene: Scene
    growing: bool
    rows: Optional[np.ndarray] = None
    gt: Optional[np.ndarray] = None
    tree: object = None
    dist: float = 0.0

    @classmethod
    def of(cls, cfg: Config, scene: Scene, backend: str) -> "_Map":
        tax = scene.taxonomy
        if cfg.online.map == OnlineMap.growing:
            m = cls(OnlineDiffuser(cfg, tax, backend=backend), scene, True, dist=max(2.0 * cfg.online.voxel_size, 0.05))
            if scene.gt_labels is not None:  # a map point's truth: the nearest labelled scene point's
                from scipy.spatial import cKDTree

                m.gt, m.tree = np.zeros(0, np.int16), cKDTree(scene.points)
            return m
        pts, nrm, grid = work_cloud(scene, cfg.scene.voxel_size)
        with progress.stage(f"kNN graph of the given map (k={cfg.graph.k}, {pts.shape[0]:,} points)"):
            od = OnlineDiffuser(cfg, tax, points=pts, normals=nrm, backend=backend)
        rows = od.map_index[to_original(scene, grid, np.arange(pts.shape[0]))]  # scene point -> map row
        return cls(od, scene, False, rows=rows, gt=scene.gt_labels)

    def metrics(self, st: FrameStats) -> dict:
        """mIoU so far after a frame (:func:`frame_metrics`; a growing map's new points' truth added
        first), {} without ground truth."""
        od = self.od
        if self.growing and self.gt is not None and st.new_points:
            self.gt = np.concatenate([self.gt, _map_gt(self.tree, self.scene.gt_labels, od.points[-st.new_points:],
                                                       self.dist)])
        if self.gt is None:
            return {}
        if self.growing:
            return frame_metrics(od.labels, od.bayesian_labels, self.gt, self.scene.taxonomy.names)
        return frame_metrics(od.labels[self.rows], od.bayesian_labels[self.rows], self.gt, self.scene.taxonomy.names)

    def map_truth(self) -> Optional[np.ndarray]:
        """A growing map's points' ground truth (None for a given map: its truth is the scene's)."""
        return self.gt.copy() if self.growing and self.gt is not None else None

    def score(self, res: OnlineResult) -> None:
        """The final scores (a given map's on the scene's points, as batch runs) and its scene labels."""
        names = self.scene.taxonomy.names
        if self.growing:
            if self.gt is not None:
                res.metrics = score(res.labels, self.gt, names)
                res.bayesian = score(res.bayesian_labels, self.gt, names)
            return
        res.scene_labels = res.labels[self.rows]
        if self.scene.gt_labels is not None:
            res.metrics = score(res.scene_labels, self.scene.gt_labels, names)
            res.bayesian = score(res.bayesian_labels[self.rows], self.scene.gt_labels, names)


def _take_frames(cfg: Config, frames: Sequence[Frame], m: _Map, hooks: RunHooks, t: dict
                 ) -> tuple[list[dict], list[int], dict]:
    """The frames one at a time through the online Diffuser (the sensor's idle time spent on extra
    steps), then its final pass (``online.finish``: hooks see its steps). Returns every frame's
    figures, the frames taken and the final pass's."""
    od = m.od
    history: list[dict] = []
    kept: list[int] = []
    t["frames"] = t["update"] = t["metrics"] = 0.0

    def skipped(i: int, msg: str) -> None:
        history.append(dataclasses.asdict(od.skip_frame(str(i), msg, index=i)))

    loop = FrameLoop(frames, f"online ({cfg.online.map.value} map): {describe_predictions(cfg.predictions)}",
                     check=check_online_frame, skip_bad=cfg.online.bad_frames == BadFrame.skip,
                     warn_prefix="online: ", on_skip=skipped)
    blas = contextlib.ExitStack()  # BLAS's spinning workers would take the Jacobi threads' core between frames
    blas.enter_context(blas_one_thread())
    slot = 1.0 / cfg.online.rate if cfg.online.rate > 0 else 0.0  # the sensor's time between frames, s
    t["idle"] = 0.0
    finished: dict = {}
    try:
        for i, f in loop:
            tf = time.perf_counter()
            hooks.on_frame(i, f)
            tu = time.perf_counter()
            t["frames"] += tu - tf
            od.add_frame(f, index=i)
            t["update"] += time.perf_counter() - tu
            kept.append(i)
            st = od.history[-1]
            tq = time.perf_counter()
            metrics = m.metrics(st)
            t["metrics"] += time.perf_counter() - tq
            rec = {**dataclasses.asdict(st), **metrics}
            history.append(rec)
            if loop.bar.enabled:
                loop.bar.note(f"{st.latency_ms:.0f} ms, {od.n:,} points" +
                              (f", mIoU {metrics['diffuser_miou']:.1f}" if metrics else ""))
            hooks.on_online_frame(f, OnlineUpdate(index=i, stats=st, points=od.points, labels=od.labels,
                                                  bayesian=od.bayesian_labels, gt=m.gt if m.growing else None,
                                                  metrics=metrics, scores=od.scores))
            if slot:  # what the frame left of the sensor's frame time: extra steps (the next frame sees them)
                ti = time.perf_counter()
                od.idle(slot - (ti - tf))
                rec.update(idle_steps=st.idle_steps, idle_ms=st.idle_ms, changed=st.changed,
                           sweep_residual=st.sweep_residual, error_bound=st.error_bound)
                t["idle"] += time.perf_counter() - ti
        t["frames"] += loop.read_s
        tq = time.perf_counter()
        if kept and cfg.online.finish:
            finished = od.finish(cfg.online.finish, observer=Observe(hooks))  # hooks see its steps
        t["finish"] = time.perf_counter() - tq
    finally:
        od.close()
        blas.close()
    return history, kept, finished


def compare_with_batch(cfg: Config, scene: Scene, kept: list[int], od: OnlineDiffuser, res: OnlineResult,
                       rows: Optional[np.ndarray]) -> dict:
    """The batch Diffuser (with its Bayesian baseline) on the frames the online run took; for a
    growing map on its final cloud (points and normals as they are, no voxel grid). Returns
    their scores and the share of map points whose final online label equals the batch's."""
    bc = dataclasses.replace(cfg, method=dataclasses.replace(cfg.method, name="diffuser"))
    frames = LazyFrames.subset(scene.frames, kept) if len(kept) != len(scene.frames) else scene.frames
    if res.mode == "growing":
        bc = dataclasses.replace(bc, scene=dataclasses.replace(cfg.scene, voxel_size=0.0))
        bscene = Scene(name=scene.name, points=res.points.copy(), taxonomy=scene.taxonomy, frames=frames,
                       normals=None if od.normals is None else np.asarray(od.normals).copy(), gt_labels=res.gt)
    else:
        bscene = dataclasses.replace(scene, frames=frames)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # its warnings were the online run's
        b = run(bc, scene=bscene)
    if res.mode == "growing":
        batch_map = b.labels
        online_map = res.labels
    else:
        # the batch's work rows are the map's rows re-ordered: compare on the diffused points
        batch_map = np.empty_like(res.labels)
        batch_map[od.map_index] = labels_from_scores(b.diffusion.Z)
        online_map = res.labels
    out = {"equal_labels": float(100.0 * np.mean(batch_map == online_map)) if online_map.size else None,
           "iterations": int(b.diffusion.iterations) if b.diffusion is not None else None,
           "diffusion_s": float(b.timings_s.get("diffusion", 0.0)),
           "points": int(online_map.size)}
    if b.metrics is not None:
        out["diffuser"] = {k: b.metrics[k] for k in ("miou", "accuracy", "coverage", "per_class_iou")}
        out["bayesian"] = {k: b.baseline["bayesian"][k] for k in ("miou", "accuracy", "coverage")}
    return out


def summary(res: OnlineResult) -> dict:
    """summary.json content of an online run: ``metrics`` the final online Diffuser, ``baseline``
    the online Bayesian, ``online`` the settings, latency and every frame's figures, ``batch``."""
    s = res.scene
    return {
        "protocol": "online",
        "method": "diffuser",
        "scene": s.name,
        "map": res.mode,
        "n_points": int(s.n_points) if res.mode == "given" else int(res.points.shape[0]),
        "n_points_diffused": int(res.points.shape[0]),
        "n_frames": len(res.frames),
        "n_frames_skipped": sum(1 for f in res.frames if f.get("skipped")),
        "n_classes": s.taxonomy.num_classes,
        "taxonomy": s.taxonomy.name,
        "n_unlabeled": int((res.labels == IGNORE).sum()),
        "metrics": res.metrics,
        "baseline": {"bayesian": res.bayesian},
        "batch": res.batch,
        "online": {**res.settings, "latency_ms": res.latency_ms, "frames": res.frames},
        "diffusion": {"steps_per_frame": res.settings.get("steps"), "gamma": res.settings.get("gamma")},
        "timings_s": {k: round(v, 4) for k, v in res.timings_s.items()},
    }


def _f(x, spec=".1f") -> str:
    return "-" if x is None else format(x, spec)


def table(res: OnlineResult) -> str:
    s = res.scene
    n_taken = sum(1 for f in res.frames if not f.get("skipped"))
    skipped = len(res.frames) - n_taken
    lines = [f"diffuser-lab online | scene {s.name} | {res.mode} map: {res.points.shape[0]:,} points | "
             f"{n_taken} frames{f' ({skipped} skipped)' if skipped else ''} | {s.taxonomy.num_classes} classes"]
    L = res.latency_ms
    ok = [f for f in res.frames if not f.get("skipped")]
    part = lambda k: float(np.median([f[k] for f in ok])) if ok else 0.0  # noqa: E731
    st = res.settings
    lines.append(f"per frame [ms]  median {_f(L.get('median'))}  p95 {_f(L.get('p95'))}  max {_f(L.get('max'))}  "
                 f"(map {part('map_ms'):.1f}, graph {part('graph_ms'):.1f}, evidence {part('evidence_ms'):.1f}, "
                 f"steps {part('steps_ms'):.1f}; "
                 f"<= {st['steps']} steps, gamma {st['gamma']:.4f})")
    fin = st.get("finish") or {}
    if st.get("rate_hz") or fin:
        idle = f"idle steps at {st['rate_hz']:g} Hz: median {part('idle_steps'):.0f} a frame" if st.get("rate_hz") \
            else "no idle steps (online.rate=0)"
        lines.append(idle + (f"; final pass ({fin.get('final', 'settle')}) {fin['steps']} steps ({fin['ms'] / 1e3:.2f} s, "
                             f"relative change {fin['residual']:.1e})" if fin else ""))
    b = res.batch or {}
    if res.metrics is not None:
        lines.append(f"{'':22s}{'mIoU':>7s}{'acc':>7s}{'cover':>7s}")
        rows = [("online diffuser", res.metrics), ("online bayesian", res.bayesian)]
        if "diffuser" in b:
            rows += [("batch diffuser", b["diffuser"]), ("batch bayesian", b["bayesian"])]
        for name, m in rows:
            m = m or {}
            lines.append(f"{name:22s}{_f(m.get('miou')):>7s}{_f(m.get('accuracy')):>7s}{_f(m.get('coverage')):>7s}")
    else:
        lab = res.labels[res.labels != IGNORE]
        lines.append(f"no ground truth: no mIoU; the online Diffuser labelled {lab.size:,} of {res.labels.size:,} "
                     f"map points")
    if b.get("equal_labels") is not None:
        where = "on the final cloud" if res.mode == "growing" else "on the same frames"
        lines.append(f"final labels equal to the batch Diffuser's {where} ({b['iterations']} iterations): "
                     f"{b['equal_labels']:.1f}% of {b['points']:,} points")
    t = res.timings_s
    lines.append("time [s]  " + "  ".join(f"{k} {v:.2f}" for k, v in t.items()))
    return "\n".join(lines)
