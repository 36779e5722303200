"""Replica as NICE-SLAM / iMAP ship it (``Replica/<scene>/``): ``scene=replica scene.options.root=Replica/room0``.

Layout (NICE-SLAM's ``scripts/download_replica.sh``; every name is a key)::

    Replica/cam_params.json            {"camera": {"w": 1200, "h": 680, "fx": 600, "fy": 600,
                                                   "cx": 599.5, "cy": 339.5, "scale": 6553.5}}
    Replica/room0/traj.txt             line i: frame i's 4x4 camera-to-world, 16 numbers row-major
    Replica/room0/results/frame000000.jpg   colour
    Replica/room0/results/depth000000.png   16-bit, ``scale`` units per metre (6553.5: 1 m = 6553.5)
    Replica/room0_mesh.ply             the scene's mesh (scene.options.mesh / cloud)

Conventions (NICE-SLAM's ``src/utils/datasets.py``, class ``Replica``): frame i is line i of
``traj.txt``; the pose is camera-to-world with OpenCV camera axes (x right, y down, z forward),
metres -- NICE-SLAM negates its y and z columns after loading, for its own OpenGL-style
renderer, exactly as it does for ScanNet's and TUM's OpenCV poses; here ``T_cw`` is its inverse.
Intrinsics and depth scale come from ``cam_params.json`` (``camera``: in ``root``, else its
parent, NICE-SLAM's place for it), each overridable by a key (``fx fy cx cy w h depth_scale``);
``cx = 599.5 = (1200 - 1) / 2`` shows its pixel centres lie at integers, as K's do here.

Frames: line i of the trajectory is used when its depth image exists (NICE-SLAM counts the
images and takes that many lines); its colour image must exist then. A frame is named after its
colour image's stem (``frame000000``): ``predictions=files`` finds ``frame000000.png``. Labels: NICE-SLAM ships
none (Replica's semantic renders come with other releases, e.g. Semantic-NeRF's); ``labels`` is an
optional template with ``{frame}`` like the others.
"""
from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
from omegaconf import MISSING

from diffuser_lab.config import SceneConfig, above, at_least, key, rule
from diffuser_lab.data import inputs
from diffuser_lab.data.capture import CaptureOptions, CapturedFrame, capture_scene
from diffuser_lab.data.images import read_depth, read_label_png, read_rgb
from diffuser_lab.data.scene import Scene, Taxonomy
from diffuser_lab.data.sensor import SensorModel
from diffuser_lab.data.poses import check_rigid, rigid_inverse

__all__ = ["ReplicaOptions", "load", "read_trajectory", "read_camera", "NICE_SLAM_CAMERA"]

NICE_SLAM_CAMERA = {"w": 1200, "h": 680, "fx": 600.0, "fy": 600.0, "cx": 599.5, "cy": 339.5, "scale": 6553.5}
"""NICE-SLAM's Replica camera (configs/Replica/replica.yaml, cam_params.json), named in error messages."""


def _frame_template(null: bool = False):
    def ok(v) -> bool:
        try:
            return v.format(frame=1) != v.format(frame=2)
        except (KeyError, IndexError, ValueError):
            return False

    return rule("a path relative to root with a {frame} field (e.g. results/frame{frame:06d}.jpg)"
                + (" or null" if null else ""), lambda v: isinstance(v, str) and ok(v), null=null)


@dataclass
class ReplicaOptions(CaptureOptions):
    """``scene=replica``: a Replica sequence in NICE-SLAM's layout (module docstring)."""

    root: str = MISSING  # the sequence folder (Replica/room0: traj.txt, results/)
    trajectory: str = "traj.txt"  # relative to root: line i = frame i's 4x4 camera-to-world, row-major
    color: str = key("results/frame{frame:06d}.jpg", _frame_template())  # relative to root, {frame} = line number
    depth: str = key("results/depth{frame:06d}.png", _frame_template())  # 16-bit, depth_scale units per metre
    labels: Optional[str] = key(None, _frame_template(null=True))  # optional ground-truth label images; null = none
    camera: Optional[str] = None  # intrinsics JSON relative to root; null = cam_params.json in root, else in its parent
    fx: Optional[float] = key(None, above(0, "pixels", null=True))  # overrides the camera file's
    fy: Optional[float] = key(None, above(0, "pixels", null=True))
    cx: Optional[float] = None  # pixels, pixel centres at integers
    cy: Optional[float] = None
    w: Optional[int] = key(None, at_least(1, null=True))  # image width the intrinsics are for, pixels
    h: Optional[int] = key(None, at_least(1, null=True))
    depth_scale: Optional[float] = key(None, above(0, "units per metre", null=True))  # null = the camera file's scale


def read_trajectory(path: str | Path) -> list[np.ndarray]:
    """traj.txt -> one (4, 4) float64 camera-to-world per non-empty line (16 numbers, row-major),
    each finite and rigid; one line naming the file and line otherwise."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Replica trajectory {path} does not exist")
    poses = []
    for n, line in enumerate(inputs.read_bytes(path, "capture").decode().splitlines(), 1):  # loop over poses (text lines)
        if not line.strip():
            continue
        try:
            vals = np.array([float(t) for t in line.split()], np.float64)
        except ValueError:
            raise ValueError(f"{path}: line {n} is not 16 numbers (a row-major 4x4 camera-to-world)") from None
        if vals.size != 16 or not np.isfinite(vals).all():
            bad = "" if np.isfinite(vals).all() else " (non-finite)"
            raise ValueError(f"{path}: line {n} has {vals.size} values{bad}, expected 16 finite numbers "
                             f"(a row-major 4x4 camera-to-world)")
        T = vals.reshape(4, 4)
        check_rigid(T, f"{path}: line {n}", "camera_to_world")
        poses.append(T)
    if not poses:
        raise ValueError(f"{path}: no poses, expected one 4x4 camera-to-world per line")
    return poses


def read_camera(o: ReplicaOptions, root: Path) -> tuple[np.ndarray, tuple[int, int], float, str]:
    """(K (3, 3), (h, w) it is for, depth units per metre, where they came from)."""
    if o.camera:
        tried = [root / o.camera]
    else:
        tried = [root / "cam_params.json", root.parent / "cam_params.json"]
    found = next((p for p in tried if p.is_file()), None)
    cam: dict = {}
    if found is not None:
        try:
            data = json.loads(inputs.read_bytes(found, "intrinsics").decode())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise ValueError(f"{found}: not valid JSON ({getattr(e, 'msg', e)})") from None
        cam = data.get("camera") if isinstance(data, dict) else None
        if not isinstance(cam, dict):
            raise ValueError(f"{found}: no 'camera' object, expected NICE-SLAM's cam_params.json "
                             f"{{\"camera\": {{\"w\", \"h\", \"fx\", \"fy\", \"cx\", \"cy\", \"scale\"}}}}")
    keys = {"fx": o.fx, "fy": o.fy, "cx": o.cx, "cy": o.cy, "w": o.w, "h": o.h, "scale": o.depth_scale}
    vals = {}
    for k, v in keys.items():  # loop over the 7 camera values
        if v is None:
            v = cam.get(k)
        if v is None:
            if found is None and o.camera:
                raise FileNotFoundError(f"Replica camera file {tried[0]} does not exist")
            where = found if found is not None else f"no cam_params.json in {root} or {root.parent}"
            key_name = "depth_scale" if k == "scale" else k
            raise ValueError(f"{where}: no camera value {k}; set scene.options.{key_name} (NICE-SLAM's Replica: "
                             f"{NICE_SLAM_CAMERA[k]}) or scene.options.camera=FILE")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise ValueError(f"{found}: camera {k}={v!r}, expected a finite number")
        vals[k] = float(v)
    if min(vals["fx"], vals["fy"], vals["w"], vals["h"], vals["scale"]) <= 0:
        raise ValueError(f"{found or 'scene.options'}: camera {vals}, expected positive fx fy w h scale")
    K = np.array([[vals["fx"], 0.0, vals["cx"]], [0.0, vals["fy"], vals["cy"]], [0.0, 0.0, 1.0]])
    return K, (int(vals["h"]), int(vals["w"])), vals["scale"], str(found) if found else "scene.options"


def load(cfg: SceneConfig, taxonomy: Taxonomy, sensor: Optional[SensorModel]) -> Scene:
    """``scene.source=replica``: the sequence of ``scene.options`` (a :class:`ReplicaOptions`)."""
    o: ReplicaOptions = cfg.options
    root = Path(o.root)
    if not root.is_dir():
        raise FileNotFoundError(f"Replica sequence folder {root} does not exist")
    K, K_size, scale, cam_src = read_camera(o, root)
    poses = read_trajectory(root / o.trajectory)
    frames = []
    for i, c2w in enumerate(poses):  # loop over poses: file names only, images are read lazily
        depth, color = root / o.depth.format(frame=i), root / o.color.format(frame=i)
        if not depth.is_file():
            continue
        if not color.is_file():
            raise FileNotFoundError(f"{root}: frame {i} has depth {depth.name} but no colour image {color} "
                                    f"(scene.options.color={o.color})")
        labels = root / o.labels.format(frame=i) if o.labels else None
        frames.append(CapturedFrame(
            name=color.stem,
            T_cw=rigid_inverse(c2w), K=K, K_size=K_size, K_from=f"{cam_src} (w h)", K_image=depth,
            depth=lambda p=depth: read_depth(p, scale, invalid=(0,)),
            rgb=lambda p=color: read_rgb(p),
            labels=(lambda p=labels: read_label_png(p)) if labels is not None and labels.is_file() else None))
    if not frames:
        raise FileNotFoundError(f"{root}: none of the {len(poses)} poses of {o.trajectory} has a depth image "
                                f"{o.depth} (scene.options.depth)")
    if len(frames) < len(poses):
        warnings.warn(f"{root}: {len(poses) - len(frames)} of {len(poses)} poses of {o.trajectory} have no depth "
                      f"image ({o.depth}); they are skipped", stacklevel=2)
    info = {"n_frames_found": len(frames), "n_poses": len(poses), "camera": cam_src, "depth_scale": scale}
    return capture_scene(root.resolve().name, frames, o, taxonomy, root=root, info=info)
