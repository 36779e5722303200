"""The records of a tiled run (``protocol=tiled``, docs/tiling.md): written by the driver from the
run's result once the tiles are done (:func:`record_tiled`), never by a tile or a Ray worker.

A tiled run records only its final labels and its tiles' figures: no evidence, no cameras, no
intermediate Z (a tile's diffusion is not observed; the scenes tiling is for are too large for
per-iteration clouds). The clouds are thinned for display: every n-th point, n = ceil(N /
:data:`MAX_DISPLAY_POINTS`) (:func:`display_index`), the same points in both files.

run.rrd (application id ``diffuser_lab_tiled``; blueprint: labels, tiles, errors and ground truth
in tabs over the legend, beside the tiles' table and bar charts; the boxes only in the tiles tab,
the cloud in grey there and in the errors tab)::

    world                       AnnotationContext (taxonomy names + colours; 65535 = unlabeled)
    world/tiled/labels          Points3D, static: final labels of the displayed points
    world/tiled/ground_truth    Points3D, static: ground-truth class ids (when known)
    world/tiled/wrong           Points3D, static: displayed points whose label is wrong (when known)
    world/tiled/tiles           Boxes3D, static, outlines: one box per tile (x-y cell cut to its
                                points' extent, z of the cloud), coloured by status (green done,
                                red failed, grey kept from tiling.resume), labelled "<id> <status>"
    legend/classes              Points2D, static: the classes present, unlabeled, wrong label
    tiles                       TextDocument, static: the tiles' table (markdown, ``#`` = row)
    tile/<figure>/<tile id>     BarChart, static: one bar at x = the tile's row (accuracy [%] with
                                ground truth, iterations, residual_log10 (the tile's last relative
                                residual), points, frames_read, time_s); beyond
                                :data:`MAX_KEYED_TILES` tiles one chart ``tile/<figure>``

run.mcap::

    /scene/points          foxglove.PointCloud: the displayed points (input or ground-truth colours,
                           label = ground truth), as other runs' but thinned
    /tiled/labels          foxglove.PointCloud: the displayed points coloured by final label
                           (label field = the final class id, -1 unlabeled)
    /tiled/tiles           foxglove.SceneUpdate: one entity per tile (a cube, status colour,
                           metadata id / status / points / frames_read / iterations / time_s / node / pid)
    /diffuser_lab/tiles    JSON (no schema), one message per tile: its record (summary.json's
                           tiling.tiles entry), sequence = tile index

and the metadata ``diffuser_lab.config``, ``diffuser_lab.run``, ``diffuser_lab.tiled`` (``json``:
grid, size, halo, displayed points and stride, the tiles' records) and ``diffuser_lab.summary``.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Optional, Sequence

import numpy as np

from diffuser_lab.config import RecordMode
from diffuser_lab.data.scene import IGNORE
from diffuser_lab.runs import tiled as tiled_run
from diffuser_lab.runs.records import config_yaml

from .mcap_write import McapRecorder
from .eyes import eye_kw, overview_eye
from .recorders import MCAP_NAME, RRD_NAME
from .rerun_log import APP_TILED, RIGHT_RGB, RerunRecorder, class_ids, legend_view, log_legend, point_radius

log = logging.getLogger("diffuser_lab.recording")

MAX_DISPLAY_POINTS = 2_000_000
"""The most points a tiled run's clouds hold in run.rrd and run.mcap (every n-th point beyond)."""
STATUS_RGB = {"done": (40, 190, 70), "error": (220, 40, 40), "resumed": (150, 150, 150)}
"""A tile box's colour by its status (done, failed, kept from tiling.resume)."""
_FIGURES = ("points", "frames_read", "iterations", "time_s")
_CHARTS = ("accuracy", "iterations", "residual_log10", "points")
"""The tiles' bar charts in the layout (frames_read and time_s: in the table and the record)."""
_FIGURE_NAMES = {"accuracy": "accuracy [%]", "iterations": "iterations", "points": "points",
                 "time_s": "time [s]", "frames_read": "frames read", "residual_log10": "last residual, log10"}
"""The charts' names, short: a view's title is cut at its width (two charts a row)."""


def display_index(n: int, max_points: int = MAX_DISPLAY_POINTS) -> tuple[np.ndarray, int]:
    """(indices, stride) of the points shown: every ``stride``-th of ``n``, at most ``max_points``."""
    stride = max(1, -(-int(n) // int(max_points)))
    return np.arange(0, int(n), stride), stride


def tile_boxes(points: np.ndarray, tiles: Sequence[dict], size: float) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) centres and (T, 3) half sizes of the tiles' boxes: the x-y cell of edge ``size`` (the
    run's fitted edge, ``TiledResult.tile_m``) from the cloud's x-y minimum (:func:`~diffuser_lab.runs.tiled.tile_grid`) cut to the x-y extent
    of the points in it (the cells of the grid's last row and column reach past the cloud), z of
    the whole cloud. A tile without points keeps its whole cell."""
    origin = points[:, :2].min(0).astype(np.float64)
    zlo, zhi = float(points[:, 2].min()), float(points[:, 2].max())
    cells = np.array([[int(v) for v in t["id"].split("_")] for t in tiles], np.int64).reshape(-1, 2)
    lo = origin + cells * size
    hi = lo + size
    if len(cells):
        # each point's cell, as tile_grid; the extent of the points per cell (no loop over points)
        pc = np.floor((points[:, :2].astype(np.float64) - origin) / size).astype(np.int64)
        shape = np.maximum(pc.max(0), cells.max(0)) + 1
        flat = pc[:, 0] * shape[1] + pc[:, 1]
        pmin = np.full((shape[0] * shape[1], 2), np.inf)
        pmax = np.full((shape[0] * shape[1], 2), -np.inf)
        np.minimum.at(pmin, flat, points[:, :2])
        np.maximum.at(pmax, flat, points[:, :2])
        t_flat = cells[:, 0] * shape[1] + cells[:, 1]
        has = np.isfinite(pmin[t_flat]).all(1)
        lo[has] = np.maximum(lo[has], pmin[t_flat][has])
        hi[has] = np.minimum(hi[has], pmax[t_flat][has])
    centers = np.zeros((len(tiles), 3))
    centers[:, :2] = 0.5 * (lo + hi)
    centers[:, 2] = 0.5 * (zlo + zhi)
    half = np.zeros((len(tiles), 3))
    half[:, :2] = np.maximum(0.5 * (hi - lo), 1e-3)
    half[:, 2] = max(0.5 * (zhi - zlo), 1e-3)
    return centers, half


def _status_rgb(tiles: Sequence[dict]) -> np.ndarray:
    return np.array([STATUS_RGB.get(t.get("status"), (150, 150, 150)) for t in tiles], np.uint8).reshape(-1, 3)


def tiles_markdown(tiles: Sequence[dict]) -> str:
    """The tiles' table (run.rrd's ``tiles`` document, ``diffuser-lab-inspect``)."""
    rows = ["| # | tile | status | points | frames read | iterations | time [s] | node | pid |",
            "| ---: | --- | --- | ---: | ---: | ---: | ---: | --- | --- |"]
    for i, t in enumerate(tiles):  # loop over tiles (a few hundred at most), not points
        rows.append(f"| {i} | {t['id']} | {t['status']} | {t.get('points', 0):,} | {t.get('frames_read', 0)} | "
                    f"{t.get('iterations', 0)} | {t.get('time_s', '-')} | {t.get('node', '-')} | {t.get('pid', '-')} |")
    return "\n".join(rows)


MAX_KEYED_TILES = 32
"""Up to this many tiles, each tile's bar is an entity of its own (``tile/<figure>/<tile id>``),
named in the chart's legend; beyond, one chart per figure with the bars at the tiles' table
rows (``tile/<figure>``, x = the table's ``#``)."""


def blueprint(has_gt: bool, points: Optional[np.ndarray] = None, miou: Optional[float] = None):
    """Labels, tile outlines, errors and ground truth in tabs, each opening on the overview eye
    over ``points`` (N, 3) world m (:func:`~.eyes.overview_eye`; None: Rerun's own), beside the
    legend, the tiles' table and their bar charts; ``miou`` (percent): the scene's, in the
    accuracy chart's name."""
    import rerun as rr
    import rerun.blueprint as rrb

    eye = overview_eye(points) if points is not None else None
    grey = {"/world/tiled/labels": rr.Points3D.from_fields(colors=RIGHT_RGB).visualizer()}

    def view3d(name: str, contents: list[str], **kw):
        return rrb.Spatial3DView(name=name, origin="/world", contents=contents, **eye_kw(eye), **kw)

    # the boxes only on the tiles tab, over the cloud in grey (status colours, no class colours)
    tabs = [view3d("tiled: labels", ["/world/tiled/labels"]),
            view3d("tiles", ["/world/tiled/labels", "/world/tiled/tiles"], overrides=grey)]
    if has_gt:
        tabs += [view3d("errors", ["/world/tiled/labels", "/world/tiled/wrong"], overrides=grey),
                 view3d("ground truth", ["/world/tiled/ground_truth"])]
    names = dict(_FIGURE_NAMES)
    if miou is not None:
        names["accuracy"] = f"accuracy [%], mIoU {miou:.1f}"
    # the bars' legend (the tiles' entity paths) would cover the bars: a bar stands over its tile's
    # row # of the table, and hovering it names its entity /tile/<figure>/<tile id>
    charts = [rrb.BarChartView(name=names[k], origin=f"/tile/{k}",
                               plot_legend=rrb.PlotLegend(visible=False))
              for k in _CHARTS if k != "accuracy" or has_gt]  # (a chart without its entities stays empty)
    return rrb.Blueprint(
        rrb.Horizontal(rrb.Vertical(rrb.Tabs(*tabs, active_tab="tiled: labels"), legend_view(), row_shares=[4, 1]),
                       rrb.Vertical(rrb.TextDocumentView(name="tiles (the charts' bars in the order of #)", origin="/tiles"),
                                    # two charts a row: high enough for the numbers on their y axes
                                    *[rrb.Horizontal(*charts[i:i + 2]) for i in range(0, len(charts), 2)]),
                       column_shares=[3, 2]),
        rrb.TimePanel(state="collapsed"), collapse_panels=True)


def tile_accuracy(labels: np.ndarray, gt: np.ndarray, cell: np.ndarray, tiles: Sequence[dict]) -> np.ndarray:
    """(T,) percent of each tile's annotated points whose label is right (NaN: none annotated);
    ``cell`` (N, 2) each point's grid cell, the tiles' ids ``"<ix>_<iy>"``."""
    ids = np.array([[int(v) for v in t["id"].split("_")] for t in tiles], np.int64).reshape(-1, 2)
    shape = np.maximum(cell.max(0), ids.max(0, initial=0)) + 1
    flat = cell[:, 0].astype(np.int64) * shape[1] + cell[:, 1]
    ann = gt != IGNORE
    n = np.bincount(flat[ann], minlength=shape[0] * shape[1])
    ok = np.bincount(flat[ann & (labels == gt)], minlength=shape[0] * shape[1])
    t = ids[:, 0] * shape[1] + ids[:, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n[t] > 0, 100.0 * ok[t] / np.maximum(n[t], 1), np.nan)


def _rerun(path: Path, res: Any, idx: np.ndarray, centers: np.ndarray, half: np.ndarray, conf: Any,
           provenance: Optional[dict]) -> None:
    import rerun as rr

    scene = res.scene
    tax = scene.taxonomy
    rec = RerunRecorder(path, application_id=APP_TILED, max_image_side=conf.record.max_image_side,
                        online=True)  # online: no batch blueprint
    try:
        if provenance:
            rec.log_provenance(provenance)
        pts = scene.points[idx]
        has_gt = scene.gt_labels is not None
        miou = (res.metrics or {}).get("miou") if has_gt else None
        rec.rec.send_blueprint(blueprint(has_gt, pts, miou), make_active=True, make_default=True)
        rec.log_taxonomy(tax.names, tax.colors)
        r = point_radius(pts)
        lab = res.labels[idx]
        rec.rec.log("world/tiled/labels", rr.Points3D(pts, class_ids=class_ids(lab), radii=r), static=True)
        tiles = res.tiles
        figures = {k: np.array([float(t.get(k) or 0) for t in tiles]) for k in _FIGURES}
        res_t = np.array([float(t.get("residual") or np.nan) for t in tiles])
        if np.isfinite(res_t).any():  # tiles recorded before the residual was kept have none
            figures["residual_log10"] = np.log10(np.where(res_t > 0, res_t, np.nan))
        if has_gt:
            gt = scene.gt_labels[idx]
            rec.rec.log("world/tiled/ground_truth", rr.Points3D(pts, class_ids=class_ids(gt), radii=r), static=True)
            wrong = (gt != IGNORE) & (lab != gt)
            rec.rec.log("world/tiled/wrong", rr.Points3D(pts[wrong], colors=rec.wrong_rgb, radii=1.2 * r), static=True)
            _, _, cell = tiled_run.tile_grid(scene.points, float(conf.tiling.size))
            figures["accuracy"] = np.nan_to_num(tile_accuracy(res.labels, scene.gt_labels, cell, tiles))
        log_legend(rec.rec, tax.names, tax.colors,
                   np.unique(np.concatenate([lab, gt])) if has_gt else np.unique(lab),
                   rec.wrong_rgb if has_gt else None, confidence=False)
        rec.rec.log("world/tiled/tiles", rr.Boxes3D(centers=centers, half_sizes=half, colors=_status_rgb(tiles),
                                                    fill_mode="majorwireframe", radii=0.5 * r,
                                                    labels=[f"{t['id']} {t['status']}" for t in tiles]), static=True)
        rec.rec.log("tiles", rr.TextDocument(tiles_markdown(tiles), media_type=rr.MediaType.MARKDOWN), static=True)
        keyed = len(tiles) <= MAX_KEYED_TILES
        palette = _tile_palette(len(tiles))
        for k, v in figures.items():  # loop over the figures and (a few dozen) tiles, not points
            if keyed:
                for i, t in enumerate(tiles):
                    rec.rec.log(f"tile/{k}/{t['id']}", rr.BarChart([v[i]], abscissa=[i - 0.5], color=palette[i]),
                                static=True)
            else:
                rec.rec.log(f"tile/{k}", rr.BarChart(v, abscissa=np.arange(len(tiles)) - 0.5), static=True)
    finally:
        rec.close()


def _tile_palette(n: int) -> np.ndarray:
    """(n, 3) uint8 colours of the tiles' bars: tab10's, repeated."""
    tab10 = np.array([(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
                      (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)], np.uint8)
    return tab10[np.arange(n) % 10]


def _mcap(path: Path, res: Any, idx: np.ndarray, stride: int, centers: np.ndarray, half: np.ndarray, conf: Any,
          overrides: Sequence[str], summary: dict, provenance: Optional[dict]) -> None:
    scene = res.scene
    try:
        yaml = config_yaml(conf)
    except Exception:  # noqa: BLE001 - a library caller may pass a plain object
        yaml = repr(conf)
    rc = conf.record
    rec = McapRecorder(path, config_yaml=yaml, overrides=overrides, compression=rc.compression.value,
                       writer_thread=False, max_image_side=rc.max_image_side)
    try:
        if provenance:
            rec.log_provenance(provenance)
        shown = SimpleNamespace(name=scene.name, n_points=scene.n_points, points=scene.points[idx],
                                colors=None if scene.colors is None else scene.colors[idx],
                                gt_labels=None if scene.gt_labels is None else scene.gt_labels[idx],
                                taxonomy=scene.taxonomy)
        rec.log_scene(shown)
        meta = {"grid": list(res.grid), "size": float(conf.tiling.size), "tile_m": float(getattr(res, "tile_m", 0.0)),
                "halo": float(res.halo),
                "n_points": int(scene.n_points), "displayed_points": int(idx.size), "stride": int(stride),
                "max_display_points": MAX_DISPLAY_POINTS, "tiles": res.tiles}
        rec.log_tiled(shown.points, res.labels[idx], res.tiles, centers, half, _status_rgb(res.tiles), meta)
        rec.log_summary(summary)
    finally:
        rec.close()


def record_tiled(conf: Any, run_dir: Path | str, res: Any, overrides: Sequence[str] = (),
                 provenance: Optional[dict] = None) -> dict:
    """Write run.rrd and/or run.mcap (``conf.record.mode``) of a finished tiled run ``res``
    (:class:`~diffuser_lab.runs.tiled.TiledResult`), with what made it (``provenance``: the
    provenance, inputs and outputs blocks of its summary.json, :meth:`RerunRecorder.log_provenance`);
    returns ``{"rrd": .., "mcap": ..}`` of the files written and ``errors`` {recorder: why} where one
    failed (the run's result stands)."""
    mode = conf.record.mode
    if mode == RecordMode.off:
        return {}
    run_dir = Path(run_dir)
    idx, stride = display_index(res.scene.n_points, MAX_DISPLAY_POINTS)
    centers, half = tile_boxes(res.scene.points, res.tiles, float(getattr(res, "tile_m", 0.0) or conf.tiling.size))
    files: dict[str, Any] = {}
    errors: dict[str, str] = {}
    jobs = []
    if mode in (RecordMode.rerun, RecordMode.both):
        jobs.append(("rerun", "rrd", RRD_NAME, lambda p: _rerun(p, res, idx, centers, half, conf, provenance)))
    if mode in (RecordMode.mcap, RecordMode.both):
        summary = tiled_run.summary(res, conf)
        jobs.append(("mcap", "mcap", MCAP_NAME,
                     lambda p: _mcap(p, res, idx, stride, centers, half, conf, overrides, summary, provenance)))
    for which, key, name, write in jobs:  # loop over the (two) files
        try:
            write(run_dir / name)
            files[key] = name
        except Exception as exc:  # noqa: BLE001 - a record must never stop the run
            errors[which] = f"{type(exc).__name__}: {exc}"
            log.warning("recording %s failed: %s", which, errors[which])
    if errors:
        files["errors"] = errors
    return files


def tiled_meta(metadata: dict) -> dict | None:
    """The ``diffuser_lab.tiled`` metadata of a run.mcap (:class:`~.mcap_read.RunLog.metadata`), or None."""
    m = metadata.get("diffuser_lab.tiled")
    return json.loads(m["json"]) if m else None


__all__ = ["record_tiled", "display_index", "tile_boxes", "tiles_markdown", "tiled_meta", "MAX_DISPLAY_POINTS",
           "STATUS_RGB"]
