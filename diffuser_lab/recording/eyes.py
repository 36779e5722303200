"""Where run.rrd's 3D views open: a top-down oblique eye over the scene (:func:`overview_eye`)
and an eye that rides the online run's moving camera (:func:`follow_eye`).

Without an eye in the blueprint Rerun opens a 3D view from outside the scene's bounding box, at
about the height of its centre: in a room the walls' backs hide the whole interior (issue 28).
Looking down at ~55 degrees from above one side shows the floor and what stands on it, the walls
as thin rims; in a city, the streets between the blocks.
"""
from __future__ import annotations

from typing import Any, Optional

import numpy as np

FOV_Y_DEG = 55.0
"""The vertical field of view of Rerun's 3D eye (re_view_spatial's default), degrees."""
ELEVATION_DEG = 55.0
"""The overview eye's angle above the horizontal plane, seen from the look target, degrees."""
AZIMUTH_DEG = 30.0
"""The overview eye's side: from -y (the scene's 'south'), turned this far towards -x, degrees."""
MAX_SAMPLE = 200_000
"""The most points the extent is estimated from (every n-th point beyond)."""


def camera_poses(frames: Any) -> np.ndarray:
    """(F, 4, 4) float64 world->camera transforms of ``frames``: an (F, 4, 4) array, or a sequence
    of (4, 4) arrays or of objects with ``T_cw`` (each is read: a lazy sequence loads its frames)."""
    if frames is None:
        return np.zeros((0, 4, 4))
    if isinstance(frames, np.ndarray):
        return np.asarray(frames, np.float64).reshape(-1, 4, 4)
    return np.asarray([getattr(f, "T_cw", f) for f in frames], np.float64).reshape(-1, 4, 4)


def scene_up(T_cw: Optional[np.ndarray] = None, min_agreement: float = 0.5) -> np.ndarray:
    """(3,) unit up vector of the world, from the cameras' up (``-y`` of an OpenCV camera, in world:
    ``-R_cw[1, :]``) where they agree (the norm of their mean of unit vectors > ``min_agreement``),
    else +z (the scenes here are z-up; a COLMAP or nerfstudio capture may not be).

    Args:
        T_cw: (F, 4, 4) world->camera transforms (OpenCV camera axes: x right, y down, z forward), or None.
    """
    z = np.array([0.0, 0.0, 1.0])
    if T_cw is None or len(T_cw) == 0:
        return z
    ups = -np.asarray(T_cw, np.float64)[:, 1, :3]  # row 1 of R_cw = the camera's y axis in world
    mean = ups.mean(0)
    n = float(np.linalg.norm(mean))
    return mean / n if n > min_agreement else z


def _basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (east, north) spanning the plane normal to ``up``: x and y of the world
    projected onto it (x, y themselves for z-up)."""
    ref = np.eye(3)
    east = ref[0] - ref[0] @ up * up
    if np.linalg.norm(east) < 1e-6:  # up is +-x: y is horizontal
        east = ref[1] - ref[1] @ up * up
    east /= np.linalg.norm(east)
    return east, np.cross(up, east)


def overview_geometry(points: Optional[np.ndarray], T_cw: Optional[np.ndarray] = None, *,
                      elevation_deg: float = ELEVATION_DEG, azimuth_deg: float = AZIMUTH_DEG,
                      fov_y_deg: float = FOV_Y_DEG, margin: float = 1.05
                      ) -> Optional[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(position, look_target, up), each (3,) float64 in world units (metres), of a top-down oblique
    eye over ``points`` (N, 3) world (or the camera centres of ``T_cw`` (F, 4, 4) world->camera where
    there are no points); None when neither gives a position.

    The look target is the centre of the box between the 2nd and 98th percentiles of each world axis
    (stray points do not move it); the eye looks down at it ``elevation_deg`` above the plane normal
    to up (:func:`scene_up`), from the side ``azimuth_deg`` off -y, just far enough back that the
    box's eight corners fit a square view of ``fov_y_deg`` (times ``margin``)."""
    T = None if T_cw is None else np.asarray(T_cw, np.float64).reshape(-1, 4, 4)
    pts = np.zeros((0, 3)) if points is None else np.asarray(points).reshape(-1, 3)
    if len(pts) == 0 and T is not None and len(T):
        # camera centres C = -R^T t (the extent of a map still to be built)
        pts = -np.einsum("fji,fj->fi", T[:, :3, :3], T[:, :3, 3])
    pts = pts[np.isfinite(pts).all(1)] if len(pts) else pts
    if len(pts) == 0:
        return None
    sample = pts[:: max(1, len(pts) // MAX_SAMPLE)].astype(np.float64)
    lo, hi = np.percentile(sample, [2.0, 98.0], axis=0)
    target = 0.5 * (lo + hi)
    up = scene_up(T)
    east, north = _basis(up)
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    back = np.cos(el) * (-np.cos(az) * north - np.sin(az) * east) + np.sin(el) * up  # target -> eye, unit
    fwd = -back
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, fwd)
    # the eight corners in the eye's frame (right, up, forward), relative to the target
    corners = lo + (hi - lo) * np.array(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij")).reshape(3, -1).T
    rel = corners - target
    x, y, zf = rel @ right, rel @ cam_up, rel @ fwd
    tan_half = np.tan(0.5 * np.radians(fov_y_deg)) / margin
    # a corner at depth d + zf is in view when |x|, |y| <= (d + zf) tan_half
    dist = float(max(np.max(np.maximum(np.abs(x), np.abs(y)) / tan_half - zf), 1e-2))
    return target + dist * back, target, up


def overview_eye(points: Optional[np.ndarray], frames: Any = None, **kw):
    """A ``rrb.EyeControls3D`` (orbital) looking down at the scene from above one side, at ~55
    degrees, its whole extent in view: see :func:`overview_geometry` (``points`` (N, 3) world metres;
    ``frames``: what :func:`camera_poses` takes, for the up direction and, without points, the
    extent). None (Rerun's own eye) when there is nothing to frame."""
    import rerun.blueprint as rrb

    geo = overview_geometry(points, camera_poses(frames) if frames is not None else None, **kw)
    if geo is None:
        return None
    pos, target, up = geo
    return rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=pos, look_target=target, eye_up=up)


def follow_eye(entity: str):
    """A ``rrb.EyeControls3D`` tracking ``entity``: a camera (Transform3D + Pinhole) is looked
    through, its pose and field of view taken over at every time (Rerun 0.41)."""
    import rerun.blueprint as rrb

    return rrb.EyeControls3D(tracking_entity=entity)


def eye_kw(eye) -> dict:
    """``{"eye_controls": eye}`` for a ``rrb.Spatial3DView``, or {} (Rerun's own eye)."""
    return {} if eye is None else {"eye_controls": eye}


__all__ = ["overview_eye", "overview_geometry", "follow_eye", "scene_up", "camera_poses", "eye_kw",
           "FOV_Y_DEG", "ELEVATION_DEG"]
