"""The paper's single RGB-D frame protocol (Sec. IV-A-2, Table II).

For each target frame: back-project its depth into a point cloud (voxel-downsampled with
``scene.voxel_size`` when > 0), label that cloud from the target frame alone (1 view) or from
a window of W neighbouring frames centred on it (W views), project the 3D labels back into
the target frame and score 2D mIoU against its ground-truth label image. Pixels without
depth or without a label count as misses of their true class.

Rows (paper Table II): direct projection (1 view), LDLS (1 view), Bayesian fusion (W views),
Diffuser (1 view), Diffuser (W views); Bayesian with 1 view is the direct row up to
voxel merging and is reported too.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Optional

import numpy as np

from . import evidence as evidence_mod
from . import progress
from .config import Config
from .diffusion import labels_from_scores, normalise, solve
from .geometry import backproject, voxel_downsample
from .metrics import confusion_matrix, scores_from_confusion
from .pipeline import graph_stage, load_scene, make_graph
from .predictions import with_predictions
from .scene import IGNORE, Frame, Scene

LDLS_PIXEL_RADIUS = 1  # as conf/method/ldls.yaml


@dataclass
class Row:
    method: str
    views: int
    conf: Optional[np.ndarray] = None  # pooled (C, C+1) confusion over target frames
    per_frame_miou: list = field(default_factory=list)

    def add(self, pred_img: np.ndarray, gt: np.ndarray, names) -> None:
        c = confusion_matrix(pred_img, gt, len(names))
        self.conf = c if self.conf is None else self.conf + c
        self.per_frame_miou.append(scores_from_confusion(c, names)["miou"])

    def result(self, names) -> dict:
        s = scores_from_confusion(self.conf, names) if self.conf is not None else {}
        pf = np.array(self.per_frame_miou, float)
        return {"method": self.method, "views": self.views, "miou": s.get("miou"), "accuracy": s.get("accuracy"),
                "mean_frame_miou": float(np.nanmean(pf)) if pf.size else None,
                "per_class_iou": s.get("per_class_iou")}


@dataclass
class SingleFrameResult:
    scene: Scene
    window: int
    targets: list[int]
    rows: list[dict]
    predictions_2d: Optional[dict]
    mean_points: float
    timings_s: dict


def _window(i: int, n: int, w: int) -> list[int]:
    """W frame indices around target i (kept at W near the ends of the sequence)."""
    w = min(w, n)
    start = min(max(i - w // 2, 0), n - w)
    return list(range(start, start + w))


def single_frame(cfg: Config, scene: Optional[Scene] = None) -> SingleFrameResult:
    t0 = time.perf_counter()
    if scene is None:
        scene = load_scene(cfg.scene)
    tax, names = scene.taxonomy, scene.taxonomy.names
    frames = with_predictions(scene.frames, cfg.predictions, tax)
    n = len(frames)
    if n == 0:
        raise ValueError(f"scene {scene.name}: no frames for the single-frame protocol")
    W = cfg.protocol.window
    targets = list(range(0, n, cfg.protocol.target_step))[: cfg.protocol.max_targets]
    rows = {key: Row(*key) for key in [("direct", 1), ("ldls", 1), ("bayesian", 1), ("bayesian", W),
                                       ("diffuser", 1), ("diffuser", W)]}
    pred2d = Row("2d", 1)
    cache: dict[int, Frame] = {}
    t = {"load": time.perf_counter() - t0, "frames": 0.0, "evidence": 0.0, "graph": 0.0, "diffusion": 0.0}
    n_points = []
    ev_kw = dict(depth_tol=cfg.evidence.depth_tol)
    lam, solver = cfg.evidence.pixel_weight, cfg.solver

    def frame(j: int) -> Frame:
        if j not in cache:
            cache[j] = frames[j]
        return cache[j]

    with progress.stage(f"single-frame protocol: target frames (window {W})", total=len(targets),
                        unit="frame") as bar:
        for k, i in enumerate(targets):
            bar.set(k)
            ta = time.perf_counter()
            win = _window(i, n, W)
            for j in [j for j in cache if j not in win]:  # keep only the current window in memory
                del cache[j]
            f = frame(i)
            if f.gt_labels is None:
                raise ValueError(f"frame {f.name}: the single-frame protocol needs ground-truth label images")
            pts, pix = backproject(f.depth, f.K, f.T_cw)
            if pts.shape[0] <= cfg.graph.k:
                continue  # almost no depth in this frame: nothing to label
            if cfg.scene.voxel_size > 0:
                grid = voxel_downsample(pts, cfg.scene.voxel_size)
                work, to_work = grid.points, grid.inverse
            else:
                work, to_work = pts, np.arange(pts.shape[0])
            n_points.append(work.shape[0])
            pred = f.labels if f.labels is not None else np.argmax(f.probs, axis=2)
            pred2d.add(pred, f.gt_labels, names)
            win_frames = [frame(j) for j in win]
            t["frames"] += time.perf_counter() - ta

            te = time.perf_counter()
            ev1 = evidence_mod.accumulate(work, [f], tax.num_classes, pixel_radius=cfg.evidence.pixel_radius, **ev_kw)
            ev1_base = ev1 if cfg.evidence.pixel_radius == 0 else evidence_mod.accumulate(work, [f], tax.num_classes,
                                                                                          **ev_kw)
            ev1_ldls = evidence_mod.accumulate(work, [f], tax.num_classes, pixel_radius=LDLS_PIXEL_RADIUS, **ev_kw)
            evW = evidence_mod.accumulate(work, win_frames, tax.num_classes, pixel_radius=cfg.evidence.pixel_radius,
                                          **ev_kw)
            evW_base = evW if cfg.evidence.pixel_radius == 0 else evidence_mod.accumulate(work, win_frames,
                                                                                          tax.num_classes, **ev_kw)
            t["evidence"] += time.perf_counter() - te

            tg = time.perf_counter()
            with graph_stage(work.shape[0], cfg.graph, cfg.graph.use_normals):
                _, g_diff = make_graph(work, None, cfg.graph)
                _, g_ldls = make_graph(work, None, replace(cfg.graph, use_normals=False))
            t["graph"] += time.perf_counter() - tg

            td = time.perf_counter()
            work_labels = {
                ("direct", 1): labels_from_scores(ev1_base.mass),
                ("bayesian", 1): labels_from_scores(ev1_base.mass),
                ("bayesian", W): labels_from_scores(evW_base.mass),
            }
            for key, g, ev in [(("ldls", 1), g_ldls, ev1_ldls), (("diffuser", 1), g_diff, ev1),
                               (("diffuser", W), g_diff, evW)]:
                z = solve(normalise(g, ev.mass, lam), solver).Z
                work_labels[key] = labels_from_scores(z)
            t["diffusion"] += time.perf_counter() - td

            for key, lab in work_labels.items():  # 3D labels back into the target frame
                img = np.full(f.shape, IGNORE, np.int16)
                img[pix[:, 0], pix[:, 1]] = lab[to_work]
                rows[key].add(img, f.gt_labels, names)
        bar.set(len(targets))

    t["total"] = time.perf_counter() - t0
    order = [("direct", 1), ("ldls", 1), ("bayesian", 1), ("bayesian", W), ("diffuser", 1), ("diffuser", W)]
    results = [rows[k].result(names) for k in dict.fromkeys(order)]  # W = 1 folds duplicate rows
    p2 = pred2d.result(names) if pred2d.conf is not None else None
    return SingleFrameResult(scene=scene, window=W, targets=targets, rows=results, predictions_2d=p2,
                             mean_points=float(np.mean(n_points)) if n_points else 0.0, timings_s=t)


def table(res: SingleFrameResult) -> str:
    lines = [f"diffuser-lab single-frame protocol | scene {res.scene.name} | {len(res.targets)} target frames | "
             f"window {res.window} | {res.mean_points:,.0f} points per frame"]
    lines.append(f"{'method':12s}{'views':>6s}{'2D mIoU':>9s}{'frame mean':>12s}{'acc':>7s}")
    for r in res.rows:
        lines.append(f"{r['method']:12s}{r['views']:>6d}{r['miou']:>9.1f}{r['mean_frame_miou']:>12.1f}"
                     f"{r['accuracy']:>7.1f}")
    if res.predictions_2d:
        p = res.predictions_2d
        lines.append(f"{'2D input':12s}{'':>6s}{p['miou']:>9.1f}{p['mean_frame_miou']:>12.1f}{p['accuracy']:>7.1f}")
    lines.append("time [s]  " + "  ".join(f"{k} {v:.2f}" for k, v in res.timings_s.items()))
    return "\n".join(lines)
