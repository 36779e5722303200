"""The records of a tiled run (``protocol=tiled``, docs/tiling.md): written by the driver from the
run's result once the tiles are done (:func:`record_tiled`), never by a tile or a Ray worker.

A tiled run records only its final labels and its tiles' figures: no evidence, no cameras, no
intermediate Z (a tile's diffusion is not observed; the scenes tiling is for are too large for
per-iteration clouds). The clouds are thinned for display: every n-th point, n = ceil(N /
:data:`MAX_DISPLAY_POINTS`) (:func:`display_index`), the same points in both files.

run.rrd (blueprint: labels, errors, ground truth and the tile grid in tabs beside the tiles' plots)::

    world                       AnnotationContext (taxonomy names + colours; 65535 = unlabeled)
    world/tiled/labels          Points3D, static: final labels of the displayed points
    world/tiled/ground_truth    Points3D, static: ground-truth class ids (when known)
    world/tiled/wrong           Points3D, static: displayed points whose label is wrong (when known)
    world/tiled/tiles           Boxes3D, static: one box per tile (x-y cell, z of the cloud), coloured
                                by status (green done, red failed, grey kept from tiling.resume),
                                labelled "<id> <status>"
    tiles                       TextDocument, static: the tiles' table (markdown)
    tile/points|frames_read|iterations|time_s    Scalars on the ``tile`` timeline (= tile index)

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
from .rerun_log import RerunRecorder, class_ids, point_radius

log = logging.getLogger("diffuser_lab.recording")

MAX_DISPLAY_POINTS = 2_000_000
"""The most points a tiled run's clouds hold in run.rrd and run.mcap (every n-th point beyond)."""
TIMELINE = "tile"
STATUS_RGB = {"done": (40, 190, 70), "error": (220, 40, 40), "resumed": (150, 150, 150)}
"""A tile box's colour by its status (done, failed, kept from tiling.resume)."""
_FIGURES = ("points", "frames_read", "iterations", "time_s")


def display_index(n: int, max_points: int = MAX_DISPLAY_POINTS) -> tuple[np.ndarray, int]:
    """(indices, stride) of the points shown: every ``stride``-th of ``n``, at most ``max_points``."""
    stride = max(1, -(-int(n) // int(max_points)))
    return np.arange(0, int(n), stride), stride


def tile_boxes(points: np.ndarray, tiles: Sequence[dict], size: float) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) centres and (T, 3) half sizes of the tiles' boxes: the x-y cell of ``tiling.size``
    from the cloud's x-y minimum (:func:`~diffuser_lab.runs.tiled.tile_grid`), z of the whole cloud."""
    origin = points[:, :2].min(0).astype(np.float64)
    zlo, zhi = float(points[:, 2].min()), float(points[:, 2].max())
    cells = np.array([[int(v) for v in t["id"].split("_")] for t in tiles], np.float64).reshape(-1, 2)
    centers = np.zeros((len(tiles), 3))
    centers[:, :2] = origin + (cells + 0.5) * size
    centers[:, 2] = 0.5 * (zlo + zhi)
    half = np.tile([0.5 * size, 0.5 * size, max(0.5 * (zhi - zlo), 1e-3)], (len(tiles), 1))
    return centers, half


def _status_rgb(tiles: Sequence[dict]) -> np.ndarray:
    return np.array([STATUS_RGB.get(t.get("status"), (150, 150, 150)) for t in tiles], np.uint8).reshape(-1, 3)


def tiles_markdown(tiles: Sequence[dict]) -> str:
    """The tiles' table (run.rrd's ``tiles`` document, ``diffuser-lab-inspect``)."""
    rows = ["| tile | status | points | frames read | iterations | time [s] | node | pid |",
            "| --- | --- | ---: | ---: | ---: | ---: | --- | --- |"]
    for t in tiles:  # loop over tiles (a few hundred at most), not points
        rows.append(f"| {t['id']} | {t['status']} | {t.get('points', 0):,} | {t.get('frames_read', 0)} | "
                    f"{t.get('iterations', 0)} | {t.get('time_s', '-')} | {t.get('node', '-')} | {t.get('pid', '-')} |")
    return "\n".join(rows)


def blueprint(has_gt: bool, points: Optional[np.ndarray] = None):
    """Labels, tile grid, errors and ground truth in tabs, each opening on the overview eye over
    ``points`` (N, 3) world m (:func:`~.eyes.overview_eye`; None: Rerun's own), beside the tiles'
    table and plots."""
    import rerun.blueprint as rrb

    eye = overview_eye(points) if points is not None else None

    def view3d(name: str, contents: list[str]):
        return rrb.Spatial3DView(name=name, origin="/world", contents=contents, **eye_kw(eye))

    tabs = [view3d("tiled: labels", ["/world/tiled/labels", "/world/tiled/tiles"]),
            view3d("tiles", ["/world/tiled/tiles"])]
    if has_gt:
        tabs += [view3d("errors", ["/world/tiled/wrong", "/world/tiled/tiles"]),
                 view3d("ground truth", ["/world/tiled/ground_truth"])]
    plots = [rrb.TimeSeriesView(name=f"per tile: {k}", origin="/tile", contents=[f"/tile/{k}"]) for k in _FIGURES]
    return rrb.Blueprint(
        rrb.Horizontal(rrb.Tabs(*tabs, active_tab="tiled: labels"),
                       rrb.Vertical(rrb.TextDocumentView(name="tiles", origin="/tiles"), *plots),
                       column_shares=[3, 2]),
        rrb.TimePanel(state="expanded"), collapse_panels=True)


def _rerun(path: Path, res: Any, idx: np.ndarray, centers: np.ndarray, half: np.ndarray, conf: Any) -> None:
    import rerun as rr

    scene = res.scene
    tax = scene.taxonomy
    rec = RerunRecorder(path, max_image_side=conf.record.max_image_side, online=True)  # online: no batch blueprint
    try:
        pts = scene.points[idx]
        rec.rec.send_blueprint(blueprint(scene.gt_labels is not None, pts), make_active=False, make_default=True)
        rec.log_taxonomy(tax.names, tax.colors)
        r = point_radius(pts)
        lab = res.labels[idx]
        rec.rec.log("world/tiled/labels", rr.Points3D(pts, class_ids=class_ids(lab), radii=r), static=True)
        if scene.gt_labels is not None:
            gt = scene.gt_labels[idx]
            rec.rec.log("world/tiled/ground_truth", rr.Points3D(pts, class_ids=class_ids(gt), radii=r), static=True)
            wrong = (gt != IGNORE) & (lab != gt)
            rec.rec.log("world/tiled/wrong", rr.Points3D(pts[wrong], colors=rec.wrong_rgb, radii=1.2 * r), static=True)
        tiles = res.tiles
        rec.rec.log("world/tiled/tiles", rr.Boxes3D(centers=centers, half_sizes=half, colors=_status_rgb(tiles),
                                                    labels=[f"{t['id']} {t['status']}" for t in tiles]), static=True)
        rec.rec.log("tiles", rr.TextDocument(tiles_markdown(tiles), media_type=rr.MediaType.MARKDOWN), static=True)
        for i, t in enumerate(tiles):  # loop over tiles
            rec.rec.set_time(TIMELINE, sequence=i)
            for k in _FIGURES:
                if t.get(k) is not None:
                    rec.rec.log(f"tile/{k}", rr.Scalars(float(t[k])))
    finally:
        rec.close()


def _mcap(path: Path, res: Any, idx: np.ndarray, stride: int, centers: np.ndarray, half: np.ndarray, conf: Any,
          overrides: Sequence[str], summary: dict) -> None:
    scene = res.scene
    try:
        yaml = config_yaml(conf)
    except Exception:  # noqa: BLE001 - a library caller may pass a plain object
        yaml = repr(conf)
    rc = conf.record
    rec = McapRecorder(path, config_yaml=yaml, overrides=overrides, compression=rc.compression.value,
                       writer_thread=False, max_image_side=rc.max_image_side)
    try:
        shown = SimpleNamespace(name=scene.name, n_points=scene.n_points, points=scene.points[idx],
                                colors=None if scene.colors is None else scene.colors[idx],
                                gt_labels=None if scene.gt_labels is None else scene.gt_labels[idx],
                                taxonomy=scene.taxonomy)
        rec.log_scene(shown)
        meta = {"grid": list(res.grid), "size": float(conf.tiling.size), "halo": float(res.halo),
                "n_points": int(scene.n_points), "displayed_points": int(idx.size), "stride": int(stride),
                "max_display_points": MAX_DISPLAY_POINTS, "tiles": res.tiles}
        rec.log_tiled(shown.points, res.labels[idx], res.tiles, centers, half, _status_rgb(res.tiles), meta)
        rec.log_summary(summary)
    finally:
        rec.close()


def record_tiled(conf: Any, run_dir: Path | str, res: Any, overrides: Sequence[str] = ()) -> dict:
    """Write run.rrd and/or run.mcap (``conf.record.mode``) of a finished tiled run ``res``
    (:class:`~diffuser_lab.runs.tiled.TiledResult`); returns ``{"rrd": .., "mcap": ..}`` of the
    files written and ``errors`` {recorder: why} where one failed (the run's result stands)."""
    mode = conf.record.mode
    if mode == RecordMode.off:
        return {}
    run_dir = Path(run_dir)
    idx, stride = display_index(res.scene.n_points, MAX_DISPLAY_POINTS)
    centers, half = tile_boxes(res.scene.points, res.tiles, float(conf.tiling.size))
    files: dict[str, Any] = {}
    errors: dict[str, str] = {}
    jobs = []
    if mode in (RecordMode.rerun, RecordMode.both):
        jobs.append(("rerun", "rrd", RRD_NAME, lambda p: _rerun(p, res, idx, centers, half, conf)))
    if mode in (RecordMode.mcap, RecordMode.both):
        summary = tiled_run.summary(res, conf)
        jobs.append(("mcap", "mcap", MCAP_NAME,
                     lambda p: _mcap(p, res, idx, stride, centers, half, conf, overrides, summary)))
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
