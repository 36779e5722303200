"""Tiled global 3D labelling (``protocol=tiled``, docs/tiling.md): the batch pipeline per tile.

The cloud is cut into a regular x-y grid of ``tiling.size`` metres (from the cloud's x-y minimum),
the edge shrunk so that the grid's cells just cover the cloud (:func:`fitted_edge`).
A tile's run is :func:`diffuser_lab.runs.pipeline.run` on a sub-scene: the points within
``tiling.halo`` (x and y) of the tile, and the frames whose view meets that box
(:func:`frames_meeting`), a :meth:`~diffuser_lab.data.frames.LazyFrames.subset` of the scene's
frames (each frame's predictions are seeded by the frame, so they are the ones the untiled run
has). The tile keeps its own points' labels; the halo only gives them their neighbours and
evidence. Labels and the Bayesian baseline are put together and scored once, over the whole scene.

Each tile writes ``tiles/<ix>_<iy>.npz`` (its labels, a checksum of its points, its record)
atomically; a run started with ``tiling.resume=<earlier run folder>`` keeps the tiles found
complete there and computes the others. Tiles run one after another in this process
(``tiling.workers=0``) or as Ray tasks (``tiling.workers>=1``: a local instance with that many
CPUs, or the cluster at ``tiling.address``); a Ray worker reads its tile's points from the file the
driver wrote (``tiles/inputs/<id>.npz``) and only its tile's frames, built from the scene source once
per worker process without the cloud where the source can; a failing tile is retried
(``tiling.max_retries``), then reported with its error while the others' labels are kept.
"""
from __future__ import annotations

import dataclasses
import logging
import os
import socket
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from diffuser_lab import progress
from diffuser_lab.backends import provenance
from diffuser_lab.config import Config, SparseClasses
from diffuser_lab.data import inputs, validate
from diffuser_lab.data.frames import LazyFrames, first_line
from diffuser_lab.data.scene import IGNORE, Scene
from diffuser_lab.data.taxonomy import resolve_taxonomy
from diffuser_lab.hooks import RunHooks
from diffuser_lab.method import fusion
from diffuser_lab.method.metrics import score

from . import pipeline
from .records import config_yaml
from .resolve import resolve
from .tile_geometry import (GRID_SLACK, Cells, TileInput, TileSpec, fitted_edge, frames_meeting, halo_metres,
                            tile_grid, tile_points, tile_specs)
from . import tile_store
from .tile_store import INPUTS, fill_from_halos, write_tile
from .work import sparse_classes

__all__ = ["TileSpec", "TileInput", "TiledResult", "tiled", "tile_grid", "tile_points", "frames_meeting", "fitted_edge",
           "fill_from_halos", "GRID_SLACK", "summary", "table"]


@dataclass
class TiledResult:
    """What a tiled run produced: labels on the scene's N points, the per-tile records."""

    scene: Scene
    method: str
    labels: np.ndarray  # (N,) int16, IGNORE = unlabeled (a failed tile's points too)
    bayesian_labels: np.ndarray  # (N,) int16
    grid: tuple[int, int]
    tiles: list[dict]
    tiles_dir: Path
    metrics: Optional[dict] = None
    baseline: dict = field(default_factory=dict)
    timings_s: dict = field(default_factory=dict)
    resumed_from: Optional[str] = None
    rho: Optional[float] = None  # the whole cloud's mean point spacing (sigma_d of every tile's graph from it)
    halo: float = 0.0  # the halo the tiles had, metres (tiling.halo, or halo_factor * sigma_d)
    tile_m: float = 0.0  # the tiles' edge, metres: tiling.size fitted to the cloud (fitted_edge)
    files: dict = field(default_factory=dict)  # what the run wrote beside the tiles (a features run: features.npy)
    from_halo: int = 0  # points their tile left unlabelled, labelled from a neighbour's halo (fill_from_halos)
    machines: list = field(default_factory=list)  # where the tiles ran: one entry per provenance (tile_machines)

    @property
    def failed(self) -> list[dict]:
        return [t for t in self.tiles if t["status"] == "error"]


def diffuse_tile(cfg: Config, inp: TileInput, frames, taxonomy, name: str, spec: TileSpec
                 ) -> tuple[np.ndarray, np.ndarray, dict, Optional[dict], tuple[np.ndarray, np.ndarray]]:
    """The pipeline on one tile: its own points' labels and Bayesian labels, its record, what its label
    space keeps of its own points (a features run's features: :func:`write_tile`'s dict; else None), and
    its halo's labelled points: (scene indices int64, labels int16), for :func:`fill_from_halos`.
    ``frames`` is the whole scene's frame sequence: the tile reads only ``spec.frames`` of it."""
    t0 = time.perf_counter()
    own, rows = inp.own, inp.rows
    rec = {"id": spec.id, "points": int(own.size), "points_with_halo": int(rows.size),
           "frames_read": len(spec.frames), "iterations": 0}
    labels = np.full(own.size, IGNORE, np.int16)
    bayes = labels.copy()
    feats = None
    halo = (np.zeros(0, np.int64), np.zeros(0, np.int16))
    if spec.frames:
        sub = Scene(name=f"{name} tile {spec.id}", points=inp.points, taxonomy=taxonomy,
                    frames=LazyFrames.subset(frames, spec.frames), normals=inp.normals)
        with warnings.catch_warnings(record=True) as caught, inputs.collecting() as read:
            warnings.simplefilter("always")
            res = pipeline.run(cfg, scene=sub)
        # the files this tile read (a Ray worker's too): the driver's summary lists them (tiled())
        rec["inputs"] = [dataclasses.asdict(e) for e in read.rows()]
        pos = np.searchsorted(rows, own)
        labels, bayes = res.labels[pos], res.bayesian_labels[pos]
        in_halo = np.ones(rows.size, bool)
        in_halo[pos] = False
        in_halo &= res.labels != IGNORE
        halo = (rows[in_halo].astype(np.int64), res.labels[in_halo].astype(np.int16))
        rec.update(res.space.tile_record())  # a features run: the tile's own basis and what it kept
        feats = res.space.tile_features(res.rows[pos])
        rec["iterations"] = int(res.diffusion.iterations) if res.diffusion is not None else 0
        if res.diffusion is not None:  # the tile's last relative residual (run.rrd's per-tile chart)
            rec["residual"] = float(res.diffusion.residual)
        msgs = sorted({first_line(w.message) for w in caught})
        if msgs:
            rec["warnings"] = msgs
    # provenance: the tile's own process (a Ray worker may run on another node); tile_machines groups them
    rec.update(time_s=round(time.perf_counter() - t0, 3), node=socket.gethostname(), pid=os.getpid(),
               status="done", peak_rss_gb=round(_peak_rss_gb(), 3), provenance=provenance.collect())
    return labels, bayes, rec, feats, halo


def tile_machines(tiles: list[dict]) -> list[dict]:
    """Where the tiles ran. Takes each tile record's ``provenance`` block out of it (the block of the
    process that computed the tile; a resumed tile's from its earlier run) and leaves ``machine``, the
    block's key (:func:`~diffuser_lab.backends.provenance.key`); returns one entry per distinct
    block: ``machine`` (the key), ``tiles`` (ids), ``nodes`` (host names), ``differs`` (the fields in
    which it differs from this process's block) and, when some do, the block itself (``provenance``)."""
    here = provenance.collect()
    groups: dict[str, dict] = {}
    blocks: dict[str, dict] = {}
    for rec in tiles:  # loop over tile records
        block = rec.pop("provenance", None)
        if not block:  # a failed tile, or a file of an older version
            continue
        k = provenance.key(block)
        rec["machine"] = k
        g = groups.setdefault(k, {"machine": k, "tiles": [], "nodes": []})
        blocks.setdefault(k, block)
        g["tiles"].append(rec["id"])
        node = rec.get("node") or block.get("host")
        if node not in g["nodes"]:
            g["nodes"].append(node)
    for k, g in groups.items():
        g["differs"] = [name for name, _, _ in provenance.blocks_differ(here, blocks[k])]
        if g["differs"]:
            g["provenance"] = blocks[k]
    return list(groups.values())


def _peak_rss_gb() -> float:
    """This process's peak resident memory so far (GB; 0 where the platform does not say)."""
    try:
        import resource
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux
    except (ImportError, OSError):
        return 0.0


def _run_tile(cfg: Config, inp: TileInput, frames, taxonomy, name: str, spec: TileSpec, tiles_dir: str) -> dict:
    labels, bayes, rec, feats, halo = diffuse_tile(cfg, inp, frames, taxonomy, name, spec)
    write_tile(Path(tiles_dir), spec, inp.own, labels, bayes, rec, feats, halo)
    return rec


_WORKER_FRAMES: dict[str, object] = {}


def _ray_tile(cfg: Config, frames_ref, taxonomy, name: str, spec: TileSpec, tiles_dir: str) -> dict:
    """A Ray task: the tile's points from ``tiles/inputs/<id>.npz`` (the driver wrote it), its frames
    from the source (built once per worker process, without the cloud where the source can) or
    from the sequence the driver put, then :func:`_run_tile`. Memory: the tile's, not the scene's."""
    # threads: Ray sets OMP_NUM_THREADS to the task's CPUs (1), which caps the compiled kernels' threads
    if frames_ref is None:
        key = config_yaml(cfg.scene) + config_yaml(cfg.depth) + config_yaml(cfg.taxonomy)
        if key not in _WORKER_FRAMES:
            _WORKER_FRAMES.clear()
            _WORKER_FRAMES[key] = pipeline.load_frames(cfg.scene, taxonomy, cfg.depth)
        frames = _WORKER_FRAMES[key]
    else:
        frames = frames_ref
    inp = TileInput.load(Path(tiles_dir) / INPUTS / f"{spec.id}.npz")
    with progress.quiet():
        return _run_tile(cfg, inp, frames, taxonomy, name, spec, tiles_dir)


def tiled(cfg: Config, *, scene: Optional[Scene] = None, hooks: Optional[RunHooks] = None,
          run_dir: Optional[Path] = None) -> TiledResult:
    """Label ``scene`` (default: the configured source) tile by tile; the tiles' files go to
    ``run_dir/tiles`` (or to ``tiling.resume``'s). ``hooks`` are not called (tiles run apart)."""
    cfg = resolve(cfg)
    if cfg.scene.voxel_size != 0:
        raise ValueError(f"protocol=tiled needs scene.voxel_size=0 (got {cfg.scene.voxel_size}): the voxel grid "
                         f"is anchored at the cloud's minimum, which a tile does not share")
    t = {}
    t0 = time.perf_counter()
    given = scene is not None
    if scene is None:
        scene = pipeline.load_scene(cfg.scene, resolve_taxonomy(cfg), cfg.depth)
    validate.check_points(scene)
    t["load"] = time.perf_counter() - t0
    tc0 = time.perf_counter()
    cfg, cells, rho = _tile_config(cfg, scene)
    tiles_dir = tile_store.tiles_dir(cfg, run_dir)
    tile_store.check_fingerprint(tiles_dir, cfg)
    specs = tile_specs(cfg, scene, cells, cells.boxes(scene.points, cfg.tiling.halo))
    owns = {s.id: cells.owns[(s.ix, s.iy)] for s in specs}
    t["tiles"] = time.perf_counter() - tc0  # the spacing and which frames see which tiles

    records, todo = tile_store.finished(tiles_dir, specs, owns, cfg.tiling.resume)
    td = time.perf_counter()
    records.update(_run_tiles(cfg, scene, given, cells, todo, tiles_dir))
    t["diffusion"] = time.perf_counter() - td

    tl = time.perf_counter()
    labels, bayes, files, from_halo = tile_store.assemble(tiles_dir, specs, owns, records, scene.n_points, run_dir)
    t["labels"] = time.perf_counter() - tl
    tiles = [records[s.id] for s in specs]
    for r in tiles:  # what each tile read, in this process or a Ray worker: this run's inputs
        inputs.merge(r.pop("inputs", ()))
    res = TiledResult(scene=scene, method=cfg.method.name, labels=labels, bayesian_labels=bayes, grid=cells.shape,
                      tile_m=float(cells.size), tiles=tiles, tiles_dir=tiles_dir, resumed_from=cfg.tiling.resume,
                      rho=rho, halo=cfg.tiling.halo, files=files, from_halo=from_halo, machines=tile_machines(tiles))
    if scene.gt_labels is not None:
        tm = time.perf_counter()
        res.metrics = score(labels, scene.gt_labels, scene.taxonomy.names)
        res.baseline["bayesian"] = score(bayes, scene.gt_labels, scene.taxonomy.names)
        t["metrics"] = time.perf_counter() - tm
    t["total"] = time.perf_counter() - t0
    res.timings_s = t
    return res


def _tile_config(cfg: Config, scene: Scene) -> tuple[Config, Cells, Optional[float]]:
    """What every tile shares with the untiled run, fixed in the config: sigma_d = sigma_d_factor * rho
    of the whole cloud (rho: the method's :meth:`~diffuser_lab.method.fusion.FusionMethod.spacing`,
    returned), the halo in metres (:func:`halo_metres`) and ``solver.sparse_classes=auto``'s choice
    (by the whole cloud's size); the cloud's cells."""
    method = fusion.get(cfg.method.name)
    cells = Cells(scene.points, cfg.tiling.size)
    rho = method.spacing(cfg, lambda: cells.spacing(scene.points, cfg.graph.k))
    if rho is not None:
        cfg = dataclasses.replace(cfg, graph=dataclasses.replace(cfg.graph, sigma_d=cfg.graph.sigma_d_factor * rho))
    cfg = dataclasses.replace(cfg, tiling=dataclasses.replace(cfg.tiling, halo=halo_metres(cfg, method)))
    if cfg.solver.sparse_classes == SparseClasses.auto:
        on = sparse_classes(cfg.solver, scene.n_points, scene.taxonomy.num_classes) > 0
        cfg = dataclasses.replace(cfg, solver=dataclasses.replace(
            cfg.solver, sparse_classes=SparseClasses.on if on else SparseClasses.off))
    return cfg, cells, rho


def _run_tiles(cfg: Config, scene: Scene, given: bool, cells: Cells, todo: list[TileSpec], tiles_dir: Path) -> dict:
    """The tiles ``todo``, one after another here (``tiling.workers=0``) or on Ray (:func:`_on_ray`);
    their records by id (a failed tile's: its error)."""
    tc = cfg.tiling
    if tc.workers != 0 or tc.address:
        return _on_ray(cfg, scene, given, cells, todo, tiles_dir) if todo else {}
    records = {}
    with progress.stage(f"tiles ({cells.shape[0]}x{cells.shape[1]} grid, {len(todo)} to run)", total=len(todo),
                        unit="tile") as bar:
        for spec in todo:  # loop over tiles
            try:
                records[spec.id] = _run_tile(cfg, cells.input(scene, spec), scene.frames, scene.taxonomy,
                                             scene.name, spec, str(tiles_dir))
            except (ValueError, MemoryError, OSError, FloatingPointError) as exc:
                records[spec.id] = _error(spec, cells.owns[(spec.ix, spec.iy)], exc)
            bar.update()
    return records


def _error(spec: TileSpec, own: np.ndarray, exc: BaseException) -> dict:
    return {"id": spec.id, "points": int(own.size), "frames_read": len(spec.frames), "iterations": 0,
            "status": "error", "error": f"{type(exc).__name__}: {first_line(exc)}"}


def _on_ray(cfg: Config, scene: Scene, given: bool, cells: Cells, todo: list[TileSpec], tiles_dir: Path) -> dict:
    """The tiles as Ray tasks (retried ``tiling.max_retries`` times); their records by id. Each
    task's points go through ``tiles/inputs/<id>.npz`` (written here one tile at a time); its
    frames come from the source in the worker, or, for a ``given`` scene, from the object put here."""
    import ray  # only a run on Ray pays its import (a second)

    tc = cfg.tiling
    started = False
    if not ray.is_initialized():
        # address="local": a new local instance even where another Ray runs on this machine (Ray would
        # join that one, refusing num_cpus)
        kw = dict(address=tc.address) if tc.address else dict(address="local", num_cpus=tc.workers)
        # the workers import this package from where the driver does (a node must see that path,
        # e.g. a shared file system, or have diffuser-lab installed)
        path = [str(Path(__file__).resolve().parents[2])] + [p for p in [os.environ.get("PYTHONPATH")] if p]
        ray.init(include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING,
                 runtime_env={"env_vars": {"PYTHONPATH": os.pathsep.join(path)}}, **kw)
        started = True
    inputs = tiles_dir / INPUTS
    inputs.mkdir(exist_ok=True)
    try:
        task = ray.remote(num_cpus=1, max_retries=tc.max_retries, retry_exceptions=True)(_ray_tile)
        frames_ref = ray.put(scene.frames) if given else None
        refs = {}
        for spec in todo:  # loop over tiles: one tile's points in memory at a time
            cells.input(scene, spec).save(inputs / f"{spec.id}.npz")
            refs[task.remote(cfg, frames_ref, scene.taxonomy, scene.name, spec, str(tiles_dir))] = spec
        out: dict[str, dict] = {}
        pending = list(refs)
        with progress.stage(f"tiles on Ray ({len(todo)} tasks)", total=len(todo), unit="tile") as bar:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                for ref in done:  # loop over finished tiles
                    spec = refs[ref]
                    try:
                        out[spec.id] = ray.get(ref)
                        (inputs / f"{spec.id}.npz").unlink(missing_ok=True)
                    except Exception as exc:  # noqa: BLE001 - a tile's error, after its retries, is its record
                        cause = getattr(exc, "cause", None) or exc
                        out[spec.id] = _error(spec, cells.owns[(spec.ix, spec.iy)], cause)
                    bar.update()
        return out
    finally:
        if started:
            ray.shutdown()


def summary(res: TiledResult, cfg: Config) -> dict:
    """summary.json content of a tiled run (``tiling.tiles``: one record per tile)."""
    s = res.scene
    failed = res.failed
    return {
        "protocol": "tiled",
        "method": res.method,
        "scene": s.name,
        "n_points": s.n_points,
        "n_frames": len(s.frames),
        "n_classes": s.taxonomy.num_classes,
        "taxonomy": s.taxonomy.name,
        "n_unlabeled": int((res.labels == IGNORE).sum()),
        "metrics": res.metrics,
        "baseline": {"bayesian": res.baseline.get("bayesian")},
        "diffusion": {"iterations": max([r.get("iterations", 0) for r in res.tiles] or [0])},
        "timings_s": {k: round(v, 4) for k, v in res.timings_s.items()},
        "tiling": {"size": cfg.tiling.size, "tile_m": res.tile_m, "halo": res.halo, "halo_factor": cfg.tiling.halo_factor, "grid": list(res.grid),
                   "n_tiles": len(res.tiles), "failed": len(failed), "workers": cfg.tiling.workers,
                   "address": cfg.tiling.address, "tiles_dir": str(res.tiles_dir), "resumed_from": res.resumed_from,
                   "rho_m": res.rho, "from_halo": res.from_halo, "machines": res.machines, "tiles": res.tiles},
    }


def table(res: TiledResult, run_dir: Optional[Path] = None) -> str:
    """What the command line prints after a tiled run."""
    s = res.scene
    n = len(res.tiles)
    frames = [r["frames_read"] for r in res.tiles]
    resumed = sum(r["status"] == "resumed" for r in res.tiles)
    lines = [f"diffuser-lab | scene {s.name} | {s.n_points:,} points | {len(s.frames)} frames | tiled "
             f"{res.grid[0]}x{res.grid[1]} grid, {n} tiles"]
    if res.metrics is not None:
        lines.append(f"{'':22s}{'mIoU':>7s}{'acc':>7s}{'cover':>7s}")
        for name, m in [(res.method, res.metrics), ("bayesian (baseline)", res.baseline.get("bayesian"))]:
            m = m or {}
            lines.append(f"{name:22s}" + "".join(f"{'-' if m.get(k) is None else format(m[k], '.1f'):>7s}"
                                                 for k in ("miou", "accuracy", "coverage")))
    lines.append(f"tiles: {n - len(res.failed)} of {n} done ({resumed} kept from {res.resumed_from}), frames read "
                 f"per tile {min(frames, default=0)}-{max(frames, default=0)} of {len(s.frames)}"
                 if resumed else f"tiles: {n - len(res.failed)} of {n} done, frames read per tile "
                 f"{min(frames, default=0)}-{max(frames, default=0)} of {len(s.frames)}")
    for r in res.failed:  # loop over failed tiles
        lines.append(f"tile {r['id']} failed: {r['error']}")
    for m in res.machines:  # loop over machines unlike this process's: their figures may differ
        if m["differs"]:
            n = len(m["tiles"])
            lines.append(f"{n} tile{'s' if n != 1 else ''} ran on another machine or versions "
                         f"({', '.join(m['nodes'])}: {', '.join(m['differs'])} differ)")
    lines.append("time [s]  " + "  ".join(f"{k} {v:.2f}" for k, v in res.timings_s.items()))
    if run_dir is not None:
        lines.append(f"run folder: {run_dir}")
        if res.failed:
            folder = res.resumed_from or run_dir
            lines.append(f"finish the failed tiles: diffuser-lab protocol=tiled ... tiling.resume={folder}")
    return "\n".join(lines)
