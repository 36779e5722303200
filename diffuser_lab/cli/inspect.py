"""`diffuser-lab-inspect`: read a run's records back.

    diffuser-lab-inspect RUN                      summary + per-iteration table (RUN: run folder or run.mcap)
    diffuser-lab-inspect RUN/run.rrd              what made a run.rrd: machine, versions, commit, inputs, outputs
    diffuser-lab-inspect RUN --config             also print the resolved config
    diffuser-lab-inspect RUN --at 120 --out z.npy extract Z (M, C) float32 of a recorded iteration ("last" works)
    diffuser-lab-inspect RUN --to-rrd OUT.rrd     re-log the run from its MCAP alone into a fresh .rrd
    ... --to-rrd OUT.rrd --scores chair,table     also the classes' row-normalised scores per iteration
    diffuser-lab-inspect RUN --view               open the run in the Rerun viewer (run.rrd, else
                                                  the MCAP re-logged to a temporary .rrd)
    diffuser-lab-inspect RUN --foxglove-layout L.json  write the Foxglove layout for run.mcap

A tiled run (protocol=tiled) prints its grid and a line per tile (status, points, frames read,
iterations, time, node); ``--at`` and ``--to-rrd`` refuse (it records no iterations: open its run.rrd).
An online run (protocol=online) prints a per-frame summary instead (frames, latency, final
mIoU, the frames whose Z was kept); ``--at FRAME`` takes a frame index; ``--to-rrd`` refuses
(its run.mcap keeps the map's labels only on the kept frames: open its run.rrd). A single-frame
run (protocol=single_frame) prints its targets, Table II and a line per target; ``--at STEP``
takes a step of the run's timeline (target k's iteration t is its start + t); ``--to-rrd``
re-logs every target's recorded iterations, images and Table II.

Everything is read from run.mcap (no summary section needed): a truncated file (killed run,
cut copy) gives its complete leading iterations and a warning on stderr, exit code 0. Every kind
ends with what made the run (``made by``, ``inputs``, ``outputs``: the records' provenance, the same
blocks as summary.json's); a run.rrd given alone prints those lines from its recording property.
Exit codes: 0 ok, 1 unreadable file, 2 bad arguments (missing file, iteration not recorded).
"""
from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from diffuser_lab.backends import provenance as provenance_mod
from diffuser_lab.method.diffusion import labels_from_scores
from diffuser_lab.recording import schema
from diffuser_lab.recording.features import feature_view_of
from diffuser_lab.recording.mcap_encode import (
    TOPIC_CALIBRATION,
    TOPIC_CAMERA_LABELS,
    TOPIC_FEATURE_VIEW,
    TOPIC_FEATURES,
    TOPIC_METRICS,
    TOPIC_ONLINE_FRAME,
    TOPIC_RUN,
    TOPIC_SCENE,
    TOPIC_TARGET,
    TOPIC_Z,
    camera_index,
    decode_label_png,
    decode_z,
    z_precision_text,
)
from diffuser_lab.recording.mcap_read import RunLog, iter_run, metrics_dict, read_run, relog_scene, work_points
from diffuser_lab.recording.mcap_write import FOXGLOVE_LAYOUT, online_foxglove_layout
from diffuser_lab.recording.rerun_log import RerunRecorder, read_provenance
from diffuser_lab.recording.schedule import describe
from diffuser_lab.recording.single_frame import replay as replay_single_frame
from diffuser_lab.recording.steps import StepTracker
from diffuser_lab.recording.tiled import tiled_meta

PROG = "diffuser-lab-inspect"


class UsageError(Exception):
    pass


def _mcap_path(run: Path) -> Path:
    if run.is_dir():
        p = run / "run.mcap"
        if not p.is_file():
            raise UsageError(f"{run}: no run.mcap in this folder (was the run recorded with record=mcap|both?)")
        return p
    if not run.is_file():
        raise UsageError(f"{run}: no such file or folder")
    return run


def _size(path: Path) -> str:
    return _size_of(path.stat().st_size)


def _f(x: Optional[float], spec: str = ".1f") -> str:
    return "-" if x is None else format(x, spec)


def _iters(its: Sequence[int]) -> str:
    its = list(its)
    if len(its) <= 8:
        return ", ".join(map(str, its))
    return ", ".join(map(str, its[:4])) + ", ..., " + ", ".join(map(str, its[-2:]))


def summary_text(log: Any) -> str:
    """The run at a glance (see the README for an example)."""
    info, run, s = log.info, log.run, log.summary
    lines = [f"run.mcap: {log.path} ({_size(log.path)}, {'complete' if log.complete else 'TRUNCATED'})"]
    scene = (info.scene if info is not None else run.get("scene")) or "?"
    method = info.method if info is not None else (s or {}).get("method", "?")
    names = log.class_names
    n_pts = int(info.n_points) if info is not None else int(run.get("n_points", 0))
    work = f" ({int(info.n_work_points):,} diffused)" if info is not None else ""
    frames = f" | {len(info.cameras)} frames" if info is not None else ""
    tax = info.taxonomy if info is not None else run.get("taxonomy", "")
    lines.append(f"scene     {scene} | method {method} | {n_pts:,} points{work}{frames} | "
                 f"{len(names)} classes ({tax})")
    lines.append(f"classes   {', '.join(names)}")
    lines.append(f"overrides {' '.join(log.overrides) if log.overrides else '(none)'}")
    its = log.z_iterations
    if not its:
        lines.append("recorded  0 iterations (no diffusion recorded: static records only)")
    elif info is not None:
        dts = sorted(set(log.z_dtype.values()), key=lambda d: d == "float32")
        zinfo = f"Z {' / last '.join(dts) if len(dts) > 1 else (dts or ['float32'])[0]}, {int(info.n_work_points):,} x {len(names)}"
        lines.append(f"recorded  {len(its)} iterations: {_iters(its)} ({describe(int(info.interval))}, "
                     f"first and last; {zinfo})")
    else:
        lines.append(f"recorded  {len(its)} iterations: {_iters(its)}")
    if s is not None:
        d = s.get("diffusion") or {}
        m = s.get("metrics") or {}
        b = (s.get("baseline") or {}).get("bayesian") or {}
        if d.get("iterations"):
            how = "converged" if d.get("converged") else "max reached"
            res = f"{d['iterations']} iterations ({how}, relative residual {_f(d.get('residual'), '.1e')})"
        else:
            res = "no diffusion (static records only)"
        lines.append(f"result    {res} | mIoU {_f(m.get('miou'))}  acc {_f(m.get('accuracy'))}  "
                     f"cover {_f(m.get('coverage'))} | bayesian mIoU {_f(b.get('miou'))}")
    else:
        lines.append("result    (no summary: the run did not finish)")
    return "\n".join(lines)


def _hash(h: Optional[str]) -> str:
    return (h or "?")[:12]


def made_by_text(block: Optional[dict]) -> str:
    """What made a run, three lines (``made by``, ``inputs``, ``outputs``) from its records'
    provenance block (:meth:`~diffuser_lab.hooks.RunHooks.on_provenance`); hashes shortened to 12
    hex digits (summary.json and ``inputs.tsv`` have them whole)."""
    if not block:
        return "made by   (not recorded: a run from before its records held their provenance)"
    inp, out = block.get("inputs") or {}, block.get("outputs")
    cfg = f" | config sha256 {_hash(inp.get('config_sha256'))}" if inp.get("config_sha256") else ""
    lines = [f"made by   {provenance_mod.summary_line(block.get('provenance'))}{cfg}"]
    parts = []
    gen = inp.get("generator")
    if gen:
        parts.append(f"generator {gen.get('source')} seed {gen.get('seed')}")
    for role, m in sorted((inp.get("manifests") or {}).items()):
        parts.append(f"{role} {m['count']:,} files ({_size_of(m['bytes'])}, manifest {_hash(m['sha256'])})")
    for f in inp.get("files") or []:
        parts.append(f"{f['role']} {f['path']} ({_size_of(f['size'])}, {_hash(f['sha256'])})")
    if "sha256" in inp:
        lines.append(f"inputs    {_hash(inp['sha256'])}: " + ("; ".join(parts) or "no files"))
    else:
        lines.append("inputs    (not yet recorded: the run did not finish)")
    if out is not None:
        files = [f"{name} {_hash(v['sha256'])}" for name, v in sorted((out.get("files") or {}).items())]
        lines.append("outputs   " + ", ".join(files + [f"figures {_hash(out.get('figures_sha256'))}"]))
    return "\n".join(lines)


def _size_of(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return ""


def rrd_text(path: Path) -> str:
    """A run.rrd alone: its size and what made it (its recording property)."""
    return f"run.rrd: {path} ({_size(path)})\n" + made_by_text(read_provenance(path))


def online_text(log: Any) -> str:
    """An online run at a glance: frames, latency, final mIoU, the Z states kept."""
    meta, s, fr = log.online or {}, log.summary, log.frames
    run = log.run
    lines = [f"run.mcap: {log.path} ({_size(log.path)}, {'complete' if log.complete else 'TRUNCATED'})"]
    n_seq = int(meta.get("n_frames", 0) or 0)
    pts = fr[-1]["points"] if fr else 0
    lines.append(f"scene     {run.get('scene', '?')} | online, {meta.get('map', '?')} map: {pts:,} points | "
                 f"{len(fr)} of {n_seq} frames recorded | {len(log.class_names)} classes ({run.get('taxonomy', '')})")
    lines.append(f"overrides {' '.join(log.overrides) if log.overrides else '(none)'}")
    if fr:
        lat = np.array([f["latency_ms"] for f in fr], float)
        lines.append(f"latency   median {np.median(lat):.1f} ms, p95 {np.percentile(lat, 95):.1f} ms, "
                     f"max {lat.max():.1f} ms per frame (the update alone)")

    its = log.z_iterations
    dts = sorted(set(log.z_dtype.values()), key=lambda d: d == "float32")
    interval = meta.get("interval", "null")
    how = describe(None if interval in ("null", "", None) else int(interval)).replace("iteration", "frame")
    lines.append(f"states    {len(its)} kept: frames {_iters(its)} ({how} over the frames taken, first and last; "
                 f"Z {' / last '.join(dts) if dts else '-'})")
    last = fr[-1] if fr else {}
    if s is not None:
        m, b = s.get("metrics") or {}, (s.get("baseline") or {}).get("bayesian") or {}
        bd = (s.get("batch") or {}).get("diffuser") or {}
        lines.append(f"result    final mIoU {_f(m.get('miou'))} (online Bayesian {_f(b.get('miou'))}, batch Diffuser "
                     f"{_f(bd.get('miou'))}) | {s.get('n_frames_skipped', 0)} frames skipped")
    else:
        lines.append(f"result    (no summary: the run did not finish) | mIoU so far at frame {last.get('index', '-')}: "
                     f"{_f(last.get('diffuser_miou'))} (Bayesian {_f(last.get('bayesian_miou'))})")
    return "\n".join(lines)


def online_table_text(frames: Sequence[dict], kept: Sequence[int]) -> str:
    """One line per frame whose Z was kept (and the last frame recorded)."""
    head = (f"{'frame':>6s}  {'latency':>8s}  {'points':>9s}  {'new':>7s}  {'changed':>8s}  {'steps':>5s}  "
            f"{'mIoU':>6s}  {'bayes':>6s}  {'Z':>7s}")
    keep = set(kept)
    rows = [head]
    for i, f in enumerate(frames):
        if f["index"] not in keep and i != len(frames) - 1:
            continue
        rows.append(f"{f['index']:6d}  {f['latency_ms']:8.1f}  {f['points']:9,d}  {f['new_points']:7,d}  "
                    f"{f['changed']:8,d}  {f['steps']:5d}  {_f(f['diffuser_miou']):>6s}  {_f(f['bayesian_miou']):>6s}  "
                    f"{f['state'] or '-':>7s}")
    return "\n".join(rows)


def is_online_mcap(mcap_path: Path | str) -> bool:
    """Whether a run.mcap is an online run's (its first records only)."""
    log = RunLog(path=Path(mcap_path))
    for topic, _ in iter_run(mcap_path, log):
        if topic in ("metadata:diffuser_lab.online", TOPIC_ONLINE_FRAME):
            return True
        if topic in (TOPIC_RUN, TOPIC_Z):
            return False
    return False


def is_tiled_mcap(mcap_path: Path | str) -> bool:
    """Whether a run.mcap is a tiled run's (its ``diffuser_lab.tiled`` metadata, before any iteration)."""
    log = RunLog(path=Path(mcap_path))
    for topic, _ in iter_run(mcap_path, log):
        if topic == "metadata:diffuser_lab.tiled":
            return True
        if topic in (TOPIC_RUN, TOPIC_Z, TOPIC_ONLINE_FRAME):
            return False
    return False


def is_single_frame_mcap(mcap_path: Path | str) -> bool:
    """Whether a run.mcap is a single-frame run's (its ``diffuser_lab.single_frame`` metadata or a
    target, before any iteration)."""
    log = RunLog(path=Path(mcap_path))
    for topic, _ in iter_run(mcap_path, log):
        if topic in ("metadata:diffuser_lab.single_frame", TOPIC_TARGET):
            return True
        if topic in (TOPIC_RUN, TOPIC_Z, TOPIC_ONLINE_FRAME, "metadata:diffuser_lab.tiled"):
            return False
    return False


def single_frame_text(log: Any) -> str:
    """A single-frame run at a glance: the targets, what was recorded, the result."""
    meta, run, s, tg = log.single_frame or {}, log.run, log.summary, log.targets
    lines = [f"run.mcap: {log.path} ({_size(log.path)}, {'complete' if log.complete else 'TRUNCATED'})"]
    method = f"{tg[0]['method']} ({tg[0]['views']} views)" if tg else "diffuser"
    pts = np.mean([t["n_points"] for t in tg]) if tg else 0
    lines.append(f"scene     {run.get('scene', '?')} | single-frame protocol (Table II): {len(tg)} target frames of "
                 f"{meta.get('n_frames', '?')}, window {meta.get('window', '?')}, {pts:,.0f} points a target | "
                 f"{len(log.class_names)} classes ({run.get('taxonomy', '')})")
    lines.append(f"overrides {' '.join(log.overrides) if log.overrides else '(none)'}")
    dts = sorted(set(log.z_dtype.values()), key=lambda d: d == "float32")
    its = log.z_iterations
    interval = meta.get("interval")
    lines.append(f"recorded  the {method} diffusion of every target: {len(its)} Z states ({describe(interval)} of "
                 f"each, first and last; Z {' / last '.join(dts) if dts else '-'}), on the run's steps "
                 f"{_iters(its)} (target k's iteration t = its start + t)")
    if s is not None:
        pick = {(r["method"], r["views"]): r for r in s.get("rows") or []}
        m = pick.get(("diffuser", meta.get("window"))) or {}
        b = pick.get(("bayesian", meta.get("window"))) or {}
        lines.append(f"result    2D mIoU {_f(m.get('miou'))}  acc {_f(m.get('accuracy'))} (Diffuser, "
                     f"{meta.get('window')} views) | Bayesian {_f(b.get('miou'))}")
    else:
        lines.append("result    (no summary: the run did not finish)")
    return "\n".join(lines)


def single_frame_table_text(log: Any) -> str:
    """Table II (the summary's rows, else the last target's rows so far) and a line per target."""
    rows = (log.summary or {}).get("rows") or next((t["rows"] for t in reversed(log.targets) if "rows" in t), [])
    out = [f"{'method':12s}{'views':>6s}{'2D mIoU':>9s}{'acc':>7s}{'frame mean':>12s}"]
    for r in rows:
        out.append(f"{r['method']:12s}{r['views']:>6d}{_f(r.get('miou')):>9s}{_f(r.get('accuracy')):>7s}"
                   f"{_f(r.get('mean_frame_miou')):>12s}")
    out.append(f"{'target':>6s}  {'name':<16s}  {'points':>8s}  {'iters':>5s}  {'steps':>11s}  {'frame mIoU':>10s}")
    for t in log.targets:
        mine = next((r for r in t.get("rows", []) if r["method"] == t["method"] and r["views"] == t["views"]), {})
        steps = f"{t['start']}-{t['end']}" if "end" in t else f"{t['start']}-"
        out.append(f"{t['index']:6d}  {t['name'][:16]:<16s}  {t['n_points']:8,d}  {t.get('iterations', 0):5d}  "
                   f"{steps:>11s}  {_f(mine.get('frame_miou')):>10s}")
    return "\n".join(out)


def tiled_text(log: Any, meta: dict) -> str:
    """A tiled run at a glance: the grid, the points shown, the result."""
    run, s = log.run, log.summary
    tiles = meta.get("tiles", [])
    status = {k: sum(t.get("status") == k for t in tiles) for k in ("done", "resumed", "error")}
    lines = [f"run.mcap: {log.path} ({_size(log.path)}, {'complete' if log.complete else 'TRUNCATED'})",
             f"scene     {run.get('scene', '?')} | tiled {meta['grid'][0]}x{meta['grid'][1]} grid of "
             f"{meta['size']:g} m (halo {meta['halo']:g} m), {len(tiles)} tiles: {status['done']} done, "
             f"{status['resumed']} kept from resume, {status['error']} failed | {len(log.class_names)} classes "
             f"({run.get('taxonomy', '')})",
             f"overrides {' '.join(log.overrides) if log.overrides else '(none)'}",
             f"recorded  final labels of {meta['displayed_points']:,} of {meta['n_points']:,} points ("
             + ("all" if meta["stride"] == 1 else f"every {meta['stride']}-th") + "), the tiles; no iterations "
             "(a tiled run records no intermediate Z)"]
    if s is not None:
        m, b = s.get("metrics") or {}, (s.get("baseline") or {}).get("bayesian") or {}
        lines.append(f"result    mIoU {_f(m.get('miou'))}  acc {_f(m.get('accuracy'))}  cover "
                     f"{_f(m.get('coverage'))} | bayesian mIoU {_f(b.get('miou'))} | {s.get('n_unlabeled', 0):,} "
                     f"points unlabeled")
    else:
        lines.append("result    (no summary)")
    return "\n".join(lines)


def tiles_table_text(tiles: Sequence[dict]) -> str:
    """One line per tile."""
    rows = [f"{'tile':>8s}  {'status':>8s}  {'points':>9s}  {'frames':>6s}  {'iters':>5s}  {'time[s]':>7s}  node:pid"]
    for t in tiles:
        rows.append(f"{t['id']:>8s}  {t.get('status', '?'):>8s}  {t.get('points', 0):9,d}  {t.get('frames_read', 0):6d}  "
                    f"{t.get('iterations', 0):5d}  {_f(t.get('time_s'), '.2f'):>7s}  {t.get('node', '-')}:{t.get('pid', '-')}"
                    + (f"  {t['error']}" if t.get("error") else ""))
    return "\n".join(rows)


def table_text(metrics: Sequence[dict]) -> str:
    """One line per recorded iteration."""
    head = f"{'iter':>6s}  {'residual':>9s}  {'changed':>8s}  {'mIoU':>6s}  {'acc':>6s}  {'cover':>6s}  {'conf':>5s}"
    rows = [head]
    for m in metrics:
        rows.append(f"{m['iteration']:6d}  {m['residual']:9.2e}  {m['n_changed']:8,d}  {_f(m['miou']):>6s}  "
                    f"{_f(m['accuracy']):>6s}  {m['coverage']:6.1f}  {m['mean_confidence']:5.3f}")
    return "\n".join(rows)


def run_classes(mcap_path: Path | str) -> tuple[list[str], str]:
    """(class names, taxonomy name) of a run.mcap, read from its first records only."""
    import json

    log = RunLog(path=Path(mcap_path))
    for topic, data in iter_run(mcap_path, log):
        if topic == "metadata:diffuser_lab.run" and data.get("class_names"):
            return list(json.loads(data["class_names"])), str(data.get("taxonomy", ""))
        if topic == TOPIC_RUN:
            info = schema.RunInfo.FromString(data)
            return list(info.class_names), str(info.taxonomy)
    return [], ""


def score_classes(mcap_path: Path | str, wanted: Sequence[str]) -> list[tuple[str, int]]:
    """(name, class index) of ``wanted`` in the run's taxonomy; UsageError naming a bad one."""
    names, tax = run_classes(mcap_path)
    index = {n: i for i, n in enumerate(names)}
    for w in wanted:
        if w not in index:
            raise UsageError(f"--scores: no class {w!r} in this run's taxonomy {tax or '?'}; its classes: "
                             f"{', '.join(names) if names else '(none recorded)'}")
    return [(w, index[w]) for w in dict.fromkeys(wanted)]


def mcap_to_rrd(mcap_path: Path | str, rrd_path: Path | str, *, max_image_side: int = 320,
                scores: Sequence[str] = ()) -> Any:
    """Re-log a run into a fresh .rrd from its run.mcap alone (same entities, blueprint and
    per-iteration class ids as the live run.rrd, the cameras with their label images and what made
    the run; not their depth or colour images, which run.mcap does not hold). ``scores``: class names whose
    row-normalised scores Z_ic / sum_c Z_ic are logged too (``world/scores/<class>`` per recorded
    iteration, a blueprint tab each; a name not in the taxonomy raises :class:`UsageError` before
    anything is written). Returns the :class:`~diffuser_lab.recording.mcap_read.RunLog` (truncation)."""
    from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

    layers = score_classes(mcap_path, scores) if scores else []
    log = RunLog(path=Path(mcap_path))
    rec = RerunRecorder(Path(rrd_path), max_image_side=max_image_side, score_classes=layers)
    tracker = None
    points = gt = None
    residual: dict[int, float] = {}
    calib: dict[int, Any] = {}  # camera index -> CameraCalibration (of the stored image)
    label_images: dict[int, np.ndarray] = {}  # camera index -> (h, w) class ids
    colors = np.zeros((0, 3), np.uint8)
    try:
        for topic, data in iter_run(mcap_path, log):
            if topic == TOPIC_SCENE:
                points, _, colors, gt = relog_scene(rec, data, log.run, mcap_path)
            elif topic == TOPIC_RUN:
                info = schema.RunInfo.FromString(data)
                log.info = info
                for i, cam in enumerate(info.cameras):
                    K, w, h = np.reshape(cam.K, (3, 3)), cam.width, cam.height
                    if i in calib:  # the pinhole of the stored label image, as the live run.rrd's
                        K, w, h = np.reshape(calib[i].K, (3, 3)), calib[i].width, calib[i].height
                    rec.log_camera(i, cam.name, K, np.reshape(cam.T_cw, (4, 4)), w, h,
                                   labels=label_images.get(i))
                m = int(info.n_work_points)
                work = work_points(info, points)
                seen = np.frombuffer(info.seen, np.uint8).astype(bool)
                bayes = np.frombuffer(info.bayesian_labels, "<i2")
                to_work = np.frombuffer(info.original_to_work, "<i4") if info.original_to_work else None
                rec.log_evidence(work, seen, bayes)
                tracker = StepTracker(m, list(info.class_names), gt, to_work)
            elif topic == TOPIC_CALIBRATION:
                cal = CameraCalibration.FromString(data)
                calib[camera_index(cal.frame_id)] = cal
            elif topic == TOPIC_CAMERA_LABELS:
                img = CompressedImage.FromString(data)
                label_images[camera_index(img.frame_id)] = decode_label_png(img.data, colors)
            elif topic == TOPIC_METRICS:
                d = metrics_dict(data)
                log.metrics.append(d)
                residual[d["iteration"]] = d["residual"]
            elif topic == TOPIC_FEATURE_VIEW:  # a features run: its projection, then its colours
                rec.log_feature_view(feature_view_of(schema.FeatureView.FromString(data)))
            elif topic == TOPIC_FEATURES:
                fc = schema.FeatureColors.FromString(data)
                rec.log_features(int(fc.iteration), np.frombuffer(fc.rgb, np.uint8).reshape(-1, 3),
                                 np.frombuffer(fc.similarity, np.uint8))
            elif topic == TOPIC_Z and tracker is not None:
                msg = schema.ZState.FromString(data)
                it = int(msg.iteration)
                if log.z_iterations and log.z_iterations[-1] == it:
                    continue  # the last state again, exact (the run converged on a recorded iteration)
                log.z_iterations.append(it)
                labels = np.frombuffer(msg.labels, "<i2") if msg.labels else None  # the run's own argmax
                step = tracker.step(it, decode_z(msg), residual.get(it, float("nan")), labels=labels)
                rec.log_step(step, points)
                rec.log_scores(step)
        if log.provenance:  # what made the run, as the live run.rrd has it
            rec.log_provenance(log.provenance)
    finally:
        rec.close()
    return log


def _viewer() -> list[str]:
    exe = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    return [exe]


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog=PROG, description="Summary, per-iteration table, Z states and replay of a "
                                 "diffuser-lab run, read from its run.mcap.")
    ap.add_argument("run", help="run folder (logs/runs/...) or a run.mcap file")
    ap.add_argument("--at", metavar="ITER", help="a recorded iteration (or 'last') whose Z to extract")
    ap.add_argument("--out", metavar="Z.npy", help="with --at: write Z there, (M, C) float32")
    ap.add_argument("--to-rrd", metavar="OUT.rrd", help="re-log the run from its MCAP alone into OUT.rrd")
    ap.add_argument("--scores", metavar="CLASS,..", help="with --to-rrd/--view: also re-log these classes' "
                    "row-normalised scores Z_ic / sum_c Z_ic per recorded iteration (a tab each)")
    ap.add_argument("--view", action="store_true", help="open the run in the Rerun viewer")
    ap.add_argument("--foxglove-layout", metavar="OUT.json",
                    help="write a Foxglove layout for run.mcap (labelled cloud, cameras, label images, metrics)")
    ap.add_argument("--config", action="store_true", help="print the resolved config too")
    ap.add_argument("--no-table", action="store_true", help="leave out the per-iteration table")
    args = ap.parse_args(argv)
    try:
        return _main(args)
    except UsageError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 - one line, not a traceback, naming what was read
        msg = " ".join(str(exc).split())
        where = "" if args.run in msg else f"{args.run}: "
        print(f"{PROG}: error: {where}{type(exc).__name__}: {msg}", file=sys.stderr)
        return 1


def _warn_truncated(log: Any) -> None:
    if log.truncated:
        print(f"{PROG}: warning: {log.path} is truncated ({log.error}); read {len(log.z_iterations)} complete "
              f"{'frame state' if log.online is not None else 'iteration'}(s)"
              f"{', last ' + str(log.z_iterations[-1]) if log.z_iterations else ''}", file=sys.stderr)


def _main(args: argparse.Namespace) -> int:
    run = Path(args.run)
    if args.out and args.at is None:
        raise UsageError("--out needs --at ITER")
    scores = [c.strip() for c in (args.scores or "").split(",") if c.strip()]
    if args.scores is not None and not (args.to_rrd or args.view):
        raise UsageError("--scores needs --to-rrd OUT.rrd or --view")
    if args.scores is not None and not scores:
        raise UsageError("--scores: give class names, e.g. --scores chair,table")
    if args.view and not scores and ((run / "run.rrd").is_file() or run.suffix == ".rrd"):
        rrd = run if run.suffix == ".rrd" else run / "run.rrd"
        print(f"opening {rrd} in the Rerun viewer")
        return subprocess.call(_viewer() + [str(rrd)])
    if run.suffix == ".rrd" and run.is_file() and not (args.at or args.to_rrd or args.view or args.foxglove_layout):
        print(rrd_text(run))
        return 0
    mcap = _mcap_path(run)
    if args.foxglove_layout:
        if is_online_mcap(mcap):  # its topics and plot fields
            Path(args.foxglove_layout).write_text(online_foxglove_layout())
        else:
            shutil.copyfile(FOXGLOVE_LAYOUT, args.foxglove_layout)
        print(f"wrote {args.foxglove_layout}: open {mcap} in Foxglove, then Layouts > Import from file")
        return 0
    if (args.to_rrd or args.view or args.at is not None) and is_tiled_mcap(mcap):
        raise UsageError(f"{mcap}: a tiled run records its final labels and tiles, no iterations; open its "
                         f"run.rrd (diffuser-lab-inspect RUN --view)")
    single = is_single_frame_mcap(mcap)
    if (args.to_rrd or args.view) and single:
        if scores:
            raise UsageError("--scores: a single-frame run's record has no score layers")
        out = Path(args.to_rrd) if args.to_rrd else Path(tempfile.mkdtemp(prefix="diffuser-lab-")) / "replay.rrd"
        log = replay_single_frame(mcap, out)
        _warn_truncated(log)
        print(f"wrote {out} ({_size(out)}): {len(log.targets)} target frames, {len(log.z_iterations)} recorded "
              f"iterations re-logged from {mcap}")
        if args.view:
            return subprocess.call(_viewer() + [str(out)])
        return 0
    if (args.to_rrd or args.view) and not single and is_online_mcap(mcap):
        raise UsageError(f"{mcap}: an online run's run.mcap keeps the map's labels only on the frames whose Z it "
                         f"kept, so it is not re-logged; open the run's run.rrd (diffuser-lab-inspect RUN --view)")
    if args.to_rrd or args.view:
        out = Path(args.to_rrd) if args.to_rrd else Path(tempfile.mkdtemp(prefix="diffuser-lab-")) / "replay.rrd"
        log = mcap_to_rrd(mcap, out, scores=scores)
        _warn_truncated(log)
        extra = f", scores of {', '.join(scores)}" if scores else ""
        print(f"wrote {out} ({_size(out)}): {len(log.z_iterations)} iterations re-logged from {mcap}{extra}")
        if args.view:
            return subprocess.call(_viewer() + [str(out)])
        return 0
    want = None
    if args.at is not None:
        want = "last" if args.at == "last" else [_int(args.at)]
    log = read_run(mcap, z=want)
    if log.info is None and not log.metadata and not log.truncated:
        raise UsageError(f"{mcap}: not a diffuser-lab run.mcap (no run records)")
    _warn_truncated(log)
    what = "frame" if log.online is not None else "step" if single else "iteration"
    if args.at is not None:
        if not log.z_iterations:
            raise UsageError(f"{mcap}: no Z state recorded (method without diffusion, or cut before the first)")
        it = log.z_iterations[-1] if args.at == "last" else _int(args.at)
        if it not in log.z:
            raise UsageError(f"{what} {it} was not recorded; recorded: {_iters(log.z_iterations)}")
        Z = log.z[it]
        precision = z_precision_text(log.z_dtype.get(it, "float32"))
        if args.out:
            np.save(args.out, Z)
            print(f"wrote {args.out}: Z at {what} {it}, {Z.shape[0]:,} x {Z.shape[1]} float32; "
                  f"stored as {precision}")
        else:
            lab = labels_from_scores(Z)
            print(f"Z at {what} {it}: {Z.shape[0]:,} x {Z.shape[1]} float32, max {Z.max():.3e}, "
                  f"{int((lab >= 0).sum()):,} labelled points; stored as {precision} (use --out z.npy to save it)")
        return 0
    meta = tiled_meta(log.metadata)
    if meta is not None:
        print(tiled_text(log, meta) + "\n" + made_by_text(log.provenance))
        if args.config:
            print("config:\n" + log.config_yaml)
        if not args.no_table:
            print(tiles_table_text(meta.get("tiles", [])))
        return 0
    if single:
        print(single_frame_text(log) + "\n" + made_by_text(log.provenance))
        if args.config:
            print("config:\n" + log.config_yaml)
        if not args.no_table:
            print(single_frame_table_text(log))
        return 0
    if log.online is not None:
        print(online_text(log) + "\n" + made_by_text(log.provenance))
        if args.config:
            print("config:\n" + log.config_yaml)
        if not args.no_table and log.frames:
            print(online_table_text(log.frames, log.z_iterations))
        return 0
    print(summary_text(log) + "\n" + made_by_text(log.provenance))
    if args.config:
        print("config:\n" + log.config_yaml)
    if not args.no_table and log.metrics:
        print(table_text(log.metrics))
    return 0


def _int(s: str) -> int:
    try:
        return int(s)
    except ValueError:
        raise UsageError(f"--at {s}: expected an iteration number or 'last'") from None


if __name__ == "__main__":
    sys.exit(main())
