"""Depth images for frames that have none, so the paper's depth check (Eq. 2's visibility) runs as
usual: rendered from a triangle mesh (:class:`MeshDepth`, ray casting) or from the point cloud
itself (:class:`CloudDepth`, a point z-buffer).

Both are callables ``(K, T_cw, (H, W)) -> (H, W) float32 z-depth`` in metres, 0 = nothing seen,
with the conventions of :mod:`diffuser_lab.data.geometry` (world metres, ``T_cw`` world-to-camera,
pixel centres at integer coordinates).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from .geometry import project
from .o3d import open3d
from .render import MeshRenderer

__all__ = ["CloudDepth", "MeshDepth"]


class CloudDepth:
    """A point z-buffer: every point is drawn as a square splat at its own depth, of world radius
    ``splat`` x its local spacing (the mean distance to its 4 nearest neighbours), so a surface
    sampled at any density renders closed; each pixel keeps the nearest splat.

    Args:
        points: (N, 3) float32 world metres.
        splat: the splat radius in units of the local spacing. A splat is drawn at its point's
            depth, so a large one in front of a slanted surface hides the points behind it; a
            small one lets occluded points through its gaps (0.4: the best labels on real depth).
        max_radius_px: splats are at most this many pixels in radius (near points).
    """

    def __init__(self, points: np.ndarray, splat: float = 0.4, max_radius_px: int = 8):
        self.points = np.ascontiguousarray(points, np.float32)
        k = min(5, len(self.points))
        if k < 2:
            raise ValueError(f"a cloud of {len(self.points)} points cannot render depth (expected at least 2)")
        d, _ = cKDTree(self.points).query(self.points, k=k, workers=-1)
        self.spacing = d[:, 1:].mean(1).astype(np.float32)  # metres
        self.median_spacing = float(np.median(self.spacing))
        self.splat, self.max_radius_px = float(splat), int(max_radius_px)

    def __call__(self, K: np.ndarray, T_cw: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        h, w = int(shape[0]), int(shape[1])
        u, v, z = project(self.points, K, T_cw)
        f = 0.5 * (K[0, 0] + K[1, 1])
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.minimum(np.rint(self.splat * self.spacing * f / z), self.max_radius_px)
        m = self.max_radius_px
        keep = np.flatnonzero((z > 1e-6) & (u > -m - 1) & (u < w + m) & (v > -m - 1) & (v < h + m))
        cols, rows = np.rint(u[keep]).astype(np.int64), np.rint(v[keep]).astype(np.int64)
        zk, rk = z[keep], r[keep].astype(np.int64)
        buf = np.full(h * w, np.inf, np.float32)
        for radius in np.unique(rk):  # loop over splat sizes (at most max_radius_px + 1), not points
            sel = np.flatnonzero(rk == radius)
            off = np.arange(-radius, radius + 1)
            dr, dc = np.meshgrid(off, off, indexing="ij")
            rr = (rows[sel, None] + dr.ravel()[None]).ravel()
            cc = (cols[sel, None] + dc.ravel()[None]).ravel()
            zz = np.repeat(zk[sel], dr.size)
            ok = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
            np.minimum.at(buf, rr[ok] * w + cc[ok], zz[ok])
        buf[~np.isfinite(buf)] = 0.0
        return buf.reshape(h, w)


class MeshDepth:
    """Depth ray-cast from a triangle mesh (open3d's Embree scene, built once)."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray):
        self.renderer = MeshRenderer(vertices, triangles, np.zeros(len(triangles), np.int16))

    @classmethod
    def from_file(cls, path: str | Path) -> "MeshDepth":
        """A triangle mesh file open3d reads (PLY, OBJ, ...); one line naming it otherwise."""
        o3d = open3d()

        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"mesh file {path} does not exist (scene.options.mesh)")
        mesh = o3d.io.read_triangle_mesh(str(path))
        if len(mesh.triangles) == 0:
            raise ValueError(f"{path}: no triangles, expected a triangle mesh for visibility=mesh")
        return cls(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.triangles, np.int64))

    def __call__(self, K: np.ndarray, T_cw: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        return self.renderer.render(K, T_cw, int(shape[1]), int(shape[0]))[0]
