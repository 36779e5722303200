"""The protocols a run follows: the registry :data:`PROTOCOLS`, one entry each, named by ``protocol.name``.

An entry knows how to run (a library call: ``run(cfg, scene=None, hooks=None)``), what it writes
into a run folder beside summary.json and what summary.json says (``finish``), and the table the
command line prints (``table``). Built in: ``global_3d`` (:func:`diffuser_lab.runs.pipeline.run`,
paper Table I), ``single_frame`` (:func:`diffuser_lab.runs.single_frame.single_frame`, Table II) and
``online`` (:func:`diffuser_lab.runs.online.online`) and ``tiled`` (:func:`diffuser_lab.runs.tiled.tiled`:
the global pipeline per x-y tile, docs/tiling.md).

Adding a protocol is one function that runs it (resolving the config it is handed), one
``conf/protocol/<name>.yaml`` with ``name: <name>`` and one registry line (an entry below, or
:func:`register`). The command line (:mod:`diffuser_lab.cli.main`) asks this registry and nothing else.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from diffuser_lab.config import Config
from diffuser_lab.data.scene import Scene
from diffuser_lab.hooks import RunHooks
from diffuser_lab.registry import Registry

from . import online as online_mod
from . import report, single_frame, tiled
from .pipeline import run
from .records import write_labels, write_scores, write_scoring

__all__ = ["Protocol", "PROTOCOLS", "register", "get"]


@dataclass(frozen=True)
class Protocol:
    """One protocol.

    Attributes:
        name: the ``protocol.name`` value that selects it.
        description: a few words (docs/config.md's choices).
        run: ``(cfg, *, scene=None, hooks=None) -> result``: the library call (the scene: the
            configured source when None; ``hooks`` watch it; a protocol that takes none ignores them).
        finish: ``(result, cfg, run_dir, summary, records) -> dict``: write the result's files into
            ``run_dir`` and finish ``summary`` (a :class:`~diffuser_lab.runs.report.SummaryFile`) with
            it and ``records`` (the recorders' files); returns summary.json's content.
        table: ``(result, run_dir) -> str``: what the command line prints.
        records: whether the command line makes recorders (run.rrd, run.mcap) for it.
        run_dir: whether ``run`` takes the run folder (``run_dir=``: a run that writes files as it goes).
        result_records: the command line writes its records (run.rrd, run.mcap) from the result
            once the run is done (:func:`diffuser_lab.recording.record_result`), not through hooks.
    """

    name: str
    description: str
    run: Callable[..., Any]
    finish: Callable[[Any, Config, Path, report.SummaryFile, dict], dict]
    table: Callable[[Any, Path], str]
    records: bool = True
    run_dir: bool = False
    result_records: bool = False


def _finish_global(result, cfg: Config, run_dir: Path, summary: report.SummaryFile, records: dict) -> dict:
    t = time.perf_counter()
    files = write_labels(run_dir, result.scene.points, result.labels, result.scene.taxonomy, ply=cfg.output.labels_ply,
                         clouds=cfg.output.clouds, confidence=result.confidence)
    files.update(write_scoring(run_dir, result.scene, result.bayesian_labels))
    files.update(result.space.write(run_dir, result.rows))  # a features run's features (classes: none)
    if cfg.output.scores:
        files.update(write_scores(run_dir, result))
    result.timings_s["write"] = time.perf_counter() - t
    return summary.result(result, cfg, records=records, files=files)


def _run_single_frame(cfg: Config, *, scene: Optional[Scene] = None, hooks: Optional[RunHooks] = None):
    return single_frame.single_frame(cfg, scene, hooks=hooks)


def _finish_single_frame(result, cfg: Config, run_dir: Path, summary: report.SummaryFile, records: dict) -> dict:
    summary.single_frame(result)
    summary.update(records=records)
    return summary.data


def _finish_online(result, cfg: Config, run_dir: Path, summary: report.SummaryFile, records: dict) -> dict:
    """labels.npy holds the final map's labels (given map: of the scene's points; growing: map
    order), map.npy a growing map's points."""
    pts = result.scene.points if result.scene_labels is not None else result.points
    labels = result.scene_labels if result.scene_labels is not None else result.labels
    files = write_labels(run_dir, pts, labels, result.scene.taxonomy, ply=cfg.output.labels_ply,
                         clouds=cfg.output.clouds)
    if result.mode == "growing":
        np.save(run_dir / "map.npy", result.points)
        files["map"] = "map.npy"
    summary.data.update(online_mod.summary(result))
    kept = report.keyframes_kept(result.scene)
    if kept:
        summary.data["keyframes"] = kept
    follow = report.followed(result.scene)
    if follow:
        summary.data["follow"] = follow
    summary.update(records=records, files=files, status="ok")
    return summary.data


def _finish_tiled(result, cfg: Config, run_dir: Path, summary: report.SummaryFile, records: dict) -> dict:
    """labels.npy etc. of the whole scene; summary.json's ``tiling.tiles`` has every tile's record;
    status ``incomplete`` when a tile failed (its points unlabeled)."""
    t = time.perf_counter()
    files = write_labels(run_dir, result.scene.points, result.labels, result.scene.taxonomy, ply=cfg.output.labels_ply,
                         clouds=cfg.output.clouds)
    files.update(write_scoring(run_dir, result.scene, result.bayesian_labels))
    files.update(result.files)
    result.timings_s["write"] = time.perf_counter() - t
    summary.data.update(tiled.summary(result, cfg))
    kept = report.keyframes_kept(result.scene)
    if kept:
        summary.data["keyframes"] = kept
    summary.update(records=records, files=files, status="incomplete" if result.failed else "ok")
    return summary.data


PROTOCOLS: Registry = Registry("protocol.name", "protocol", [
    Protocol("global_3d", "label the scene's points, score 3D mIoU (paper Table I)", run, _finish_global,
             lambda result, run_dir: report.table(result, run_dir)),
    Protocol("single_frame", "label each frame's back-projected depth, score 2D mIoU (Table II)", _run_single_frame,
             _finish_single_frame, lambda result, run_dir: single_frame.table(result) + f"\nrun folder: {run_dir}"),
    Protocol("online", "frames one at a time in sequence order; the map labels itself as they come (online.*)",
             online_mod.online, _finish_online,
             lambda result, run_dir: "\n".join(x for x in (online_mod.table(result), report.follow_line(result.scene),
                                                          f"run folder: {run_dir}") if x)),
    Protocol("tiled", "global_3d per x-y tile of tiling.size (+ tiling.halo) on the frames that see it; tiles in "
             "this process or on Ray (tiling.*)", tiled.tiled, _finish_tiled, tiled.table, records=False,
             run_dir=True, result_records=True),
])
"""The protocols by name (``protocol.name``)."""




def register(entry: Protocol) -> Protocol:
    """Add a protocol (a run started after this may name it)."""
    return PROTOCOLS.register(entry)


def get(name: str) -> Protocol:
    """The entry a name names, or one line naming protocol.name and the names."""
    return PROTOCOLS.named(name)
