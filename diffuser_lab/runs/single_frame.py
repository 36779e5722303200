"""The paper's single RGB-D frame protocol (Sec. IV-A-2, Table II).

For each target frame: back-project its depth into a point cloud (voxel-downsampled with
``scene.voxel_size`` when > 0), label that cloud from the target frame alone (1 view) or from
a window of W neighbouring frames centred on it (W views), project the 3D labels back into
the target frame and score 2D mIoU against its ground-truth label image. Pixels without
depth or without a label count as misses of their true class.

Rows (paper Table II): each fusion method of :data:`~diffuser_lab.method.fusion.METHODS` with
1 view and, where it fuses several, W views: direct projection (1), LDLS (1), Bayesian fusion
(1, W), Diffuser (1, W); Bayesian with 1 view is the direct row up to voxel merging. The
Bayesian rows read the baseline's evidence (single pixel), as in global runs. A method outside
Table II (the lifting rules of :mod:`diffuser_lab.method.lifters`) adds its rows when it is the run's
``method.name``; ``graph.affinity`` and ``solver.tikhonov`` change the graph methods' rows as in
global runs (:func:`~diffuser_lab.method.fusion.graph_variant`). What differs between the methods
is their registry entries' (the evidence they read, whether they diffuse), between labels and
features the run's label space's (:mod:`diffuser_lab.method.space`: a features run adds the best view).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
from scipy.ndimage import distance_transform_edt

from diffuser_lab.config import Config, FrameNormals, GraphAffinity
from diffuser_lab.data.frames import FrameLoop
from diffuser_lab.data.geometry import backproject, normals_from_depth, voxel_downsample, voxel_edge
from diffuser_lab.data.predictions import with_predictions
from diffuser_lab.data.scene import IGNORE, Frame, Scene
from diffuser_lab.data.taxonomy import resolve_taxonomy
from diffuser_lab.hooks import RunHooks
from diffuser_lab.method import calibration, fusion
from diffuser_lab.method import evidence as evidence_mod
from diffuser_lab.method.diffusion import DiffusionResult
from diffuser_lab.method.evidence import Evidence
from diffuser_lab.method.fusion import graph_variant
from diffuser_lab.method.graph import SortedKnnGraph, graph_stage, make_graph
from diffuser_lab.method.metrics import confusion_matrix, scores_from_confusion
from diffuser_lab.method.space import of_frame as label_space

from .pipeline import load_scene
from .resolve import resolve, with_method


@dataclass
class Row:
    method: str
    views: int
    conf: Optional[np.ndarray] = None  # pooled (C, C+1) confusion over target frames
    per_frame_miou: list = field(default_factory=list)
    cal: Optional[calibration.Calibration] = None  # its class distributions over the target frames' pixels

    def add(self, pred_img: np.ndarray, gt: np.ndarray, names) -> None:
        c = confusion_matrix(pred_img, gt, len(names))
        self.conf = c if self.conf is None else self.conf + c
        self.per_frame_miou.append(scores_from_confusion(c, names)["miou"])

    def result(self, names) -> dict:
        s = scores_from_confusion(self.conf, names) if self.conf is not None else {}
        pf = np.array(self.per_frame_miou, float)
        return {"method": self.method, "views": self.views, "miou": s.get("miou"), "accuracy": s.get("accuracy"),
                "mean_frame_miou": float(np.nanmean(pf)) if pf.size else None,
                "per_class_iou": s.get("per_class_iou"),
                **({"calibration": self.cal.result()} if self.cal is not None else {})}


@dataclass
class Target:
    """A target frame as hooks see it before its diffusion (``on_target``; arrays read-only, the
    frames valid during the call only).

    Attributes:
        index: the target frame's index; count: 1-based count of targets labelled so far.
        frame: the target frame (predictions and ground truth attached).
        window: the indices of the frames it is labelled from (its own among them), ``frames`` those frames.
        work_points: (M, 3) float32 its back-projected depth (voxel centroids with scene.voxel_size), world m.
        pixels: (H, W) int64 each pixel's work point (-1: no depth; with protocol.fill_missing_depth
            the nearest pixel's), the 3D labels' way back into the image.
        work_gt: (M,) int16 the most frequent ground truth of each work point's pixels (-1: none).
        observed: the Table II row (method, views) whose diffusion the hooks observe (the Diffuser
            with the window's views).
    """

    index: int
    count: int
    frame: Frame
    window: list
    frames: list
    work_points: np.ndarray
    pixels: np.ndarray
    work_gt: np.ndarray
    observed: tuple


def pixel_majority(pixels: np.ndarray, gt: np.ndarray, m: int, num_classes: int) -> np.ndarray:
    """(m,) int16: per work point the most frequent ground-truth class among the pixels
    ``pixels`` (H, W) maps to it (the smallest of equally frequent ones; -1 where none is annotated)."""
    at, g = np.asarray(pixels).ravel(), np.asarray(gt).ravel().astype(np.int64)
    ok = (at >= 0) & (g >= 0) & (g < num_classes)
    key, cnt = np.unique(at[ok] * num_classes + g[ok], return_counts=True)
    row, cls = key // num_classes, key % num_classes
    out = np.full(m, IGNORE, np.int16)
    order = np.lexsort((cls, -cnt, row))  # per row: the largest count first, then the smallest class
    first = np.ones(len(order), bool)
    first[1:] = row[order][1:] != row[order][:-1]
    out[row[order][first]] = cls[order][first]
    return out


@dataclass
class SingleFrameResult:
    scene: Scene
    window: int
    targets: list[int]
    rows: list[dict]
    predictions_2d: Optional[dict]
    mean_points: float
    timings_s: dict
    filled: bool = False  # protocol.fill_missing_depth was on (not the paper's protocol)
    method: str = "diffuser"  # the run's method.name: summary.json's metrics are its widest row


def image_normals(f: Frame, pix: np.ndarray, to_work: np.ndarray, m: int, window: int) -> np.ndarray:
    """(m, 3) float32 unit world normals of a target frame's work points from its organised depth
    image: the depth box-averaged over ``window`` x ``window`` valid pixels (sensor noise is
    per pixel; PCA over a noisy cloud's kNN sees it in 3D), normals by central differences
    (:func:`diffuser_lab.data.geometry.normals_from_depth`), turned towards the camera, averaged
    over each work point's pixels (``pix`` (P, 2) rows/cols -> ``to_work`` (P,) in 0..m-1)."""
    n = normals_from_depth(np.asarray(f.depth, np.float64), f.K, pix, T_cw=f.T_cw, window=window)
    acc = np.zeros((m, 3))
    np.add.at(acc, to_work, n)
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    out = np.where(norm > 0, acc / np.maximum(norm, 1e-30), np.array([0.0, 0.0, 1.0]))
    return out.astype(np.float32)


def single_frame(cfg: Config, scene: Optional[Scene] = None, on_frame=None,
                 hooks: Optional[RunHooks] = None) -> SingleFrameResult:
    """The single RGB-D frame protocol (paper Table II). ``on_frame(frame, images)``, if given, sees
    each target frame and its rows' label images ({(method, views): (H, W) int16}) as scored;
    ``hooks`` (:mod:`diffuser_lab.hooks`) see the scene, each target (``on_target``), the
    Diffuser's diffusion with the window's views on it (statistics, ``wants`` / ``observe``), its
    rows (``on_target_done``) and the result. Neither changes the result. ``cfg`` is resolved
    first (:func:`~diffuser_lab.runs.resolve.resolve`)."""
    cfg = resolve(cfg)
    hooks = hooks or RunHooks()
    t0 = time.perf_counter()
    if scene is None:
        scene = load_scene(cfg.scene, resolve_taxonomy(cfg), cfg.depth)
    hooks.on_scene(scene)
    tax = scene.taxonomy
    frames = with_predictions(scene.frames, cfg.predictions, tax, scene_name=scene.name)
    if len(frames) == 0:
        raise ValueError(f"scene {scene.name}: no frames for the single-frame protocol")
    W = cfg.protocol.window
    targets = list(range(0, len(frames), cfg.protocol.target_step))[: cfg.protocol.max_targets]
    table = _Table(cfg, tax, W)
    t = {"load": time.perf_counter() - t0, "frames": 0.0, "evidence": 0.0, "graph": 0.0, "diffusion": 0.0}
    n_points, count, space = [], 0, None

    def need_gt(f: Frame) -> None:
        if f.gt_labels is None:
            raise ValueError(f"frame {f.name}: the single-frame protocol needs ground-truth label images")

    loop = FrameLoop(frames, f"single-frame protocol: target frames (window {W})", targets=targets, window=W,
                     check=need_gt)
    for i, f in loop:
        space = space or table.start(label_space(f, cfg, tax, fusion.get(cfg.method.name)))  # labels or features
        ta = time.perf_counter()
        work = _TargetWork.of(cfg, f)
        if work is None:
            continue  # almost no depth in this frame: nothing to label
        n_points.append(work.points.shape[0])
        table.add_2d(space, f)
        win_frames = loop.window_frames(i)
        t["frames"] += time.perf_counter() - ta
        count += 1
        watch = None  # the observed row's observer (the hooks)
        if table.observed is not None:
            hooks.on_target(Target(index=i, count=count, frame=f, window=loop.window_of(i), frames=win_frames,
                                   work_points=work.points, pixels=work.at,
                                   work_gt=pixel_majority(work.at, f.gt_labels, work.points.shape[0], tax.num_classes),
                                   observed=table.observed))
            watch = space.observer(hooks, None)
        labelled, seen = _label_target(cfg, space, table, f, win_frames, work, watch, t)
        images = table.add(labelled, work.at, f)
        if on_frame is not None:
            on_frame(f, images)
        if watch is not None:  # Table II as it accumulates: every row's pooled figures so far, this frame's
            hooks.on_target_done(i, images, table.so_far(images), seen)
    t["frames"] += loop.read_s
    t["total"] = time.perf_counter() - t0
    res = SingleFrameResult(scene=scene, window=W, targets=targets, rows=table.results(), predictions_2d=table.input_2d(),
                            mean_points=float(np.mean(n_points)) if n_points else 0.0, timings_s=t,
                            filled=bool(cfg.protocol.fill_missing_depth), method=cfg.method.name)
    hooks.on_result(res)
    return res


class _Table:
    """Table II as it accumulates: its rows in order (each fusion method's, then those the run's label
    space adds), each with its pooled confusion and calibration, and the 2D input's row; each method's
    entry with the run's config as it fixes it."""

    def __init__(self, cfg: Config, tax, window: int):
        self.names, self.window, self.bins, self.temperature = tax.names, window, cfg.calibration.bins, \
            cfg.calibration.temperature
        self.num_classes = tax.num_classes
        self.methods = {m.name: (m, with_method(cfg, m.name)) for m in fusion.METHODS.values()}
        self.method_rows = [(m.name, v) for m in fusion.METHODS.values() for v in m.table_rows(window, cfg.method.name)]
        self.order, self.rows, self.observed = list(self.method_rows), {}, None
        self.pred2d = Row("2d", 1)

    def start(self, space):
        """The rows of a run in ``space`` (returned): the methods' and the space's (features: the best
        view), and the row whose diffusion the hooks observe (the Diffuser's widest; none in features)."""
        self.order = self.method_rows + space.extra_rows(self.window)
        self.rows = {key: Row(*key, cal=calibration.Calibration(self.num_classes, self.bins)) for key in self.order}
        observed = [(name, v) for name, v in self.method_rows if self.methods[name][0].observed]
        self.observed = space.watched(max(observed, key=lambda r: r[1])) if observed else None
        return space

    def add_2d(self, space, f: Frame) -> None:
        pred = space.label_image(f)  # None: a features run's maps are no labels
        if pred is not None:
            self.pred2d.add(pred, f.gt_labels, self.names)

    def add(self, labelled: dict, at: np.ndarray, f: Frame) -> dict:
        """Each row's 3D labels (and scores) of a target's work points back into the target frame,
        scored; returns the label images."""
        images = {}
        for key, (lab, scores) in labelled.items():
            img = np.where(at >= 0, lab[np.maximum(at, 0)], IGNORE).astype(np.int16)
            self.rows[key].add(img, f.gt_labels, self.names)
            self.rows[key].cal.add(scores, f.gt_labels, at, self.temperature)
            images[key] = img
        return images

    def so_far(self, images: dict) -> list[dict]:
        return [{**self.rows[k].result(self.names), "frame_miou": self.rows[k].per_frame_miou[-1]}
                for k in self.order if k in images]

    def results(self) -> list[dict]:
        out = [self.rows[k].result(self.names) for k in self.order]
        for r in out:
            r["calibration"]["temperature"] = float(self.temperature)
        return out

    def input_2d(self) -> Optional[dict]:
        return self.pred2d.result(self.names) if self.pred2d.conf is not None else None


@dataclass
class _TargetWork:
    """A target frame's back-projected depth as work points (voxel centroids with scene.voxel_size):
    ``points`` (M, 3), ``pix`` (P, 2) the pixels with depth, ``to_work`` (P,) each one's work point,
    ``at`` (H, W) each pixel's work point (-1: no depth; with protocol.fill_missing_depth the nearest pixel's)."""

    points: np.ndarray
    pix: np.ndarray
    to_work: np.ndarray
    at: np.ndarray

    @classmethod
    def of(cls, cfg: Config, f: Frame) -> Optional["_TargetWork"]:
        """None when the frame has almost no depth (no more points than graph.k)."""
        pts, pix = backproject(f.depth, f.K, f.T_cw)
        if pts.shape[0] <= cfg.graph.k:
            return None
        edge = voxel_edge(cfg.scene.voxel_size, pts)  # auto: from this frame's back-projected points
        if edge > 0:
            grid = voxel_downsample(pts, edge)
            work, to_work = grid.points, grid.inverse
        else:
            work, to_work = pts, np.arange(pts.shape[0])
        at = np.full(f.shape, -1, np.int64)  # each pixel's work point (-1: no depth, uniform)
        at[pix[:, 0], pix[:, 1]] = to_work
        if cfg.protocol.fill_missing_depth:  # a pixel without depth reads its nearest pixel with depth
            near = distance_transform_edt(at < 0, return_distances=False, return_indices=True)
            at = at[near[0], near[1]]
        return cls(work, pix, to_work, at)


def _label_target(cfg: Config, space, table: _Table, f: Frame, win_frames: list, work: _TargetWork, watch,
                  t: dict) -> tuple[dict, Optional[DiffusionResult]]:
    """Every row's (labels, class scores) of a target's work points, by (method, views), and the observed
    row's diffusion: each method asked for its evidence and labels (:mod:`~diffuser_lab.method.fusion`),
    in the run's label space; the evidence and graphs shared between the rows that use the same."""
    shared = _Shared(cfg, space, f, work, t)
    out, seen = {}, None
    solver = space.solver(cfg.solver)
    for name, views in table.method_rows:
        m, mc = table.methods[name]
        frames = win_frames if views > 1 else [f]
        ekey = (views, m.evidence_radius(mc))
        te = time.perf_counter()
        ev, rule = m.window_evidence(space, mc, work.points, frames,
                                     lambda radius, frames=frames: shared.evidence((views, radius), frames))
        t["evidence"] += time.perf_counter() - te
        key, g0, td = (name, views), t["graph"], time.perf_counter()
        labelled = m.label(space, ev, rule=rule, graph=lambda e, mc=mc, ekey=ekey: shared.graph(mc, ekey, e),
                           solver=solver, lam=cfg.evidence.pixel_weight, observer=watch if key == table.observed else None)
        out[key] = labelled.labels, labelled.scores
        if labelled.diffusion is not None:
            t["diffusion"] += time.perf_counter() - td - (t["graph"] - g0)
        seen = labelled.diffusion if key == table.observed else seen
    te = time.perf_counter()
    out.update(space.window_baselines(work.points, win_frames, table.window, cfg.evidence.depth_tol))
    t["evidence"] += time.perf_counter() - te
    return out, seen


class _Shared:
    """A target's evidence per (views, pixel window) and graphs per (normals, K) (LDLS: no normals,
    K = 10; Diffuser: the run's graph) with their ``graph.affinity`` / ``solver.tikhonov`` variants per
    evidence, each built once and shared between the rows that use them."""

    def __init__(self, cfg: Config, space, f: Frame, work: _TargetWork, t: dict):
        self.cfg, self.space, self.f, self.work, self.t = cfg, space, f, work, t
        self.evidences: dict = {}
        self.graphs: dict = {}

    def evidence(self, key: tuple, frames: list) -> Evidence:
        if key not in self.evidences:
            self.evidences[key] = evidence_mod.accumulate(self.work.points, frames, self.space.dim, pixel_radius=key[1],
                                                          depth_tol=self.cfg.evidence.depth_tol)
        return self.evidences[key]

    def graph(self, mc: Config, ekey: tuple, ev: Evidence) -> tuple[SortedKnnGraph, Evidence]:
        """The graph of ``mc``'s keys and the evidence ``ev`` (of ``ekey``) as its variant changes them;
        the evidence's mass a copy (a features diffusion may overwrite it, the rows share it)."""
        tg = time.perf_counter()
        cfg, w = self.cfg, self.work
        gkey = (mc.graph.use_normals, mc.graph.k)
        if gkey not in self.graphs:
            nrm = None
            if mc.graph.use_normals and cfg.protocol.normals == FrameNormals.depth_image:
                nrm = image_normals(self.f, w.pix, w.to_work, w.points.shape[0], cfg.protocol.normal_window_px)
            with graph_stage(w.points.shape[0], mc.graph, mc.graph.use_normals):
                self.graphs[gkey] = make_graph(w.points, nrm, mc.graph)[1]
        graph = self.graphs[gkey]
        if cfg.graph.affinity != GraphAffinity.none or cfg.solver.tikhonov > 0:
            vkey = ("variant", gkey, ekey)  # the graph and evidence of this evidence's variant
            if vkey not in self.graphs:
                g = graph if cfg.graph.affinity == GraphAffinity.none else copy_graph(graph)
                colors = (frame_colors(self.f, w.pix, w.to_work, w.points.shape[0])
                          if cfg.graph.affinity == GraphAffinity.colour else None)
                self.graphs[vkey] = g, graph_variant(g, ev, mc, colors=colors, average=self.space.averaged(ev.mass))
            graph, ev = self.graphs[vkey]
        self.t["graph"] += time.perf_counter() - tg
        return graph, Evidence(mass=ev.mass.copy(), links=ev.links)


def copy_graph(g: SortedKnnGraph) -> SortedKnnGraph:
    """The graph with its own edge weights (``graph.affinity`` changes them per evidence)."""
    return SortedKnnGraph(g.order, g.sorted_neighbors, g.sorted_weights.copy(), g.sorted_row_sums.copy(), g.rho,
                          g.sigma_d)


def frame_colors(f: Frame, pix: np.ndarray, to_work: np.ndarray, m: int) -> Optional[np.ndarray]:
    """(m, 3) float32 [0, 1] the work points' colours from the target frame's image (a work point:
    the mean of its pixels'); None when the frame has no colour image (``graph.affinity=colour``
    then says so)."""
    rgb = getattr(f, "rgb", None)
    if rgb is None:
        return None
    rgb = np.asarray(rgb)
    if rgb.shape[:2] != f.shape:
        raise ValueError(f"frame {f.name}: colour image {rgb.shape[:2]} != depth {f.shape}")
    c = rgb[pix[:, 0], pix[:, 1], :3].astype(np.float64) / (255.0 if rgb.dtype == np.uint8 else 1.0)
    counts = np.bincount(to_work, minlength=m).astype(np.float64)
    cols = [np.bincount(to_work, weights=c[:, j], minlength=m) for j in range(3)]
    return (np.stack(cols, 1) / np.maximum(counts, 1)[:, None]).astype(np.float32)


def table(res: SingleFrameResult) -> str:
    lines = [f"diffuser-lab single-frame protocol | scene {res.scene.name} | {len(res.targets)} target frames | "
             f"window {res.window} | {res.mean_points:,.0f} points per frame"
             + (" | pixels without depth filled (protocol.fill_missing_depth, not the paper's protocol)"
                if res.filled else "")]
    lines.append(f"{'method':12s}{'views':>6s}{'2D mIoU':>9s}{'frame mean':>12s}{'acc':>7s}")
    for r in res.rows:
        lines.append(f"{r['method']:12s}{r['views']:>6d}{r['miou']:>9.1f}{r['mean_frame_miou']:>12.1f}"
                     f"{r['accuracy']:>7.1f}")
    if res.predictions_2d:
        p = res.predictions_2d
        lines.append(f"{'2D input':12s}{'':>6s}{p['miou']:>9.1f}{p['mean_frame_miou']:>12.1f}{p['accuracy']:>7.1f}")
    lines.append("time [s]  " + "  ".join(f"{k} {v:.2f}" for k, v in res.timings_s.items()))
    return "\n".join(lines)
