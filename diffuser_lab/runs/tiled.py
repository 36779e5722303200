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
import hashlib
import io
import json
import logging
import math
import os
import socket
import time
import warnings
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from diffuser_lab import progress
from diffuser_lab.backends import provenance
from diffuser_lab.backends.threads import blas_one_thread
from diffuser_lab.config import Config, SparseClasses
from diffuser_lab.data import inputs, validate
from diffuser_lab.data.frames import FrameLoop, LazyFrames, first_line
from diffuser_lab.data.scene import IGNORE, Scene
from diffuser_lab.data.taxonomy import resolve_taxonomy
from diffuser_lab.hooks import RunHooks
from diffuser_lab.method import fusion
from diffuser_lab.method.basis import unit_rows_float16
from diffuser_lab.method.graph import nearest_distinct
from diffuser_lab.method.metrics import score

from . import pipeline
from .records import WRITE_ROWS, config_yaml, write_json_atomic
from .resolve import resolve

__all__ = ["TileSpec", "TileInput", "TiledResult", "tiled", "tile_grid", "tile_points", "frames_meeting", "summary", "table"]

TILES = "tiles"
"""The run folder's sub-folder of tile files."""
INPUTS = "inputs"
"""``tiles/inputs/<id>.npz``: a Ray tile's points (:class:`TileInput`), removed once the tile is done."""


@dataclass(frozen=True)
class TileSpec:
    """One tile: grid cell (ix, iy) of edge ``size`` from ``origin`` (x, y), its halo and the
    indices of the frames that see the tile and its halo."""

    ix: int
    iy: int
    origin: tuple[float, float]
    size: float
    halo: float
    frames: tuple[int, ...] = ()

    @property
    def id(self) -> str:
        return f"{self.ix}_{self.iy}"


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


# a cloud overshooting a whole number of tiles by less than this fraction of tiling.size keeps that
# number (its tiles up to this much larger) rather than a whole extra row or column: the 3x3 city at
# 0.1 m spans 181.9 m, and 4 x 45.5 m tiles put their borders inside its buildings where 3 x 60.6 m
# put them on its streets (labels equal to the untiled run 99.94 % vs 99.999 %, results/tiling.md)
GRID_SLACK = 0.05


def fitted_edge(points: np.ndarray, size: float) -> float:
    """The tiles' edge, metres: ``size`` (``tiling.size``) fitted so that the ceil(extent / size -
    :data:`GRID_SLACK`) cells of each axis just cover the cloud's x-y extent (the larger of extent / cells
    over x and y, a hair more so that the farthest point falls in the last cell): the grid fitted to the
    cloud, no near-empty last row or column; never more than ``size`` x (1 + GRID_SLACK)."""
    ext = points[:, :2].max(0).astype(np.float64) - points[:, :2].min(0).astype(np.float64)
    whole = np.maximum(np.ceil(ext / size), 1.0)
    cells = np.maximum(np.ceil(ext / size - GRID_SLACK), 1.0)
    e = float((ext / cells).max()) * (1.0 + 1e-9)
    if e <= 0:
        return float(size)
    return min(float(size), e) if (cells == whole).all() else min(float(size) * (1.0 + GRID_SLACK), e)


def tile_grid(points: np.ndarray, size: float) -> tuple[tuple[float, float], tuple[int, int], np.ndarray]:
    """The grid's origin (the cloud's x-y minimum), its shape (nx, ny) and each point's cell (N, 2) int32
    (an axis at a time: 12 bytes a point at most besides the result), the cells' edge
    :func:`fitted_edge` (``size`` fitted to the cloud)."""
    return _grid(points, fitted_edge(points, size))


def _grid(points: np.ndarray, size: float) -> tuple[tuple[float, float], tuple[int, int], np.ndarray]:
    """:func:`tile_grid` for cells of edge ``size`` as given (already fitted)."""
    origin = points[:, :2].min(0).astype(np.float64)
    cell = np.empty((len(points), 2), np.int32)
    for k in range(2):  # x, y: float64 as tile_points computes it
        cell[:, k] = np.floor((points[:, k].astype(np.float64) - origin[k]) / size)
    shape = np.maximum(cell.max(0).astype(np.int64) + 1, 1)
    return (float(origin[0]), float(origin[1])), (int(shape[0]), int(shape[1])), cell


def tile_points(points: np.ndarray, spec: TileSpec) -> tuple[np.ndarray, np.ndarray]:
    """(own, rows): sorted indices of the tile's own points and of its points plus halo (own is in rows).
    A point's own tile is the cell of :func:`tile_grid`; the halo is the box grown by ``halo`` in x and y."""
    o = np.asarray(spec.origin)
    cell = np.floor((points[:, :2] - o) / spec.size).astype(np.int64)
    own = np.flatnonzero((cell[:, 0] == spec.ix) & (cell[:, 1] == spec.iy))
    lo = o + np.array([spec.ix, spec.iy]) * spec.size - spec.halo
    hi = o + np.array([spec.ix + 1, spec.iy + 1]) * spec.size + spec.halo
    xy = points[:, :2]
    near = np.all((xy >= lo) & (xy <= hi), axis=1)
    near[own] = True  # a point on the upper edge of the box (float rounding) is still in its tile
    return own, np.flatnonzero(near)


def frames_meeting(boxes: np.ndarray, K: np.ndarray, T_cw: np.ndarray, shape: tuple[int, int],
                   margin_px: float = 1.0, max_depth: Optional[float] = None) -> np.ndarray:
    """Which of the (T, 2, 3) axis-aligned boxes (min, max corner, world metres) a camera's view
    meets: the view is the pyramid of points in front of the camera (z > 0, and z <= ``max_depth``)
    that project into the image grown by ``margin_px`` pixels. A box is out of view when all its
    8 corners lie outside one of the pyramid's planes; otherwise it counts as seen (conservative:
    a box near a corner of the pyramid may count as seen without being so, never the reverse)."""
    K = np.asarray(K, np.float64)
    T = np.asarray(T_cw, np.float64)
    h, w = shape
    sel = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)])  # (8, 3) min/max per axis
    corners = np.where(sel[None].astype(bool), boxes[:, 1][:, None], boxes[:, 0][:, None])  # (T, 8, 3)
    X = corners @ T[:3, :3].T + T[:3, 3]  # camera coordinates
    e3 = np.array([0.0, 0.0, 1.0])
    lo_u, hi_u, lo_v, hi_v = -0.5 - margin_px, w - 0.5 + margin_px, -0.5 - margin_px, h - 0.5 + margin_px
    planes = [K[0] - lo_u * e3, hi_u * e3 - K[0], K[1] - lo_v * e3, hi_v * e3 - K[1]]  # u*z = K[0].X
    outside = np.all(X[..., 2] <= 0, axis=1)  # behind the camera
    if max_depth is not None:
        outside |= np.all(X[..., 2] > max_depth, axis=1)  # beyond the far plane
    for p in planes:  # loop over the pyramid's side planes: all corners on the outer side
        outside |= np.all(X @ p < 0, axis=1)
    return ~outside


@dataclass
class TileInput:
    """What a tile's diffusion reads besides its frames: its own points and its points with halo
    (sorted indices into the scene's N points; own is in rows), their coordinates and normals
    (world metres, float32). Written by the driver for Ray workers (``tiles/inputs/<id>.npz``)."""

    own: np.ndarray  # (n_own,) int64
    rows: np.ndarray  # (n_rows,) int64
    points: np.ndarray  # (n_rows, 3) float32
    normals: Optional[np.ndarray]  # (n_rows, 3) float32 or None

    def save(self, path: Path) -> Path:
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        with open(tmp, "wb") as fh:
            np.savez(fh, own=self.own, rows=self.rows, points=self.points,
                     **({} if self.normals is None else {"normals": self.normals}))
        os.replace(tmp, path)
        return path

    @classmethod
    def load(cls, path: Path) -> "TileInput":
        with np.load(path) as z:
            return cls(z["own"], z["rows"], z["points"], z["normals"] if "normals" in z.files else None)


class _Cells:
    """The cloud's points by grid cell (one argsort), for a tile's rows from its neighbouring cells."""

    def __init__(self, points: np.ndarray, size: float):
        edge = fitted_edge(points, size)  # the grid's cells' edge, metres (one pass for it, not two)
        origin, self.shape, cell = _grid(points, edge)
        flat = cell[:, 0].astype(np.int64) * self.shape[1] + cell[:, 1]
        del cell
        order = np.argsort(flat, kind="stable")  # within a cell: ascending point index
        keys, starts = np.unique(flat[order], return_index=True)
        del flat
        self.origin, self.size = origin, edge
        self.owns = {(int(k // self.shape[1]), int(k % self.shape[1])): o
                     for k, o in zip(keys, np.split(order, starts[1:]))}

    def rows(self, points: np.ndarray, spec: TileSpec) -> np.ndarray:
        """:func:`tile_points`' rows of ``spec``, from the cells within the halo's reach only: the
        tile's own cell whole, the others' points within the box."""
        r = int(math.ceil(spec.halo / spec.size))
        own = self.owns[(spec.ix, spec.iy)]
        parts = [self.owns.get((spec.ix + i, spec.iy + j)) for i in range(-r, r + 1) for j in range(-r, r + 1)
                 if i or j]
        parts = [p for p in parts if p is not None]
        if not parts:
            return own.copy()
        cand = np.concatenate(parts)
        o = np.asarray(spec.origin)
        lo = o + np.array([spec.ix, spec.iy]) * spec.size - spec.halo
        hi = o + np.array([spec.ix + 1, spec.iy + 1]) * spec.size + spec.halo
        xy = points[cand, :2]
        rows = np.concatenate([own, cand[np.all((xy >= lo) & (xy <= hi), axis=1)]])
        rows.sort()
        return rows

    def spacing(self, points: np.ndarray, k: int) -> float:
        """rho, the whole cloud's mean spacing as :func:`~diffuser_lab.method.graph.build_graph` takes it
        (per point the nearest distinct neighbour among its ``k`` nearest), tile by tile without a
        halo guessed beforehand: a tile's own points' nearest neighbours among themselves, exact for
        a point nearer to one of them than to its cell's border; the others (a thin band along the
        border) are looked up again among the points within that distance of the cell."""
        total, count = 0.0, 0
        with progress.stage(f"point spacing ({len(points):,} points, {len(self.owns)} tiles)", total=len(self.owns),
                            unit="tile") as bar:
            for (ix, iy), own in self.owns.items():  # loop over tiles
                p = points[own]
                d = nearest_distinct(p, k)  # K = 24 runs faster than 2 here
                lo = np.asarray(self.origin) + np.array([ix, iy]) * self.size
                border = np.minimum(p[:, :2] - lo, lo + self.size - p[:, :2]).min(1)
                unsure = np.flatnonzero(~(d <= border))  # a point outside the cell may be nearer
                if unsure.size:
                    du = d[unsure]
                    # a point without a distinct neighbour in its tile looks one cell further
                    h = float(du[np.isfinite(du)].max(initial=0.0)) if np.isfinite(du).all() else \
                        max(self.size, float(du[np.isfinite(du)].max(initial=0.0)))
                    rows = self.rows(points, TileSpec(ix, iy, self.origin, self.size, h))
                    q = points[rows]
                    band = np.minimum(q[:, :2] - lo, lo + self.size - q[:, :2]).min(1) <= 2 * h  # outside: < 0
                    cand = q[band]
                    dist, _ = cKDTree(cand).query(p[unsure], k=min(k + 1, len(cand)))
                    dist = np.where(dist.reshape(len(unsure), -1) > 0, dist.reshape(len(unsure), -1), np.inf)
                    d[unsure] = np.minimum(du, dist.min(1))
                d = d[np.isfinite(d)]
                total, count = total + float(d.sum()), count + int(d.size)
                bar.update()
        if count == 0:
            raise ValueError("all points coincide: the mean point spacing rho is 0")
        return total / count

    def boxes(self, points: np.ndarray, halo: float) -> np.ndarray:
        """Each tile's (2, 3) box (min, max corner of its points with halo ``halo``, metres), in
        ``owns`` order: (T, 2, 3) float64."""
        boxes = np.empty((len(self.owns), 2, 3), np.float64)
        for t, (ix, iy) in enumerate(self.owns):  # loop over tiles
            p = points[self.rows(points, TileSpec(ix, iy, self.origin, self.size, halo))]
            boxes[t] = p.min(0), p.max(0)
        return boxes

    def input(self, scene: Scene, spec: TileSpec) -> TileInput:
        rows = self.rows(scene.points, spec)
        return TileInput(self.owns[(spec.ix, spec.iy)], rows, scene.points[rows],
                         None if scene.normals is None else scene.normals[rows])


def halo_metres(cfg: Config, graph: bool) -> float:
    """The tile halo in metres: ``tiling.halo`` when given, else ``tiling.halo_factor`` * sigma_d (the
    graph's distance bandwidth, resolved: sigma_d_factor * rho), so that it scales with the point
    spacing as the graph's reach per Jacobi step does (docs/tiling.md); 0 for a method without a
    graph (a point's label depends on its own evidence only)."""
    if cfg.tiling.halo is not None:
        return float(cfg.tiling.halo)
    if not graph:
        return 0.0
    if cfg.graph.sigma_d is None:
        raise ValueError("tiling.halo=null needs the graph's sigma_d (resolved from rho first)")
    return float(cfg.tiling.halo_factor * cfg.graph.sigma_d)


def _specs(cfg: Config, scene: Scene, cells: _Cells, boxes: np.ndarray) -> list[TileSpec]:
    """The tiles with own points (``cells.owns`` order, their (T, 2, 3) ``boxes``), each with the
    frames that see it (one pass over the frames' cameras, one frame read at a time)."""
    tc = cfg.tiling
    base = [TileSpec(ix, iy, cells.origin, cells.size, tc.halo) for ix, iy in cells.owns]
    seen = np.zeros((len(base), len(scene.frames)), bool)
    margin = cfg.evidence.pixel_radius + 1.0
    for i, f in FrameLoop(scene.frames, f"cameras: which frames see which of {len(base)} tiles"):
        seen[:, i] = frames_meeting(boxes, f.K, f.T_cw, f.shape, margin, tc.max_depth)
    return [dataclasses.replace(s, frames=tuple(int(i) for i in np.flatnonzero(seen[t]))) for t, s in enumerate(base)]


def diffuse_tile(cfg: Config, inp: TileInput, frames, taxonomy, name: str, spec: TileSpec
                 ) -> tuple[np.ndarray, np.ndarray, dict, Optional[dict], tuple[np.ndarray, np.ndarray]]:
    """The pipeline on one tile: its own points' labels and Bayesian labels, its record, (a
    features run) its own points' features (:func:`write_tile`'s dict), else None, and its halo's
    labelled points: (scene indices int64, labels int16), for :func:`fill_from_halos`.
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
        if res.lifted is not None:  # a features run (method/features.py)
            lf = res.lifted
            rec["basis"] = lf.basis_info  # the tile's own basis (predictions.basis=auto) and what it kept
            if lf.basis is None:
                feats = {"features": lf.unit_rows(lf.method, res.rows[pos])}
            else:  # the coordinates in the tile's basis: (own, k), made (own, D) when features.npy is written
                feats = {"feature_coords": np.asarray(lf.method.coords[res.rows[pos]], np.float32),
                         "feature_vectors": lf.basis.vectors}
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


def fill_from_halos(labels: np.ndarray, halos: list[tuple[np.ndarray, np.ndarray]],
                    done: Optional[np.ndarray] = None) -> int:
    """Give a point its tile left unlabelled (nothing reached it there: unseen surface whose
    evidence lies across the border) the label a neighbouring tile gave it in its halo, the first
    such tile in grid order; labelled points keep theirs, and so do the points of a failed tile
    (``done``: (N,) bool, False there; None = every tile finished). ``labels``: (N,) int16, changed
    in place; ``halos``: per tile (scene indices, labels) of its labelled halo points. Returns how many
    points were filled. The untiled graph reaches these points through the border; a tile only
    through its halo, so the neighbour that holds them in its halo is the one that saw the way."""
    filled = 0
    for idx, lab in halos:  # loop over tiles
        take = labels[idx] == IGNORE
        if done is not None:
            take &= done[idx]
        labels[idx[take]] = lab[take]
        filled += int(take.sum())
    return filled


def _peak_rss_gb() -> float:
    """This process's peak resident memory so far (GB; 0 where the platform does not say)."""
    try:
        import resource
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux
    except (ImportError, OSError):
        return 0.0


def _crc(own: np.ndarray) -> int:
    return zlib.crc32(np.ascontiguousarray(own, np.int64).tobytes())


def write_tile(tiles_dir: Path, spec: TileSpec, own: np.ndarray, labels: np.ndarray, bayes: np.ndarray,
               rec: dict, features: Optional[dict] = None,
               halo: Optional[tuple[np.ndarray, np.ndarray]] = None) -> Path:
    """``tiles/<id>.npz`` through a temporary file and os.replace (never half-written under its name);
    a features run's tile also keeps its points' features (``features``: ``{"features": (own, D)
    float16 unit rows}``, or in the tile's reduced basis ``{"feature_coords": (own, k) float32,
    "feature_vectors": (D, k) float32}``), every tile its halo's labelled points."""
    path = Path(tiles_dir) / f"{spec.id}.npz"
    buf = io.BytesIO()
    extra = dict(features or {})
    if halo is not None:
        extra.update(halo_index=halo[0], halo_labels=halo[1])
    np.savez(buf, labels=labels.astype(np.int16), bayesian=bayes.astype(np.int16), crc=np.int64(_crc(own)),
             record=np.array(json.dumps(rec)), **extra)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as fh:
        fh.write(buf.getvalue())
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    return path


def read_tile(tiles_dir: Path, spec: TileSpec, own: np.ndarray, features: bool = False, halo: bool = False
              ) -> Optional[tuple[np.ndarray, np.ndarray, dict, Optional[dict], Optional[tuple]]]:
    """A tile's finished file (labels, Bayesian labels, record, with ``features`` a features
    run's features (:func:`write_tile`'s dict) or None, and with ``halo`` its halo's labelled points
    (indices, labels) or None in a file without them), or None when it is missing or not complete
    (unreadable, another shape, another set of points)."""
    path = Path(tiles_dir) / f"{spec.id}.npz"
    if not path.is_file():
        return None
    try:
        with np.load(path) as z:
            labels, bayes, crc, rec = z["labels"], z["bayesian"], int(z["crc"]), json.loads(str(z["record"]))
            feats = ({k: z[k] for k in TILE_FEATURES if k in z.files} or None) if features else None
            halo = (z["halo_index"], z["halo_labels"]) if halo and "halo_index" in z.files else None
    except Exception:  # noqa: BLE001 - a truncated or foreign file: the tile is computed again
        return None
    if labels.shape != (own.size,) or bayes.shape != (own.size,) or crc != _crc(own):
        return None
    if feats is not None and next(v for k, v in feats.items() if k != "feature_vectors").shape[0] != own.size:
        return None
    if halo is not None and halo[0].shape != halo[1].shape:
        halo = None
    return labels, bayes, rec, feats, halo


TILE_FEATURES = ("features", "feature_coords", "feature_vectors")
"""A features run's tile file's feature arrays (:func:`write_tile`)."""


def _features_into(path: Path, own: np.ndarray, feats: dict) -> None:
    """A tile's features into the rows ``own`` of features.npy (opened as a memory map for this tile
    only: its pages leave the process when it is closed), a chunk of rows at a time."""
    mm = np.load(path, mmap_mode="r+")
    if "features" in feats:
        mm[own] = feats["features"]
    else:
        with blas_one_thread():
            for lo in range(0, own.size, WRITE_ROWS):  # chunks of rows: (4096, D) temporaries
                mm[own[lo:lo + WRITE_ROWS]] = unit_rows_float16(feats["feature_coords"][lo:lo + WRITE_ROWS],
                                                                feats["feature_vectors"])
    mm.flush()
    del mm


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


def _fingerprint(cfg: Config) -> str:
    """What makes tiles of two runs interchangeable: the config without where and how they ran."""
    t = dataclasses.replace(cfg.tiling, workers=0, address=None, max_retries=0, resume=None)
    c = dataclasses.replace(cfg, tiling=t, record=type(cfg.record)(), output=type(cfg.output)())
    return hashlib.sha1(config_yaml(c).encode()).hexdigest()


def _tiles_dir(cfg: Config, run_dir: Optional[Path]) -> Path:
    if cfg.tiling.resume:
        d = Path(cfg.tiling.resume) / TILES
        if not d.is_dir():
            raise FileNotFoundError(f"tiling.resume={cfg.tiling.resume}: no {TILES}/ folder of a tiled run there")
        return d
    if run_dir is None:
        raise ValueError("a tiled run needs a run folder for its tiles (run_dir=..., or tiling.resume=<folder>)")
    d = Path(run_dir) / TILES
    d.mkdir(parents=True, exist_ok=True)
    return d


def _check_fingerprint(tiles_dir: Path, cfg: Config) -> None:
    path = tiles_dir / "tiling.json"
    fp = _fingerprint(cfg)
    if path.is_file():
        old = json.loads(path.read_text()).get("config_sha1")
        if old != fp:
            raise ValueError(f"tiling.resume: the tiles in {tiles_dir} were made with another config (scene, "
                             f"predictions, method, tiling.size/halo, ...); resume with the same keys")
    else:
        write_json_atomic(path, {"config_sha1": fp})


def tiled(cfg: Config, *, scene: Optional[Scene] = None, hooks: Optional[RunHooks] = None,
          run_dir: Optional[Path] = None) -> TiledResult:
    """Label ``scene`` (default: the configured source) tile by tile; the tiles' files go to
    ``run_dir/tiles`` (or to ``tiling.resume``'s). ``hooks`` are not called (tiles run apart)."""
    cfg = resolve(cfg)
    tc = cfg.tiling
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
    cells = _Cells(scene.points, tc.size)
    # sigma_d = sigma_d_factor * rho, rho the mean spacing of the whole cloud: the tiles use the untiled value
    graph = fusion.get(cfg.method.name).graph
    rho = cells.spacing(scene.points, cfg.graph.k) if graph and cfg.graph.sigma_d is None else None
    if rho is not None:
        cfg = dataclasses.replace(cfg, graph=dataclasses.replace(cfg.graph, sigma_d=cfg.graph.sigma_d_factor * rho))
    cfg = dataclasses.replace(cfg, tiling=dataclasses.replace(tc, halo=halo_metres(cfg, graph)))
    tc = cfg.tiling
    boxes = cells.boxes(scene.points, tc.halo)
    if cfg.solver.sparse_classes == SparseClasses.auto:  # the untiled run's choice (by the whole cloud's size)
        on = pipeline._sparse_classes(cfg.solver, scene.n_points, scene.taxonomy.num_classes) > 0
        cfg = dataclasses.replace(cfg, solver=dataclasses.replace(
            cfg.solver, sparse_classes=SparseClasses.on if on else SparseClasses.off))
    tiles_dir = _tiles_dir(cfg, run_dir)
    _check_fingerprint(tiles_dir, cfg)
    specs = _specs(cfg, scene, cells, boxes)
    shape, owns = cells.shape, {s.id: cells.owns[(s.ix, s.iy)] for s in specs}
    t["tiles"] = time.perf_counter() - tc0  # the spacing and which frames see which tiles

    records: dict[str, dict] = {}
    todo = []
    for spec in specs:  # loop over tiles: the finished ones are kept
        got = read_tile(tiles_dir, spec, owns[spec.id])
        if got is None:
            todo.append(spec)
        else:
            records[spec.id] = dict(got[2], status="resumed" if tc.resume else got[2]["status"])
    td = time.perf_counter()
    if tc.workers == 0 and not tc.address:
        with progress.stage(f"tiles ({shape[0]}x{shape[1]} grid, {len(todo)} to run)", total=len(todo),
                            unit="tile") as bar:
            for spec in todo:  # loop over tiles
                try:
                    records[spec.id] = _run_tile(cfg, cells.input(scene, spec), scene.frames, scene.taxonomy,
                                                 scene.name, spec, str(tiles_dir))
                except (ValueError, MemoryError, OSError, FloatingPointError) as exc:
                    records[spec.id] = _error(spec, owns[spec.id], exc)
                bar.update()
    elif todo:
        records.update(_on_ray(cfg, scene, given, cells, todo, tiles_dir))
    t["diffusion"] = time.perf_counter() - td

    tl = time.perf_counter()
    labels = np.full(scene.n_points, IGNORE, np.int16)
    bayes = labels.copy()
    features = None  # a features run's (N, D) float16 features.npy, a memory map filled tile by tile
    halos, done = [], np.zeros(scene.n_points, bool)  # done: the points whose own tile finished
    for spec in specs:  # loop over tiles: their files -> the scene's labels (and features)
        got = (read_tile(tiles_dir, spec, owns[spec.id], features=run_dir is not None, halo=True)
               if records[spec.id]["status"] != "error" else None)
        if got is None and records[spec.id]["status"] != "error":
            records[spec.id] = dict(records[spec.id], status="error", error="its tile file is missing or damaged")
        if got is not None:
            labels[owns[spec.id]], bayes[owns[spec.id]] = got[0], got[1]
            done[owns[spec.id]] = True
            if got[4] is not None and got[4][0].size and got[4][0].max() < scene.n_points:
                halos.append(got[4])
            if got[3] is not None:
                if features is None:  # made once, zero rows; each tile's rows written through its own map
                    features = Path(run_dir) / "features.npy"
                    fe = got[3]
                    dim = fe["features"].shape[1] if "features" in fe else fe["feature_vectors"].shape[0]
                    np.lib.format.open_memmap(features, mode="w+", dtype=np.float16, shape=(scene.n_points, dim)).flush()
                _features_into(features, owns[spec.id], got[3])  # a failed tile's points keep zero rows (unlabeled)
    from_halo = fill_from_halos(labels, halos, done) if features is None else 0  # features: per-point rows, not labels
    res_files = {}
    if features is not None:
        res_files["features"] = "features.npy"
    t["labels"] = time.perf_counter() - tl
    tiles = [records[s.id] for s in specs]
    for r in tiles:  # what each tile read, in this process or a Ray worker: this run's inputs
        inputs.merge(r.pop("inputs", ()))
    res = TiledResult(scene=scene, method=cfg.method.name, labels=labels, bayesian_labels=bayes, grid=shape,
                      tile_m=float(cells.size),
                      tiles=tiles, tiles_dir=tiles_dir, resumed_from=tc.resume, rho=rho,
                      halo=tc.halo, files=res_files, from_halo=from_halo, machines=tile_machines(tiles))
    if scene.gt_labels is not None:
        tm = time.perf_counter()
        res.metrics = score(labels, scene.gt_labels, scene.taxonomy.names)
        res.baseline["bayesian"] = score(bayes, scene.gt_labels, scene.taxonomy.names)
        t["metrics"] = time.perf_counter() - tm
    t["total"] = time.perf_counter() - t0
    res.timings_s = t
    return res


def _error(spec: TileSpec, own: np.ndarray, exc: BaseException) -> dict:
    return {"id": spec.id, "points": int(own.size), "frames_read": len(spec.frames), "iterations": 0,
            "status": "error", "error": f"{type(exc).__name__}: {first_line(exc)}"}


def _on_ray(cfg: Config, scene: Scene, given: bool, cells: _Cells, todo: list[TileSpec], tiles_dir: Path) -> dict:
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
