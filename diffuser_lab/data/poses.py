"""Camera poses and trajectories shared by the capture formats: rigid (4, 4) transforms, the pose
file reader and its rigidity check, the camera-to-world / world-to-camera conventions, the
association of time stamps (nearest within a tolerance) that pairs the images of TUM lists and ROS
bags, and the one trajectory rule both use for poses: :func:`interpolate_poses`."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from diffuser_lab.data.intrinsics import read_matrix_file

__all__ = ["CAMERA_TO_WORLD", "WORLD_TO_CAMERA", "rigid_inverse", "read_pose_c2w", "check_rigid",
           "pose_to_world_to_camera", "associate", "pose_matrices", "interpolate_poses"]

CAMERA_TO_WORLD, WORLD_TO_CAMERA = "camera_to_world", "world_to_camera"  # pose file conventions


def rigid_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a (4, 4) rigid transform, or of each of (N, 4, 4): (R^T, -R^T t), float64."""
    T = np.asarray(T, np.float64)
    R_t = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = R_t
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", R_t, T[..., :3, 3])
    out[..., 3, 3] = 1.0
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
    T = read_matrix_file(path, "pose", role="frames")
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


def pose_matrices(trans: np.ndarray, quats: np.ndarray) -> np.ndarray:
    """(N, 3) translations, (N, 4) quaternions ``qx qy qz qw`` (scalar last; normalised here) ->
    (N, 4, 4) float64 rigid transforms."""
    from scipy.spatial.transform import Rotation

    T = np.tile(np.eye(4), (len(trans), 1, 1))
    if len(trans):
        T[:, :3, :3] = Rotation.from_quat(quats).as_matrix()
        T[:, :3, 3] = trans
    return T


def interpolate_poses(stamps: np.ndarray, trans: np.ndarray, quats: np.ndarray, at: np.ndarray, tol: float,
                      interpolate: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Poses of a sampled trajectory at other times: the one trajectory rule of every source.

    A time between two samples both within ``tol`` gets the pose between them: translation linear,
    rotation slerp (the shorter arc), by the time's fraction of the gap. A time with only one sample
    within ``tol`` (outside the trajectory, or beside a gap in it) gets that nearest sample; a time
    with none is not valid (the caller drops the frame).

    Args:
        stamps: (M,) sorted sample times, any unit (int64 nanoseconds or float64 seconds).
        trans: (M, 3) metres. quats: (M, 4) ``qx qy qz qw``, unit.
        at: (N,) times, the unit of ``stamps``. tol: the largest time difference, same unit.
        interpolate: False: always the nearest sample within ``tol``.
    Returns:
        (N, 4, 4) float64 transforms (the samples' frame convention) and (N,) bool: a sample lay
        within ``tol``.
    """
    from scipy.spatial.transform import Rotation

    stamps, at = np.asarray(stamps), np.asarray(at, np.asarray(stamps).dtype)
    m = len(stamps)
    if m == 0 or len(at) == 0:
        return np.tile(np.eye(4), (len(at), 1, 1)), np.zeros(len(at), bool)
    jr = np.clip(np.searchsorted(stamps, at), 0, m - 1)
    jl = np.where(stamps[jr] == at, jr, np.clip(jr - 1, 0, m - 1))
    dl, dr = np.abs(at - stamps[jl]), np.abs(at - stamps[jr])
    ok = np.minimum(dl, dr) <= tol
    near = np.where(dl <= dr, jl, jr)
    both = interpolate & (jl != jr) & (stamps[jl] <= at) & (at <= stamps[jr]) & (dl <= tol) & (dr <= tol)
    gap = (stamps[jr] - stamps[jl]).astype(np.float64)
    a = np.where(both, (at - stamps[jl]) / np.where(both, gap, 1.0), 0.0)
    i0, i1 = np.where(both, jl, near), np.where(both, jr, near)
    t = (1 - a)[:, None] * trans[i0] + a[:, None] * trans[i1]
    r0 = Rotation.from_quat(quats[i0])
    step = (r0.inv() * Rotation.from_quat(quats[i1])).as_rotvec()  # the shorter arc, |angle| <= pi
    T = pose_matrices(t, (r0 * Rotation.from_rotvec(a[:, None] * step)).as_quat())
    return T, ok
