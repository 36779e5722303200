"""Checks of a scene and its frames that every source shares, with one-line messages.

Errors (ValueError) stop the run; warnings (``warnings.warn``) say what looks wrong and which
option fixes it. Frames are checked as they stream through the pipeline, so lazy sequences
are never loaded twice.
"""
from __future__ import annotations

import math
import warnings

import numpy as np

from .scene import Frame, Scene

GIB = 1024**3


def check_points(scene: Scene) -> None:
    """Non-empty, finite (N, 3) points; normals, labels and colours of matching length."""
    p = scene.points
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"scene {scene.name}: points of shape {p.shape}, expected (N, 3) metres")
    if p.shape[0] == 0:
        raise ValueError(f"scene {scene.name}: the point cloud is empty")
    bad = ~np.isfinite(p).all(1)
    if bad.any():
        raise ValueError(f"scene {scene.name}: {int(bad.sum())} of {p.shape[0]} points have NaN or infinite "
                         f"coordinates (first at index {int(np.flatnonzero(bad)[0])})")
    for what in ("normals", "gt_labels", "colors"):
        a = getattr(scene, what)
        if a is not None and a.shape[0] != p.shape[0]:
            raise ValueError(f"scene {scene.name}: {a.shape[0]} {what} for {p.shape[0]} points")
    if scene.normals is not None and not np.isfinite(scene.normals).all():
        raise ValueError(f"scene {scene.name}: normals contain NaN or infinite values")


def check_frame(f: Frame) -> None:
    """Intrinsics that fit the image, a finite rigid world-to-camera pose, a 2D depth map."""
    if f.depth.ndim != 2:
        raise ValueError(f"frame {f.name}: depth of shape {f.depth.shape}, expected (H, W) metres")
    h, w = f.depth.shape
    K = np.asarray(f.K, float)
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"frame {f.name}: intrinsics {K.tolist()} need a finite 3x3 K with fx, fy > 0")
    if not (-0.5 <= K[0, 2] <= w - 0.5 and -0.5 <= K[1, 2] <= h - 0.5):
        raise ValueError(f"frame {f.name}: principal point ({K[0, 2]:.1f}, {K[1, 2]:.1f}) lies outside the "
                         f"{w}x{h} image: intrinsics of another resolution?")
    T = np.asarray(f.T_cw, float)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"frame {f.name}: pose must be a finite 4x4 world-to-camera transform")
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-3 or abs(np.linalg.det(R) - 1) > 1e-3 or \
            np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-6:
        raise ValueError(f"frame {f.name}: pose is not a rigid transform (R^T R != I, det R != 1 or last row "
                         f"!= 0 0 0 1)")


def camera_centre(f: Frame) -> np.ndarray:
    """World position of the camera, metres."""
    T = np.asarray(f.T_cw, float)
    return -T[:3, :3].T @ T[:3, 3]


def check_depth_unit(f: Frame, hint: str = "the source's depth scale") -> None:
    """Warn when the frame's median valid depth is beyond 20 m or under 5 cm."""
    d = f.depth[f.depth > 0]
    if d.size:
        med = float(np.median(d))
        if med > 20 or med < 0.05:
            warnings.warn(f"frame {f.name}: median depth {med:.3g} m looks like a wrong unit; check {hint}",
                          stacklevel=2)


def check_pose_convention(points: np.ndarray, centres: np.ndarray, inverted_centres: np.ndarray) -> None:
    """Warn when most cameras sit far outside the cloud but the inverted poses would put them inside:
    a camera-to-world pose given where world-to-camera was expected (or the reverse)."""
    if len(centres) == 0:
        return
    lo, hi = points.min(0) - 1.0, points.max(0) + 1.0
    inside = lambda c: np.mean(np.all((c >= lo) & (c <= hi), axis=1))  # noqa: E731
    if inside(centres) < 0.5 and inside(inverted_centres) >= 0.8:
        warnings.warn(f"{100 * (1 - inside(centres)):.0f}% of the cameras lie more than 1 m outside the point "
                      f"cloud, but the inverted poses would put {100 * inside(inverted_centres):.0f}% inside: the "
                      f"poses look like the inverse convention (camera-to-world vs world-to-camera)", stacklevel=2)


def estimate_memory(n_points: int, n_work: int, num_classes: int, k: int, sparse_classes: int = 0) -> int:
    """Rough peak bytes of a run: kNN query (float64 distances, int64 indices for K+1 columns),
    graph and transition matrix, the N x C score matrices and the original cloud's arrays.

    Dense Jacobi holds 8 N x C float32 matrices (evidence, baseline evidence, B, B in the
    iteration's order, the class blocks' B, Z and Z_new, the final Z); with ``sparse_classes`` M > 0
    (:mod:`diffuser_lab.backends.sparse`) the last state and the iteration are two sparse states
    of N x (2M + 5) x 4 bytes plus B as CSR, so 5 dense matrices remain."""
    knn = n_work * (k + 1) * 16
    graph = n_work * k * (4 + 4 + 4 + 4)
    if sparse_classes:
        scores = n_work * num_classes * 4 * 5 + 2 * n_work * (2 * sparse_classes + 5) * 4 + n_work * 8 * 4
    else:
        scores = n_work * num_classes * 4 * 8
    cloud = n_points * (12 * 3 + 8) + n_work * 64
    return int(knn + graph + scores + cloud)


def check_memory(n_points: int, n_work: int, num_classes: int, k: int, budget_gb: float,
                 sparse_classes: int = 0) -> None:
    """Refuse a run whose :func:`estimate_memory` exceeds ``budget_gb`` GiB, up front, with the estimate
    and the keys that make it fit (the budget, a voxel grid, tiles: ``protocol=tiled tiling.size``,
    about as many tiles as the estimate is over the budget, each with its halo)."""
    need = estimate_memory(n_points, n_work, num_classes, k, sparse_classes)
    if need > budget_gb * GIB:
        layout = f"sparse class set of {sparse_classes}" if sparse_classes else "dense scores"
        hint = "" if sparse_classes or num_classes <= 32 else \
            ", solver.sparse_classes=on (keeps solver.classes_per_point classes per point)"
        raise MemoryError(f"this run needs about {need / GIB:.1f} GiB ({n_points:,} points, {n_work:,} diffused, "
                          f"K={k}, {num_classes} classes, {layout}) > memory_budget_gb={budget_gb:g}; raise the "
                          f"budget{hint}, set scene.voxel_size to diffuse fewer points, or diffuse it in tiles: "
                          f"protocol=tiled tiling.size=<metres> (at least {math.ceil(need / (budget_gb * GIB)) + 1} "
                          f"tiles; docs/tiling.md)")
