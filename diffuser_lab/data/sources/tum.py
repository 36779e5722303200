"""TUM RGB-D benchmark sequences (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats).

Layout of ``root`` (``rgbd_dataset_freiburg1_xyz/`` after unpacking the .tgz)::

    rgb.txt            '# comment' lines, then 'timestamp rgb/<timestamp>.png' (640x480 8-bit RGB)
    depth.txt          'timestamp depth/<timestamp>.png' (640x480 16-bit, 5000 units per metre, 0 = none)
    groundtruth.txt    'timestamp tx ty tz qx qy qz qw': position and unit-quaternion orientation of the
                       colour camera's optical centre in the world (camera-to-world), metres

The three streams run on their own clocks (RGB and depth at 30 Hz, the motion capture at 100 Hz).
A frame is a depth image; it is kept when an RGB image and a ground-truth pose lie within
``max_time_diff`` seconds of it (TUM's ``associate.py`` uses 0.02 s); each RGB image serves at most one
frame (the nearest), as ``associate.py`` pairs them one-to-one. The pose is the trajectory at the depth
image's time (:func:`~diffuser_lab.data.poses.interpolate_poses`, as for ROS bags): between the two
samples around it when both lie within ``max_time_diff``, else the nearest sample. Frames are named after the RGB image's
file stem (the name a 2D network's output usually carries), or the depth's without colour.

Depth is registered to the colour camera, so one K serves both; TUM's calibration page gives per-camera
values (``TUM_CAMERAS``; the fr1/fr2 images are not undistorted, which this loader ignores). The cloud
to label is the depth back-projected and voxel-merged as for a posed RGB-D folder.
"""
from __future__ import annotations

import re
import warnings
from pathlib import Path
from dataclasses import dataclass
from enum import Enum
from typing import Optional

import numpy as np
from omegaconf import MISSING

from diffuser_lab.config import SceneConfig, Section, above, at_least, check, key
from diffuser_lab.data import inputs
from diffuser_lab.data.capture import fuse_depth
from diffuser_lab.data.frames import LazyFrames
from diffuser_lab.data.images import read_depth, read_rgb
from diffuser_lab.data.poses import associate, interpolate_poses, pose_matrices, rigid_inverse
from diffuser_lab.data.scene import SCANNET20, Frame, Scene, Taxonomy
from diffuser_lab.data.sensor import SensorModel
from diffuser_lab.data.validate import check_depth_unit

__all__ = ["TumOptions", "TumCamera", "load_tum", "read_tum_list", "read_tum_samples", "read_tum_trajectory", "TUM_CAMERAS",
           "load"]


class TumCamera(Enum):
    """Intrinsics presets of the TUM RGB-D benchmark's calibration page (colour camera, to which the
    depth images are registered): fx fy cx cy in pixels at 640x480."""

    auto = "auto"  # freiburg1/2/3 from the root folder's name (rgbd_dataset_freiburg1_xyz), else ros_default
    fr1 = "fr1"  # 517.3 516.5 318.6 255.3
    fr2 = "fr2"  # 520.9 521.0 325.1 249.7
    fr3 = "fr3"  # 535.4 539.2 320.1 247.6
    ros_default = "ros_default"  # 525.0 525.0 319.5 239.5 (OpenNI's default, TUM's point-cloud example)


@dataclass
class TumOptions(Section):
    """A TUM RGB-D sequence (diffuser_lab.data.sources.tum): rgb.txt, depth.txt, groundtruth.txt with
    timestamps: RGB by nearest timestamp, the pose interpolated at the depth image's time; frames named
    after their RGB image's stem."""

    KEY = "scene.options"
    root: str = MISSING  # the sequence folder (rgbd_dataset_freiburg1_xyz)
    rgb_list: Optional[str] = "rgb.txt"  # 'timestamp file' lines; null = no colour
    depth_list: str = "depth.txt"  # 'timestamp file' lines; the frames
    groundtruth: str = "groundtruth.txt"  # 'timestamp tx ty tz qx qy qz qw', camera-to-world
    max_time_diff: float = key(0.02, above(0, "seconds"))  # seconds: the nearest RGB image and the pose samples used must lie within it (associate.py), else the frame is dropped; the pose is interpolated between the samples around the depth image
    depth_scale: float = key(5000.0, above(0))  # raw units per metre (TUM: 5000)
    camera: TumCamera = TumCamera.auto
    fx: Optional[float] = None  # pixels; set all four to override the camera preset
    fy: Optional[float] = None
    cx: Optional[float] = None
    cy: Optional[float] = None
    cloud_voxel: float = key(0.02, above(0, "metres"))  # metres, for the back-projected cloud
    cloud_stride: int = key(4, at_least(1))
    max_depth: Optional[float] = key(None, above(0, "metres", null=True))  # ignore depth beyond it in the cloud
    frame_step: int = key(1, at_least(1))
    max_frames: Optional[int] = key(None, at_least(1, null=True))

    def _check_keys(self) -> None:
        given = [v is not None for v in (self.fx, self.fy, self.cx, self.cy)]
        check(all(given) or not any(given), "scene.options.fx/fy/cx/cy", (self.fx, self.fy, self.cx, self.cy),
               "all four set (pixels) or all null (= scene.options.camera's preset)")
        check(not any(given) or (self.fx > 0 and self.fy > 0), "scene.options.fx/fy", (self.fx, self.fy), "> 0 pixels")


TUM_CAMERAS = {  # fx fy cx cy, pixels at 640x480 (TUM RGB-D "intrinsic calibration" page)
    "fr1": (517.3, 516.5, 318.6, 255.3),
    "fr2": (520.9, 521.0, 325.1, 249.7),
    "fr3": (535.4, 539.2, 320.1, 247.6),
    "ros_default": (525.0, 525.0, 319.5, 239.5),  # OpenNI's default, used by TUM's point-cloud example
}


def _rows(path: Path, ncols: int, what: str) -> list[list[str]]:
    if not path.is_file():
        raise FileNotFoundError(f"{what} file {path} does not exist")
    rows = [ln.split() for ln in inputs.read_bytes(path, "capture").decode().splitlines()
            if ln.strip() and not ln.lstrip().startswith("#")]
    bad = next((k for k, r in enumerate(rows) if len(r) != ncols), None)
    if bad is not None:
        raise ValueError(f"{path}: line '{' '.join(rows[bad])}' has {len(rows[bad])} fields, expected {ncols} "
                         f"({what})")
    if not rows:
        raise ValueError(f"{path}: no entries, expected {what} lines")
    return rows


def read_tum_list(path: str | Path) -> tuple[np.ndarray, list[str]]:
    """'timestamp filename' list (rgb.txt / depth.txt) -> (N,) float64 seconds (sorted), N file names."""
    path = Path(path)
    rows = _rows(path, 2, "'timestamp filename'")
    try:
        t = np.array([float(r[0]) for r in rows])
    except ValueError as e:
        raise ValueError(f"{path}: timestamp is not a number ({e})") from None
    order = np.argsort(t, kind="stable")
    return t[order], [rows[k][1] for k in order]


def read_tum_samples(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """groundtruth.txt -> (N,) float64 seconds (sorted), (N, 3) metres, (N, 4) unit ``qx qy qz qw``
    (scalar last, scipy's order; each must be unit within 1e-2 and is normalised): camera-to-world."""
    path = Path(path)
    rows = _rows(path, 8, "'timestamp tx ty tz qx qy qz qw'")
    try:
        a = np.array(rows, dtype=np.float64)
    except ValueError as e:
        raise ValueError(f"{path}: non-numeric trajectory entry ({e})") from None
    a = a[np.argsort(a[:, 0], kind="stable")]
    norm = np.linalg.norm(a[:, 4:8], axis=1)
    bad = ~(np.abs(norm - 1.0) <= 1e-2) | ~np.isfinite(a).all(1)
    if bad.any():
        k = int(np.argmax(bad))
        raise ValueError(f"{path}: pose at t={a[k, 0]:.6f} has quaternion norm {norm[k]:.4g} (or non-finite "
                         f"values), expected a unit quaternion qx qy qz qw")
    return a[:, 0], a[:, 1:4], a[:, 4:8] / norm[:, None]


def read_tum_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """groundtruth.txt -> (N,) float64 seconds (sorted), (N, 4, 4) float64 camera-to-world poses."""
    t, trans, quats = read_tum_samples(path)
    return t, pose_matrices(trans, quats)


def _camera_K(root: Path, camera: str, intrinsics) -> np.ndarray:
    if intrinsics is not None:
        fx, fy, cx, cy = (float(v) for v in intrinsics)
    else:
        if camera == "auto":
            m = re.search(r"freiburg([123])", root.resolve().name)
            camera = f"fr{m.group(1)}" if m else "ros_default"
        if camera not in TUM_CAMERAS:
            raise ValueError(f"TUM camera {camera!r}: expected auto, {', '.join(TUM_CAMERAS)}")
        fx, fy, cx, cy = TUM_CAMERAS[camera]
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def load_tum(
    root,
    *,
    rgb_list: str | None = "rgb.txt",
    depth_list: str = "depth.txt",
    groundtruth: str = "groundtruth.txt",
    max_time_diff: float = 0.02,
    depth_scale: float = 5000.0,
    camera: str = "auto",
    intrinsics: tuple[float, float, float, float] | None = None,
    taxonomy: Taxonomy = SCANNET20,
    voxel_size: float = 0.02,
    cloud_stride: int = 4,
    max_depth: float | None = None,
    frame_step: int = 1,
    max_frames: int | None = None,
) -> Scene:
    """Load a TUM RGB-D sequence (see module docstring) as a Scene.

    Args:
        root: the sequence folder. rgb_list / depth_list / groundtruth: the list files in it
            (``rgb_list=None``: no colour). max_time_diff: seconds, association tolerance.
        depth_scale: raw depth units per metre (TUM: 5000).
        camera: ``auto`` (freiburg1/2/3 from the folder name, else ``ros_default``) or a key of
            ``TUM_CAMERAS``; ``intrinsics`` = (fx, fy, cx, cy) pixels overrides it.
        taxonomy: the scene's classes (TUM has no labels: predictions come from files).
        voxel_size, cloud_stride, max_depth: the back-projected cloud (as for an RGB-D folder).
        frame_step, max_frames: of the associated frames, ``[::frame_step]``, at most ``max_frames``.
    Returns:
        Scene with lazily loaded frames (depth in metres, RGB resized to depth when sizes differ,
        no ground truth); ``frames.info`` counts the frames found and those dropped for want of an
        RGB image or a pose within ``max_time_diff``.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"TUM sequence folder {root} does not exist")
    if depth_scale <= 0 or max_time_diff <= 0 or frame_step < 1:
        raise ValueError(f"depth_scale={depth_scale}, max_time_diff={max_time_diff}, frame_step={frame_step}: "
                         f"expected positive values")
    K = _camera_K(root, camera, intrinsics)
    t_d, f_d = read_tum_list(root / depth_list)
    t_g, trans, quats = read_tum_samples(root / groundtruth)
    T_wc, keep = interpolate_poses(t_g, trans, quats, t_d, max_time_diff)  # at each depth image's time
    n_no_pose = int(np.count_nonzero(~keep))
    n_no_rgb = 0
    rgb_idx = None
    if rgb_list is not None:
        t_c, f_c = read_tum_list(root / rgb_list)
        rgb_idx = associate(t_d, t_c, max_time_diff)
        n_no_rgb = int(np.count_nonzero(keep & (rgb_idx < 0)))
        keep &= rgb_idx >= 0
    sel = np.flatnonzero(keep)[::frame_step]
    if max_frames is not None:
        sel = sel[: int(max_frames)]
    if len(sel) == 0:
        need = "a pose and an RGB image" if rgb_list else "a pose"
        raise ValueError(f"{root}: none of the {len(t_d)} depth images has {need} "
                         f"within max_time_diff={max_time_diff} s ({n_no_pose} without pose, {n_no_rgb} without RGB)")
    if n_no_pose + n_no_rgb > 0.5 * len(t_d):
        warnings.warn(f"{root}: {n_no_pose + n_no_rgb} of {len(t_d)} depth images dropped ({n_no_pose} without a "
                      f"pose, {n_no_rgb} without RGB within max_time_diff={max_time_diff} s)", stacklevel=2)
    T_cw = rigid_inverse(T_wc[sel])
    depth_files = [root / f_d[k] for k in sel]
    rgb_files = [root / f_c[rgb_idx[k]] for k in sel] if rgb_idx is not None else None
    names = [p.stem for p in (rgb_files if rgb_files is not None else depth_files)]

    def load(i: int, skip: frozenset = frozenset()) -> Frame:
        depth = read_depth(depth_files[i], depth_scale, 0, (0,))
        rgb = read_rgb(rgb_files[i], depth.shape) if rgb_files is not None and "rgb" not in skip else None
        return Frame(name=names[i], K=K.copy(), T_cw=T_cw[i], depth=depth, gt_labels=None, rgb=rgb)

    info = {"n_frames_found": len(t_d), "n_no_pose": n_no_pose, "n_no_rgb": n_no_rgb,
            "timestamps": t_d[sel].tolist()}
    frames = LazyFrames(names, load, info=info, poses=list(T_cw), parts=("rgb",))
    check_depth_unit(frames[0], hint=f"scene.options.depth_scale={depth_scale} (units per metre)")
    frames.info["depth_unit_checked"] = True
    points, colors = fuse_depth(frames, voxel_size, cloud_stride, max_depth)
    if points.shape[0] == 0:
        raise ValueError(f"{root}: no valid depth to build a point cloud from (max_depth={max_depth})")
    return Scene(name=root.name, points=points, taxonomy=taxonomy, frames=frames, colors=colors)


def load(cfg: SceneConfig, taxonomy: Taxonomy, sensor: Optional[SensorModel]) -> Scene:
    """``scene.source=tum``: the sequence of the ``scene.options`` keys (real depth: the pipeline
    applies ``sensor`` with ``depth.apply_to_real``)."""
    c = cfg.options
    return load_tum(c.root, taxonomy=taxonomy, rgb_list=c.rgb_list, depth_list=c.depth_list, groundtruth=c.groundtruth,
                    max_time_diff=c.max_time_diff, depth_scale=c.depth_scale, camera=c.camera.value,
                    intrinsics=None if c.fx is None else (c.fx, c.fy, c.cx, c.cy),
                    voxel_size=c.cloud_voxel, cloud_stride=c.cloud_stride, max_depth=c.max_depth,
                    frame_step=c.frame_step, max_frames=c.max_frames)
