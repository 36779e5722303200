"""A tiled run's geometry (``protocol=tiled``, docs/tiling.md): the regular x-y grid of ``tiling.size``
metres fitted to the cloud (:func:`fitted_edge`, :func:`tile_grid`), a tile's own points and its
points with halo (:func:`tile_points`, :class:`Cells`: by grid cell, for many tiles), the halo a
method needs (:func:`halo_metres`), the frames whose view meets a tile (:func:`frames_meeting`,
:func:`tile_specs`) and what a tile's diffusion reads besides its frames (:class:`TileInput`)."""
from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from diffuser_lab import progress
from diffuser_lab.config import Config
from diffuser_lab.data.frames import FrameLoop
from diffuser_lab.data.scene import Scene
from diffuser_lab.method.graph import nearest_distinct

__all__ = ["TileSpec", "TileInput", "Cells", "GRID_SLACK", "fitted_edge", "tile_grid", "tile_points", "frames_meeting",
           "halo_metres", "tile_specs"]


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


class Cells:
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


def halo_metres(cfg: Config, method) -> float:
    """The tile halo in metres: ``tiling.halo`` when given, else how far the ``method``'s labels reach
    (:meth:`~diffuser_lab.method.fusion.FusionMethod.halo`: ``tiling.halo_factor`` * sigma_d, the graph's
    distance bandwidth resolved, so that it scales with the point spacing as the graph's reach per
    Jacobi step does, docs/tiling.md; 0 without a graph)."""
    if cfg.tiling.halo is not None:
        return float(cfg.tiling.halo)
    return method.halo(cfg)


def tile_specs(cfg: Config, scene: Scene, cells: Cells, boxes: np.ndarray) -> list[TileSpec]:
    """The tiles with own points (``cells.owns`` order, their (T, 2, 3) ``boxes``), each with the
    frames that see it (one pass over the frames' cameras, one frame read at a time)."""
    tc = cfg.tiling
    base = [TileSpec(ix, iy, cells.origin, cells.size, tc.halo) for ix, iy in cells.owns]
    seen = np.zeros((len(base), len(scene.frames)), bool)
    margin = cfg.evidence.pixel_radius + 1.0
    for i, f in FrameLoop(scene.frames, f"cameras: which frames see which of {len(base)} tiles"):
        seen[:, i] = frames_meeting(boxes, f.K, f.T_cw, f.shape, margin, tc.max_depth)
    return [dataclasses.replace(s, frames=tuple(int(i) for i in np.flatnonzero(seen[t]))) for t, s in enumerate(base)]
