"""Posed RGB-D folders in the ``frame-XXXXXX.*`` layout (7-Scenes, tsdf-fusion, SUN3D exports).

Layout of ``root`` (every name is a key; docs/layouts.md)::

    camera-intrinsics.txt        3x3 K (pixels) of the depth image, shared by all frames (intrinsics_file)
    frame-000000.color.jpg       colour (any resolution; resized to the depth's)    (frame_prefix, color_suffix)
    frame-000000.depth.png       16-bit depth (or .npy metres: images.read_depth)    (depth_suffix)
    frame-000000.pose.txt        4x4 camera-to-world, metres (pose_convention)       (pose_suffix)
    frame-000000.<label_suffix>  optional ground-truth label image

Depth PNG values differ between datasets: metres = decode(raw) / ``depth_scale``, where decode is
``raw`` itself, a 16-bit circular right shift by ``depth_bit_shift`` (``depth_shift_kind=circular``:
SUN3D stores millimetres rotated left by 3 bits) or a plain right shift (``plain``: ``raw >> 3``,
the low bits carry flags, as in ``(raw >> 3) / 1e4`` m). 7-Scenes / ScanNet store millimetres
(``depth_scale=1000``; 7-Scenes marks invalid pixels 65535, others 0), TUM stores 1/5000 m. The
loader warns when the first frame's median depth looks like a wrong unit.

Frames are read lazily (one frame's files per ``scene.frames[i]``), so memory does not
grow with the sequence length.

**Followed as it is written** (``follow=true``, protocol=online; docs/online.md): the folder is polled
while a recorder writes it; a frame is taken, in name order, once its depth, colour (unless
``color_suffix`` is null) and pose files are whole (:func:`~diffuser_lab.data.images.image_complete`: a
PNG up to its IEND chunk, a JPEG up to its end marker, a .npy up to its header's bytes; the pose
parses as a 4x4 matrix). A frame still incomplete :data:`LATE_S` seconds after a later one is whole
was cut short: it is handed on as a bad frame (skipped with one line), so one damaged frame does not
hold up the rest. The intrinsics file is waited for too. A folder has no end mark: the run ends
``follow_timeout`` seconds after the last new frame (or at ``max_frames``). The readers it shares
with the other formats live in :mod:`diffuser_lab.data.images`, :mod:`diffuser_lab.data.poses` and
:mod:`diffuser_lab.data.intrinsics`.
"""
from __future__ import annotations

import bisect
import os
import re
import time
import warnings
from pathlib import Path
from dataclasses import dataclass, field
from enum import Enum
from typing import List, Optional

import numpy as np
from omegaconf import MISSING

from diffuser_lab import progress
from diffuser_lab.config import Check, PoseConvention, SceneConfig, above, at_least, key, rule, within
from diffuser_lab.data.capture import FollowOptions, followed_scene, fuse_depth, taxonomy_mapping, to_taxonomy
from diffuser_lab.data.clouds import read_cloud
from diffuser_lab.data.frames import Follow, LazyFrames, first_line
from diffuser_lab.data.images import (image_complete, label_ids_in, read_depth, read_label_png, read_rgb,
                                      resize_nearest)
from diffuser_lab.data.intrinsics import read_intrinsics
from diffuser_lab.data.mapping import ClassMapping
from diffuser_lab.data.poses import CAMERA_TO_WORLD, pose_to_world_to_camera, read_pose_c2w
from diffuser_lab.data.scene import SCANNET20, Frame, Scene, Taxonomy
from diffuser_lab.data.sensor import SensorModel
from diffuser_lab.data.validate import check_depth_unit

__all__ = ["RgbdFolderOptions", "DepthShiftKind", "load_rgbd_folder", "load", "label_ids"]


class DepthShiftKind(Enum):
    circular = "circular"  # 16-bit rotate right (SUN3D stores depth rotated left by 3 bits)
    plain = "plain"  # raw >> shift, the low bits dropped (e.g. (raw >> 3) / 1e4 m)


_SUFFIX = "a non-empty file name suffix, without / or *"


def _suffix(null: bool = False) -> Check:
    return rule(_SUFFIX, lambda v: bool(v) and "/" not in v and "*" not in v, null=null)


LATE_S = 1.0
"""Seconds a followed frame may stay incomplete once a later frame is whole (then it was cut short)."""
RESCAN_S = 1.0  # a followed folder is listed again at least this often (else when its mtime changes)


@dataclass
class RgbdFolderOptions(FollowOptions):
    """A posed RGB-D folder: frame-XXXXXX.{color.*,depth.png,pose.txt} + camera-intrinsics.txt.
    A frame's files are ``<frame_prefix><digits>.<suffix>``; docs/layouts.md describes each key."""

    KEY = "scene.options"
    root: str = MISSING  # the folder
    intrinsics_file: str = key("camera-intrinsics.txt", rule("a file name relative to root",
                                                             lambda v: bool(v) and "*" not in v))  # 3x3 K of the depth image, relative to root
    frame_prefix: str = key("frame-", rule("a file name prefix without / or *",
                                           lambda v: "/" not in v and "*" not in v))  # a frame's name = prefix + digits (frame-000000)
    depth_suffix: str = key("depth.png", _suffix())
    pose_suffix: str = key("pose.txt", _suffix())
    pose_convention: PoseConvention = PoseConvention.camera_to_world
    depth_scale: float = key(1000.0, above(0))  # metres = (raw, shifted) / depth_scale (1000 = millimetres)
    depth_bit_shift: int = key(0, within(0, 15))  # right shift of the raw 16-bit depth before scaling (SUN3D: 3)
    depth_shift_kind: DepthShiftKind = DepthShiftKind.circular  # circular (SUN3D) | plain (raw >> shift)
    invalid_depth: List[int] = field(default_factory=lambda: [0, 65535])  # raw values, before the shift
    color_suffix: Optional[str] = key("color.jpg", _suffix(null=True))  # null = no colour; no such file at all = no colour (warning)
    label_suffix: Optional[str] = key(None, _suffix(null=True))  # ground-truth label images frame-XXXXXX.<suffix>, if any
    mapping: Optional[str] = None  # label ids -> taxonomy; null = ids are taxonomy ids
    cloud: Optional[str] = None  # PLY, LAS or LAZ point cloud; null = back-project and voxel-merge the depth frames
    cloud_voxel: float = key(0.02, above(0, "metres"))  # metres, for the back-projected cloud
    cloud_stride: int = key(4, at_least(1))  # every n-th pixel of each depth frame for the back-projected cloud
    max_depth: Optional[float] = key(None, above(0, "metres", null=True))  # ignore depth beyond it
    frame_step: int = key(1, at_least(1))
    max_frames: Optional[int] = key(None, at_least(1, null=True))


_MAPPING_HINT = "pass mapping= to translate another label space"


def load_rgbd_folder(
    root,
    *,
    depth_scale: float = 1000.0,
    depth_bit_shift: int = 0,
    depth_shift_kind: str = "circular",
    invalid_depth=(0, 65535),
    intrinsics_file: str = "camera-intrinsics.txt",
    frame_prefix: str = "frame-",
    depth_suffix: str = "depth.png",
    pose_suffix: str = "pose.txt",
    pose_convention: str = CAMERA_TO_WORLD,
    color_suffix: str | None = "color.jpg",
    label_suffix: str | None = None,
    taxonomy: Taxonomy = SCANNET20,
    mapping: str | ClassMapping | None = None,
    cloud=None,
    voxel_size: float = 0.02,
    cloud_stride: int = 4,
    frame_step: int = 1,
    max_frames: int | None = None,
    max_depth: float | None = None,
    follow: Optional[FollowOptions] = None,
) -> Scene:
    """Load a posed RGB-D folder (see module docstring) as a Scene.

    Args:
        root: the folder.
        depth_scale: stored depth units per metre (after the shift). depth_bit_shift,
            depth_shift_kind: right shift of the raw 16-bit depth, ``circular`` (SUN3D) or
            ``plain`` (``raw >> shift``). invalid_depth: raw "no depth" values (before the shift).
        intrinsics_file: name of the 3x3 K file in ``root``.
        frame_prefix: a frame's name is ``<frame_prefix><digits>``; its files are
            ``<name>.<depth_suffix>``, ``<name>.<pose_suffix>``, ``<name>.<color_suffix>``.
        pose_convention: what the pose files hold, ``camera_to_world`` or ``world_to_camera``.
        color_suffix: colour file suffix, None = no colour; when no frame has such a file the
            frames carry no RGB (a warning says so) and the fused cloud is a neutral grey.
        label_suffix: suffix of ground-truth label images (e.g. ``label.png``); frames
            without that file get ``gt_labels=None``.
        taxonomy: evaluation classes. mapping: label ids -> taxonomy (CSV name/path or
            ClassMapping); None = label images (and a cloud's ``label``) hold taxonomy ids.
        cloud: PLY / LAS / LAZ path of the points to label (optional colours, normals, ``label``),
            or None = fuse the frames' depth: every ``cloud_stride``-th pixel up to
            ``max_depth`` metres (None = no cutoff), merged on a ``voxel_size`` grid,
            colours averaged from the colour images. ``max_depth`` only affects this fusion.
        frame_step, max_frames: use frames ``[::frame_step]``, at most ``max_frames`` of them.
        follow: keys whose ``follow`` is true: the folder is followed as a recorder writes it (module
            docstring); the scene's points are then ``cloud``'s, else none (an online growing map).
    Returns:
        Scene with lazily loaded frames (``Frame.labels`` None, depth-resolution images);
        normals only when the cloud PLY has them.
    """
    root = Path(root)
    if not root.is_dir() and not (follow and follow.follow):  # a followed folder may not be made yet
        raise FileNotFoundError(f"RGB-D folder {root} does not exist")
    if depth_scale <= 0 or frame_step < 1 or cloud_stride < 1 or voxel_size <= 0:
        raise ValueError(f"depth_scale={depth_scale}, frame_step={frame_step}, cloud_stride={cloud_stride}, "
                         f"voxel_size={voxel_size}: expected positive values (steps >= 1)")
    pose_to_world_to_camera(np.eye(4), pose_convention)  # a wrong name fails before any file is read
    mapping = taxonomy_mapping(mapping, taxonomy)
    if mapping is not None and mapping.target.names != taxonomy.names:
        raise ValueError(f"mapping {mapping.source} targets taxonomy {mapping.target.name}, expected {taxonomy.name}")
    name_re = re.compile(re.escape(frame_prefix) + r"\d+")

    def read(K: np.ndarray, name: str, T_cw: np.ndarray, skip: frozenset = frozenset()) -> Frame:
        """Frame ``name``'s files (colour left out when ``skip`` says so)."""
        depth = read_depth(root / f"{name}.{depth_suffix}", depth_scale, depth_bit_shift, invalid_depth,
                               depth_shift_kind)
        rgb = read_rgb(root / f"{name}.{color_suffix}", depth.shape) if color_suffix and "rgb" not in skip else None
        gt = None
        if label_suffix:
            lp = root / f"{name}.{label_suffix}"
            if lp.is_file():
                gt = to_taxonomy(resize_nearest(read_label_png(lp), depth.shape), mapping, taxonomy, str(lp),
                                 _MAPPING_HINT)
        return Frame(name=name, K=K.copy(), T_cw=T_cw, depth=depth, gt_labels=gt, rgb=rgb)

    if follow and follow.follow:
        return followed_scene(root.name, _followed(root, follow, intrinsics_file, frame_prefix, name_re, depth_suffix,
                                                   color_suffix, pose_suffix, pose_convention, read),
                              cloud, mapping, taxonomy)
    K = read_intrinsics(root / intrinsics_file)

    def stems(suffix: str) -> list[str]:
        return sorted(n for n in (p.name[: -len(suffix) - 1] for p in root.glob(f"{frame_prefix}*.{suffix}"))
                      if name_re.fullmatch(n))

    depth_stems, pose_stems = stems(depth_suffix), stems(pose_suffix)
    if not depth_stems:
        raise FileNotFoundError(f"{root}: no {frame_prefix}XXXXXX.{depth_suffix} files "
                                f"(keys frame_prefix={frame_prefix!r}, depth_suffix={depth_suffix!r})")
    color_stems = stems(color_suffix) if color_suffix else depth_stems
    if color_suffix and not color_stems:
        warnings.warn(f"{root}: no {frame_prefix}XXXXXX.{color_suffix} colour images: frames have no RGB and "
                      f"the cloud is grey (set color_suffix=null to say so)", stacklevel=2)
        color_suffix, color_stems = None, depth_stems
    if not (depth_stems == pose_stems == color_stems):
        raise ValueError(f"{root}: {len(depth_stems)} {depth_suffix}, {len(pose_stems)} {pose_suffix} and "
                         f"{len(color_stems)} {color_suffix} files (or different frame numbers), expected one "
                         f"of each per frame")
    names = depth_stems[::frame_step]
    if max_frames is not None:
        names = names[: int(max_frames)]
    poses, kept = [], []
    with progress.stage("reading poses", total=len(names), unit="pose") as bar:
        for name in names:  # loop over frames: poses are tiny and validated up front
            path = root / f"{name}.{pose_suffix}"
            T = read_pose_c2w(path, convention=pose_convention)
            if T is None:
                raise ValueError(_not_finite(path, pose_convention))
            poses.append(pose_to_world_to_camera(T, pose_convention))
            kept.append(name)
            bar.update()

    frames = LazyFrames(kept, lambda i, skip: read(K, kept[i], poses[i], skip),
                        info={"n_frames_found": len(depth_stems)}, poses=poses, parts=("rgb",))
    # checked here, before a wrong unit scales the back-projected cloud; the pipeline skips it then
    check_depth_unit(frames[0], hint=f"depth_scale={depth_scale} (units per metre) / depth_bit_shift="
                                     f"{depth_bit_shift} / depth_shift_kind={depth_shift_kind}")
    frames.info["depth_unit_checked"] = True

    normals = colors = gt_points = None
    if cloud is not None:
        with progress.stage(f"reading point cloud {Path(cloud).name}"):
            pc = read_cloud(cloud)
        points, colors, normals = pc["points"], pc.get("colors"), pc.get("normals")
        if "labels" in pc:
            gt_points = to_taxonomy(pc["labels"], mapping, taxonomy, str(cloud), _MAPPING_HINT)
    else:
        points, colors = fuse_depth(frames, voxel_size, cloud_stride, max_depth)
        if points.shape[0] == 0:
            raise ValueError(f"{root}: no valid depth to build a point cloud from (max_depth={max_depth})")
    return Scene(name=root.name, points=points, taxonomy=taxonomy, frames=frames, normals=normals,
                 colors=colors, gt_labels=gt_points)


def _not_finite(path: Path, convention: str) -> str:
    return f"{path}: pose has non-finite entries, expected a 4x4 rigid {convention.replace('_', '-')} transform"


def _followed(root: Path, options: FollowOptions, intrinsics_file: str, frame_prefix: str, name_re,
              depth_suffix: str, color_suffix: Optional[str], pose_suffix: str, pose_convention: str,
              read) -> LazyFrames:
    """The frames of a folder a recorder is writing (module docstring), complete so far, as a growing
    :class:`LazyFrames`: ``read(K, name, T_cw, skip)`` reads a frame's files once they are whole."""
    # the intrinsics once read; the last frame taken; cut-short clocks; the listing, when and at which folder mtime
    state: dict = {"K": None, "last": "", "late": {}, "names": [], "scanned": -RESCAN_S, "mtime": None}

    def whole(name: str) -> tuple[Optional[tuple[np.ndarray, Optional[str]]], str]:
        """((4, 4) world-to-camera, None) of a complete frame, (NaN, why) of one whose pose is not finite; or
        None while it is incomplete, and what is missing."""
        parts = [f"{name}.{depth_suffix}"] + ([f"{name}.{color_suffix}"] if color_suffix else [])
        missing = [p for p in parts if not image_complete(root / p)]
        try:
            T = read_pose_c2w(root / f"{name}.{pose_suffix}", convention=pose_convention)
        except (OSError, ValueError) as exc:  # not there, or not all of it yet
            missing.append(f"{name}.{pose_suffix} ({first_line(exc)})")
            T = None
        if missing:
            return None, ", ".join(missing)
        if T is None:
            return (np.full((4, 4), np.nan), _not_finite(root / f"{name}.{pose_suffix}", pose_convention)), ""
        return (pose_to_world_to_camera(T, pose_convention), None), ""

    def poll() -> bool:
        if state["K"] is None:
            try:
                state["K"] = read_intrinsics(root / intrinsics_file)
            except (OSError, ValueError) as exc:  # not written yet (or not all of it)
                follow.waiting = first_line(exc)
                return False
        try:  # listed again when the folder changed (its mtime; at least every RESCAN_S: mtimes are coarse)
            mtime, now = os.stat(root).st_mtime_ns, time.monotonic()
            if mtime != state["mtime"] or now - state["scanned"] >= RESCAN_S:
                with os.scandir(root) as it:
                    state["names"] = sorted(n for n in (e.name[: -len(depth_suffix) - 1] for e in it
                                                        if e.name.endswith(f".{depth_suffix}")) if name_re.fullmatch(n))
                state.update(mtime=mtime, scanned=now)
        except OSError as exc:
            follow.waiting = first_line(exc)
            return False
        names = state["names"][bisect.bisect_right(state["names"], state["last"]):]  # not taken yet
        follow.waiting = f"{root / frame_prefix}XXXXXX.{depth_suffix}" if not follow.names else ""
        for k, name in enumerate(names):  # loop over the frames not taken yet, in name order
            got, why = whole(name)
            if got is None:
                later = next((n for n in names[k + 1:k + 2] if whole(n)[0] is not None), None)
                if later is None:
                    state["late"].pop(name, None)
                    return False  # the frame being written: waited for
                since = state["late"].setdefault(name, time.monotonic())
                if time.monotonic() - since < LATE_S:
                    return False
                got = (np.full((4, 4), np.nan), f"{root / name}.*: still incomplete {LATE_S:g} s after {later} was "
                                                 f"whole ({why}): cut short")
            follow.add(name, got[0], (name, got[1]))
            state["last"] = name
        return False  # a folder is never closed: the run ends follow_timeout after the last frame

    def load(i: int, skip: frozenset) -> Frame:
        name, bad = follow.items[i]
        if bad:
            raise ValueError(bad)
        return read(state["K"], name, follow.poses[i], skip)

    follow: Follow = options.follower(poll, f"RGB-D folder {root}")
    return LazyFrames(0, load, info={"follow": follow.info}, parts=("rgb",), follow=follow)


def load(cfg: SceneConfig, taxonomy: Taxonomy, sensor: Optional[SensorModel]) -> Scene:
    """``scene.source=rgbd_folder``: the folder of the ``scene.options`` keys (real depth: the
    pipeline applies ``sensor`` with ``depth.apply_to_real``)."""
    r = cfg.options
    return load_rgbd_folder(r.root, taxonomy=taxonomy, depth_scale=r.depth_scale, depth_bit_shift=r.depth_bit_shift,
                            depth_shift_kind=r.depth_shift_kind.value, invalid_depth=tuple(r.invalid_depth),
                            intrinsics_file=r.intrinsics_file, frame_prefix=r.frame_prefix,
                            depth_suffix=r.depth_suffix, pose_suffix=r.pose_suffix,
                            pose_convention=r.pose_convention.value,
                            color_suffix=r.color_suffix, label_suffix=r.label_suffix, mapping=r.mapping,
                            cloud=r.cloud, voxel_size=r.cloud_voxel, cloud_stride=r.cloud_stride,
                            frame_step=r.frame_step, max_frames=r.max_frames, max_depth=r.max_depth, follow=r)


def label_ids(cfg: SceneConfig, n: int) -> list[tuple[np.ndarray, str]]:
    """``taxonomy=ids``: the first ``n`` ground-truth label images (``label_suffix``), if any."""
    r = cfg.options
    if not r.label_suffix:
        return []
    root = Path(r.root)
    return label_ids_in(list(root.glob(f"{r.frame_prefix}*.{r.label_suffix}")), n, f"ground-truth ({root})")
