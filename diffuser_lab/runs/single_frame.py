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
global runs (:func:`~diffuser_lab.runs.pipeline.graph_variant`).
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
from scipy.ndimage import distance_transform_edt

from diffuser_lab.config import Config, FrameNormals, GraphAffinity, SparseClasses
from diffuser_lab.data.frames import FrameLoop
from diffuser_lab.data.geometry import backproject, normals_from_depth, voxel_downsample, voxel_edge
from diffuser_lab.data.predictions import with_predictions
from diffuser_lab.data.scene import IGNORE, Frame, Scene
from diffuser_lab.data.taxonomy import resolve_taxonomy
from diffuser_lab.hooks import RunHooks
from diffuser_lab.method import calibration, fusion
from diffuser_lab.method import evidence as evidence_mod
from diffuser_lab.method import features as features_mod
from diffuser_lab.method.diffusion import labels_from_scores, normalise
from diffuser_lab.method.graph import SortedKnnGraph, graph_stage, make_graph
from diffuser_lab.method.metrics import confusion_matrix, scores_from_confusion

from .pipeline import FeatureLift, _Observe, feature_lift, graph_variant, lifting_rule, load_scene
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
    tax, names = scene.taxonomy, scene.taxonomy.names
    frames = with_predictions(scene.frames, cfg.predictions, tax, scene_name=scene.name)
    n = len(frames)
    if n == 0:
        raise ValueError(f"scene {scene.name}: no frames for the single-frame protocol")
    W = cfg.protocol.window
    targets = list(range(0, n, cfg.protocol.target_step))[: cfg.protocol.max_targets]
    order = [(m.name, v) for m in fusion.METHODS.values() if m.table_ii or m.name == cfg.method.name
             for v in m.single_frame_rows(W)]
    observed = ("diffuser", max(v for name, v in order if name == "diffuser")) if any(
        name == "diffuser" for name, _ in order) else None  # the diffusion the hooks see, per target
    count = 0
    settings = {}  # each method: (entry, the run's config with what it fixes applied, evidence pixel window)
    for m in fusion.METHODS.values():
        mc = with_method(cfg, m.name)
        settings[m.name] = (m, mc, 0 if m.evidence == fusion.BASELINE else mc.evidence.pixel_radius)
    rows = {key: Row(*key, cal=calibration.Calibration(tax.num_classes, cfg.calibration.bins)) for key in order}
    temperature = cfg.calibration.temperature
    pred2d = Row("2d", 1)
    t = {"load": time.perf_counter() - t0, "frames": 0.0, "evidence": 0.0, "graph": 0.0, "diffusion": 0.0}
    n_points = []
    ev_kw = dict(depth_tol=cfg.evidence.depth_tol)
    lam, solver = cfg.evidence.pixel_weight, cfg.solver
    fill = cfg.protocol.fill_missing_depth

    def need_gt(f: Frame) -> None:
        if f.gt_labels is None:
            raise ValueError(f"frame {f.name}: the single-frame protocol needs ground-truth label images")

    loop = FrameLoop(frames, f"single-frame protocol: target frames (window {W})", targets=targets, window=W,
                     check=need_gt)
    lift: Optional[FeatureLift] = None  # a features run (predictions=features): its queries
    for i, f in loop:
        if lift is None and f.features is not None:
            lift = feature_lift(cfg, tax, f.features.shape[2])
            solver = dataclasses.replace(solver, sparse_classes=SparseClasses.off)
            if W > 1:  # a features run's other baseline: each point's most confident view of the window
                order.append(("best_view", W))
                rows[("best_view", W)] = Row("best_view", W, cal=calibration.Calibration(tax.num_classes,
                                                                                          cfg.calibration.bins))
        ta = time.perf_counter()
        pts, pix = backproject(f.depth, f.K, f.T_cw)
        if pts.shape[0] <= cfg.graph.k:
            continue  # almost no depth in this frame: nothing to label
        edge = voxel_edge(cfg.scene.voxel_size, pts)  # auto: from this frame's back-projected points
        if edge > 0:
            grid = voxel_downsample(pts, edge)
            work, to_work = grid.points, grid.inverse
        else:
            work, to_work = pts, np.arange(pts.shape[0])
        n_points.append(work.shape[0])
        if lift is None:
            pred = f.labels if f.labels is not None else np.argmax(f.probs, axis=2)
            pred2d.add(pred, f.gt_labels, names)
        win_frames = loop.window_frames(i)
        at = np.full(f.shape, -1, np.int64)  # each pixel's work point (-1: no depth, uniform)
        at[pix[:, 0], pix[:, 1]] = to_work
        if fill:  # protocol.fill_missing_depth: a pixel without depth reads its nearest pixel with depth
            near = distance_transform_edt(at < 0, return_distances=False, return_indices=True)
            at = at[near[0], near[1]]
        t["frames"] += time.perf_counter() - ta
        count += 1
        watch = seen = None  # the observed row's observer (the hooks) and its result
        if lift is None and observed is not None:
            hooks.on_target(Target(index=i, count=count, frame=f, window=loop.window_of(i), frames=win_frames,
                                   work_points=work, pixels=at,
                                   work_gt=pixel_majority(at, f.gt_labels, work.shape[0], tax.num_classes),
                                   observed=observed))
            watch = _Observe(hooks, None)

        # each method's settings (what it fixes applied to the run's config), its evidence and
        # graph built once per target frame and shared between the rows that use them
        evidence, graphs, work_labels, work_scores = {}, {}, {}, {}
        for name, views in order:
            if name not in settings:  # best_view (below)
                continue
            m, mc, radius = settings[name]
            ekey = (views, radius)
            if ekey not in evidence:
                te = time.perf_counter()
                evidence[ekey] = evidence_mod.accumulate(work, win_frames if views > 1 else [f],
                                                         tax.num_classes if lift is None else lift.queries.dim,
                                                         pixel_radius=radius, **ev_kw)
                t["evidence"] += time.perf_counter() - te
            system = None
            gkey = (mc.graph.use_normals, mc.graph.k)  # LDLS: no normals, K = 10; Diffuser: the run's graph
            if m.graph:
                if gkey not in graphs:
                    tg = time.perf_counter()
                    nrm = None
                    if mc.graph.use_normals and cfg.protocol.normals == FrameNormals.depth_image:
                        nrm = image_normals(f, pix, to_work, work.shape[0], cfg.protocol.normal_window_px)
                    with graph_stage(work.shape[0], mc.graph, mc.graph.use_normals):
                        graphs[gkey] = make_graph(work, nrm, mc.graph)[1]
                    t["graph"] += time.perf_counter() - tg
            ev, key = evidence[ekey], (name, views)
            if m.evidence == fusion.RULE:  # a lifting rule: its own pass over the same links
                te = time.perf_counter()
                dim = tax.num_classes if lift is None else lift.queries.dim
                rule = lifting_rule(m, mc, work.shape[0], dim, tax.num_classes, lift)
                evidence_mod.accumulate(work, win_frames if views > 1 else [f], dim, pixel_radius=radius, hook=rule,
                                        **ev_kw)
                values = rule.values()
                t["evidence"] += time.perf_counter() - te
                if lift is None or rule.classes:
                    work_labels[key], work_scores[key] = labels_from_scores(values), values
                else:
                    work_labels[key], work_scores[key] = lift.labels(values), lift.scores(values)
                continue
            graph = graphs.get(gkey) if m.graph else None
            if m.graph and (cfg.graph.affinity != GraphAffinity.none or cfg.solver.tikhonov > 0):
                vkey = ("variant", gkey, ekey)  # the graph and evidence of this evidence's variant
                if vkey not in graphs:
                    tg = time.perf_counter()
                    g = graph if cfg.graph.affinity == GraphAffinity.none else copy_graph(graph)
                    colors = (frame_colors(f, pix, to_work, work.shape[0])
                              if cfg.graph.affinity == GraphAffinity.colour else None)
                    average = features_mod.normalised(ev.mass)[0] if lift is not None else None
                    graphs[vkey] = g, graph_variant(g, ev, mc, colors=colors, average=average)
                    t["graph"] += time.perf_counter() - tg
                graph, ev = graphs[vkey]
            if lift is None and m.graph:
                system = normalise(graph, ev.mass, lam)
            td = time.perf_counter()
            if lift is None:
                work_labels[key], diff = m.label(ev.mass, system=system, solver=solver,
                                                 observer=watch if key == observed else None)
                if key == observed:
                    seen = diff
                work_scores[key] = diff.Z if diff is not None else ev.mass
            else:  # a features run, as the global protocol's (method/features.py; the rows share ev: a copy)
                F = (features_mod.diffuse_features(graph, ev.mass.copy(), ev.links, lam, solver)[0] if m.graph
                     else ev.mass)
                work_labels[key], work_scores[key] = lift.labels(F), lift.scores(F)
            if m.graph:
                t["diffusion"] += time.perf_counter() - td

        if lift is not None and W > 1:
            te = time.perf_counter()
            best = evidence_mod.BestView(work.shape[0], lift.queries.dim, lift.confidence)
            evidence_mod.accumulate(work, win_frames, lift.queries.dim, best=best, **ev_kw)
            work_labels[("best_view", W)] = lift.labels(best.features)
            work_scores[("best_view", W)] = lift.scores(best.features)
            t["evidence"] += time.perf_counter() - te

        images = {}
        for key, lab in work_labels.items():  # 3D labels back into the target frame
            img = np.where(at >= 0, lab[np.maximum(at, 0)], IGNORE).astype(np.int16)
            rows[key].add(img, f.gt_labels, names)
            rows[key].cal.add(work_scores[key], f.gt_labels, at, temperature)
            images[key] = img
        if on_frame is not None:
            on_frame(f, images)
        if watch is not None:  # Table II as it accumulates: every row's pooled figures so far, this frame's
            hooks.on_target_done(i, images, [{**rows[k].result(names), "frame_miou": rows[k].per_frame_miou[-1]}
                                             for k in order if k in images], seen)
    t["frames"] += loop.read_s

    t["total"] = time.perf_counter() - t0
    results = [rows[k].result(names) for k in order]
    for r in results:
        r["calibration"]["temperature"] = float(temperature)
    p2 = pred2d.result(names) if pred2d.conf is not None else None
    res = SingleFrameResult(scene=scene, window=W, targets=targets, rows=results, predictions_2d=p2,
                            mean_points=float(np.mean(n_points)) if n_points else 0.0, timings_s=t,
                            filled=bool(fill), method=cfg.method.name)
    hooks.on_result(res)
    return res


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
