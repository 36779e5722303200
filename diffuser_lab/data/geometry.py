"""Geometry helpers: projection (Eq. 2), voxel grid, normals, nearest-neighbour transfer.

Frames: world coordinates in metres; T_cw is world-to-camera (x_cam = R x + t), the
camera looks along +z with x right, y down. Pixel (col, row) has its centre at the
continuous image coordinate (u, v) = (col, row) (the OpenCV convention).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter
from scipy.spatial import cKDTree

from diffuser_lab import seeding

from .o3d import open3d


def project(points: np.ndarray, K: np.ndarray, T_cw: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 2: pi(x) = K (R x + t).

    Args:
        points: (N, 3) world coordinates, metres.
        K: (3, 3) intrinsics, pixels.
        T_cw: (4, 4) world-to-camera.
    Returns:
        u, v: (N,) float32 continuous pixel coordinates (NaN behind the camera);
        z: (N,) float32 camera-frame depth, metres.
    """
    R = np.asarray(T_cw[:3, :3], np.float32)
    t = np.asarray(T_cw[:3, 3], np.float32)
    pc = points.astype(np.float32, copy=False) @ R.T + t
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = np.where(z > 1e-6, 1.0 / z, np.nan).astype(np.float32)
    x, y = pc[:, 0] * inv_z, pc[:, 1] * inv_z
    u = K[0, 0] * x + K[0, 1] * y + K[0, 2]
    v = K[1, 1] * y + K[1, 2]
    return u.astype(np.float32), v.astype(np.float32), z


def backproject(depth: np.ndarray, K: np.ndarray, T_cw: np.ndarray, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Depth image -> world points of its valid pixels.

    Args:
        depth: (H, W) z-depth in metres, 0 = invalid.
        K: (3, 3) intrinsics; T_cw: (4, 4) world-to-camera.
        stride: take every stride-th pixel in both directions.
    Returns:
        points: (M, 3) float32 world coordinates; pix: (M, 2) int64 (row, col) of each point.
    """
    rows, cols = np.mgrid[0 : depth.shape[0] : stride, 0 : depth.shape[1] : stride]
    d = depth[rows, cols]
    ok = np.isfinite(d) & (d > 0)
    rows, cols, d = rows[ok], cols[ok], d[ok].astype(np.float64)
    Kinv = np.linalg.inv(K)
    rays = np.stack([cols, rows, np.ones_like(cols)], 1).astype(np.float64) @ Kinv.T
    pc = rays * d[:, None]
    T_wc = np.linalg.inv(T_cw)
    pw = pc @ T_wc[:3, :3].T + T_wc[:3, 3]
    return pw.astype(np.float32), np.stack([rows, cols], 1)


def scaled_intrinsics(K: np.ndarray, src_shape: tuple[int, int], dst_shape: tuple[int, int]) -> np.ndarray:
    """(3, 3) K of an image of (H, W) ``src_shape`` resized to ``dst_shape`` with pixel centres
    aligned (pixel centre at integer coordinates): f' = f s, c' = (c + 0.5) s - 0.5 per axis."""
    sy, sx = dst_shape[0] / src_shape[0], dst_shape[1] / src_shape[1]
    out = np.array(K, np.float64)
    out[0, 0], out[0, 1] = K[0, 0] * sx, K[0, 1] * sx
    out[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    out[1, 1] = K[1, 1] * sy
    out[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return out


def visible_projection(points: np.ndarray, frame, depth_tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points of ``frame`` (a :class:`~diffuser_lab.data.scene.Frame`: K, T_cw, depth) that project inside the image and pass the depth check.

    Returns:
        idx: (M,) int64 indices into ``points``; rows, cols: (M,) int64 pixel of each.
    """
    h, w = frame.depth.shape[:2]
    u, v, z = project(points, frame.K, frame.T_cw)
    cols = np.rint(u)
    rows = np.rint(v)
    inside = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)  # NaN (behind camera) -> False
    idx = np.flatnonzero(inside)
    rows = rows[idx].astype(np.int64)
    cols = cols[idx].astype(np.int64)
    d = frame.depth[rows, cols]
    ok = (d > 0) & (np.abs(z[idx] - d) <= depth_tol)
    return idx[ok], rows[ok], cols[ok]


@dataclass
class VoxelGrid:
    """Voxel downsampling with the map back to the original points.

    Attributes:
        points: (M, 3) float32 centroid of the original points in each occupied voxel, metres.
        inverse: (N,) int64 voxel index of every original point.
    """

    points: np.ndarray
    inverse: np.ndarray

    def mean(self, values: np.ndarray) -> np.ndarray:
        """(N, D) per-point values -> (M, D) float32 per-voxel means."""
        m = self.points.shape[0]
        counts = np.bincount(self.inverse, minlength=m).astype(np.float64)
        cols = [np.bincount(self.inverse, weights=values[:, j], minlength=m) for j in range(values.shape[1])]
        return (np.stack(cols, 1) / counts[:, None]).astype(np.float32)


def voxel_downsample(points: np.ndarray, voxel_size: float) -> VoxelGrid:
    """Group (N, 3) world points into cubes of ``voxel_size`` metres; one centroid per cube."""
    keys = np.floor((points - points.min(0)) / voxel_size).astype(np.int64)
    dims = keys.max(0) + 1
    flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
    _, inverse = np.unique(flat, return_inverse=True)
    grid = VoxelGrid(points=np.zeros((0, 3), np.float32), inverse=inverse.ravel())
    grid.points = np.zeros((int(inverse.max()) + 1, 3), np.float32)
    grid.points = grid.mean(points)
    return grid


# scene.voxel_size=auto: the voxel edge in rho, the raw cloud's mean spacing. 2.7 rho was better than
# or equal to each scene's hand-set edge (3 seeds): scene0470 (rho 13 mm -> 3.6 cm, +4.5 mIoU), the
# real scene0014 frames (15 mm -> 4.0 cm, +0.2) and the city (10 cm -> 27 cm, +2.4); results/defaults.md
VOXEL_RHO = 2.7


def point_spacing(points: np.ndarray, sample: int = 100_000, seed: int = 0) -> float:
    """rho of (N, 3) points, metres: the mean distance to the nearest distinct neighbour (duplicates
    skipped) over a random ``sample`` of the points (all of them when N <= sample), each looked up
    among all N. The graph's rho (method/graph.py) over every point agrees to ~1% at 100k."""
    n = len(points)
    if n < 2:
        raise ValueError(f"the point spacing needs at least 2 points (got {n})")
    q = points if n <= sample else points[seeding.keyed("geometry.spacing", seed).choice(n, sample, replace=False)]
    tree = cKDTree(points)
    k = min(8, n)
    d, _ = tree.query(q, k=k, workers=-1)  # (S, k): the first of them is the point itself
    d = np.where(d > 0, d, np.inf).min(1)  # nearest distinct neighbour (duplicates skipped)
    d = d[np.isfinite(d)]
    if d.size == 0:
        raise ValueError("all points coincide: the point spacing rho is 0")
    return float(d.mean())


def voxel_edge(value, points: np.ndarray) -> float:
    """A voxel-edge setting (``scene.voxel_size``) in metres: a number as given (0 = off), or
    ``"auto"``: :data:`VOXEL_RHO` x :func:`point_spacing` of the (N, 3) ``points``."""
    if isinstance(value, str):
        if value != "auto":
            raise ValueError(f"voxel size {value!r}: expected metres (a number >= 0) or 'auto'")
        return VOXEL_RHO * point_spacing(points)
    if not value >= 0:
        raise ValueError(f"voxel size {value!r}: expected metres (a number >= 0) or 'auto'")
    return float(value)


def nearest_transfer(src_points: np.ndarray, src_values: np.ndarray, dst_points: np.ndarray) -> np.ndarray:
    """Give every (N, 3) ``dst_points`` the value of its nearest ``src_points`` (paper: the
    labels of the 2 cm-downsampled cloud go back to every original point)."""
    _, idx = cKDTree(src_points).query(dst_points, k=1, workers=-1)
    return src_values[idx]


def estimate_normals(points: np.ndarray, knn: int = 16) -> np.ndarray:
    """(N, 3) points -> (N, 3) float32 unit normals by local PCA (open3d); sign arbitrary."""
    o3d = open3d()

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=knn))
    return np.asarray(pcd.normals, dtype=np.float32)


def box_smoothed_depth(depth: np.ndarray, window: int) -> np.ndarray:
    """(H, W) depth averaged over the valid (> 0) pixels of each ``window`` x ``window`` box, 0 where
    the pixel itself has no depth (float64 for float64 input, else float32)."""
    d = np.asarray(depth)
    d = d if d.dtype == np.float64 else d.astype(np.float32)
    ok = (d > 0).astype(d.dtype)
    cnt = uniform_filter(ok, window, mode="constant")
    return np.where(ok > 0, uniform_filter(d * ok, window, mode="constant") / np.maximum(cnt, 1e-12), 0.0)


def normals_from_depth(depth: np.ndarray, K: np.ndarray, pix: np.ndarray | None = None,
                       T_cw: np.ndarray | None = None, window: int = 1) -> np.ndarray:
    """Unit surface normals of an organised depth image: the one depth-image normals function.

    Central differences of the back-projected points along rows and columns (one-sided where a
    neighbour has no depth; zero where a pixel has no valid neighbour on either axis), in float64.

    Args:
        depth: (H, W) metres, 0 = no depth; K: (3, 3) its intrinsics, pixels.
        pix: (P, 2) int (row, col) pixels to compute the normals at; None: every pixel.
        T_cw: (4, 4) world-to-camera; given, the normals are turned towards the camera (it looks
            along +z) and into the world frame.
        window: > 1: the depth is first box-averaged over ``window`` x ``window`` valid pixels
            (:func:`box_smoothed_depth`; sensor noise is per pixel).
    Returns:
        (H, W, 3) (pix None) or (P, 3) float64 unit normals, camera frame (world frame with
        ``T_cw``), zero where unknown.
    """
    d = box_smoothed_depth(depth, window) if window > 1 else depth
    d = np.asarray(d, np.float64)
    h, w = d.shape
    if pix is None:
        r, c = np.mgrid[0:h, 0:w]
    else:
        r, c = np.asarray(pix[:, 0], np.int64), np.asarray(pix[:, 1], np.int64)
    K = np.asarray(K, np.float64)

    def point(rr, cc):  # camera-frame point at (rr, cc) and whether it has depth (inside the image)
        inside = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
        rr, cc = np.clip(rr, 0, h - 1), np.clip(cc, 0, w - 1)
        z = d[rr, cc]
        P = np.stack([(cc - K[0, 2]) / K[0, 0] * z, (rr - K[1, 2]) / K[1, 1] * z, z], -1)
        return P, inside & (z > 0)

    P0, ok0 = point(r, c)

    def diff(dr: int, dc: int) -> np.ndarray:
        Pf, okf = point(r + dr, c + dc)
        Pb, okb = point(r - dr, c - dc)
        okf &= ok0
        okb &= ok0
        fwd, bwd = Pf - P0, P0 - Pb
        g = np.where((okf & okb)[..., None], 0.5 * (fwd + bwd), np.where(okf[..., None], fwd, bwd))
        return np.where((okf | okb)[..., None], g, 0.0)

    n = np.cross(diff(0, 1), diff(1, 0))
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(norm > 0, n / np.maximum(norm, 1e-30), 0.0)
    if T_cw is None:
        return n
    n *= np.where(n[..., 2:3] > 0, -1.0, 1.0)  # towards the camera
    return n @ np.asarray(T_cw, np.float64)[:3, :3]  # (R_cw^T n)^T: into the world frame
