"""The points a run labels: the scene's cloud or its voxel grid (the work cloud), and the way back
to the scene's points; what the global, online and tiled runs share of it."""
from __future__ import annotations

from typing import Optional

import numpy as np

from diffuser_lab import progress
from diffuser_lab.backends import resolve_backend
from diffuser_lab.config import SolverName, SparseClasses
from diffuser_lab.data.geometry import VoxelGrid, nearest_transfer, voxel_downsample, voxel_edge
from diffuser_lab.data.scene import Scene
from diffuser_lab.method.diffusion import sparse_by_size

__all__ = ["work_cloud", "to_original", "work_colors", "sparse_classes"]


def work_cloud(scene: Scene, voxel_size) -> tuple[np.ndarray, Optional[np.ndarray], Optional[VoxelGrid]]:
    """The points the graph is built on, their normals and the voxel grid (None: the scene's points):
    ``scene.voxel_size`` (metres, 0 = off, or ``auto``: :func:`~diffuser_lab.data.geometry.voxel_edge`)
    applied to the scene's points."""
    voxel_size = voxel_edge(voxel_size, scene.points)
    if voxel_size <= 0:
        return scene.points, scene.normals, None
    with progress.stage(f"voxel grid ({voxel_size:g} m, {scene.n_points:,} points)"):
        grid = voxel_downsample(scene.points, voxel_size)
        normals = None
        if scene.normals is not None:
            n = grid.mean(scene.normals)
            normals = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return grid.points, normals, grid


def to_original(scene: Scene, grid: Optional[VoxelGrid], work_labels: np.ndarray) -> np.ndarray:
    """Per point of the scene, the value of its work point (``work_labels`` (M,): labels, or
    ``np.arange(M)`` for each point's work point)."""
    if grid is None:
        return work_labels
    return nearest_transfer(grid.points, work_labels, scene.points)


def work_colors(scene: Scene, grid: Optional[VoxelGrid]) -> Optional[np.ndarray]:
    """(M, 3) the work points' colours (a voxel's mean; [0, 1] float or the scene's uint8), None without."""
    if scene.colors is None:
        return None
    if grid is None:
        return scene.colors
    return grid.mean(np.asarray(scene.colors, np.float32) / (255.0 if scene.colors.dtype == np.uint8 else 1.0))


def sparse_classes(solver, n_work: int, num_classes: int) -> int:
    """The per-point class count the diffusion will use (0 = dense), for the memory check:
    ``solver.sparse_classes`` on / off, or auto's size rule (diffusion.sparse_by_size)."""
    if solver.name != SolverName.jacobi or solver.sparse_classes == SparseClasses.off:
        return 0
    numba = resolve_backend(solver.backend) == "numba"
    if solver.sparse_classes == SparseClasses.on or (numba and sparse_by_size(n_work, num_classes)):
        return int(solver.classes_per_point)
    return 0
