"""Camera poses and trajectories shared by the capture formats: rigid (4, 4) transforms, the pose
file reader and its rigidity check, the camera-to-world / world-to-camera conventions, and the
association of time stamps (nearest within a tolerance) that TUM lists and ROS bags use."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from diffuser_lab.data.intrinsics import read_matrix_file

__all__ = ["CAMERA_TO_WORLD", "WORLD_TO_CAMERA", "rigid_inverse", "read_pose_c2w", "check_rigid",
           "pose_to_world_to_camera", "associate"]

CAMERA_TO_WORLD, WORLD_TO_CAMERA = "camera_to_world", "world_to_camera"  # pose file conventions


def rigid_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a (4, 4) rigid transform (R^T, -R^T t), float64."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def read_pose_c2w(path: str | Path, tol: float = 1e-3, convention: str = CAMERA_TO_WORLD) -> np.ndarray | None:
    """4x4 pose file -> (4, 4) float64 as stored, or None when it has non-finite
    entries (ScanNet marks failed tracking with -inf poses; the caller skips those).
    ``convention`` only words the errors; :func:`pose_to_world_to_camera` applies it.

    Raises:
        ValueError: not 4x4, or finite but not a rigid transform (R^T R != I within ``tol``,
            det R != 1, last row != 0 0 0 1), naming the file.
    """
    path = Path(path)
    T = read_matrix_file(path, "pose")
    if T.shape != (4, 4):
        raise ValueError(f"{path}: pose of shape {T.shape}, expected a 4x4 {convention.replace('_', '-')} matrix")
    if not np.isfinite(T).all():
        return None
    check_rigid(T, str(path), convention, tol)
    return T


def check_rigid(T: np.ndarray, where: str, convention: str = CAMERA_TO_WORLD, tol: float = 1e-3) -> None:
    """A finite (4, 4) pose must be rigid: R^T R = I and det R = 1 within ``tol``, last row 0 0 0 1;
    else one ValueError starting with ``where`` (the file, and the field when it has several)."""
    R = T[:3, :3]
    ortho = np.abs(R.T @ R - np.eye(3)).max()
    det = np.linalg.det(R)
    if ortho > tol or abs(det - 1.0) > tol or np.abs(T[3] - [0, 0, 0, 1]).max() > tol:
        raise ValueError(f"{where}: pose is not a rigid transform (max|R^T R - I| = {ortho:.2g}, det R = {det:.4g}, "
                         f"last row {T[3].tolist()}), expected 4x4 {convention.replace('_', '-')} rotation + translation")


def pose_to_world_to_camera(T: np.ndarray, convention: str) -> np.ndarray:
    """A stored (4, 4) rigid pose in ``convention`` (camera_to_world | world_to_camera) -> T_cw."""
    if convention == CAMERA_TO_WORLD:
        return rigid_inverse(T)
    if convention == WORLD_TO_CAMERA:
        return np.array(T, np.float64)
    raise ValueError(f"pose convention {convention!r}: expected {CAMERA_TO_WORLD} or {WORLD_TO_CAMERA}")


def _nearest(t: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each of the (N,) times ``t``: index of the nearest of the sorted (M,) ``ref``, |difference|."""
    j = np.clip(np.searchsorted(ref, t), 1, len(ref) - 1) if len(ref) > 1 else np.zeros(len(t), np.int64)
    if len(ref) > 1:
        j = np.where(np.abs(ref[j - 1] - t) <= np.abs(ref[j] - t), j - 1, j)
    return j, np.abs(ref[j] - t)


def associate(t: np.ndarray, ref: np.ndarray, max_diff: float, one_to_one: bool = True) -> np.ndarray:
    """(N,) int64 index into sorted ``ref`` of each time in ``t``'s nearest, -1 when farther than
    ``max_diff`` seconds; ``one_to_one``: a ``ref`` entry claimed by several keeps only the nearest."""
    j, d = _nearest(np.asarray(t, np.float64), np.asarray(ref, np.float64))
    ok = d <= max_diff
    if one_to_one and ok.any():
        cand = np.flatnonzero(ok)
        order = cand[np.lexsort((d[cand], j[cand]))]  # by ref index, then by distance
        first = np.ones(len(order), bool)
        first[1:] = j[order[1:]] != j[order[:-1]]
        ok[:] = False
        ok[order[first]] = True
    return np.where(ok, j, -1)
