"""nerfstudio's ``transforms.json`` (what ``ns-process-data`` writes for COLMAP, Record3D, Polycam,
Metashape, ... captures, and what ScanNet++ ships): ``scene=nerfstudio scene.options.root=FOLDER``.

Specified by https://docs.nerf.studio/quickstart/data_conventions.html and read as nerfstudio's
``nerfstudio/data/dataparsers/nerfstudio_dataparser.py`` reads it:

- **frames**: ``frames[*].file_path`` (relative to the json's folder), sorted by it as nerfstudio
  does; a frame's name is its image's stem (``images/frame_00001.jpg`` -> ``frame_00001``), so a
  2D network's outputs written next to their inputs' names are found by ``predictions=files``'
  default ``{name}.png``. ``downscale`` d > 1 reads ``images_{d}/<file name>`` (nerfstudio's
  downscaled copies; masks ``masks_{d}/`` and depth ``depths_{d}/`` when those exist, else the
  full-size files); K stays the json's, for ``(h, w)``, and is scaled to each image's size.
- **intrinsics** ``fl_x fl_y cx cy w h``: per frame, else the top level (a per-frame value
  overrides the top level's; nerfstudio itself takes the top level's when both are given).
  nerfstudio shoots pixel (col, row)'s ray through ``(col + 0.5, row + 0.5)`` (its pixel
  coordinates put the image's corner at 0, as COLMAP's do), so K here has ``cx - 0.5, cy - 0.5``
  (pixel centres at integers, :mod:`diffuser_lab.data.geometry`).
- **distortion** ``camera_model`` (top level or per frame) with ``k1 k2 k3 k4 p1 p2`` or
  ``distortion_params`` ``[k1, k2, k3, k4, p1, p2]`` (per frame, else top level, absent = 0):
  ``OPENCV`` / ``RADIAL`` / ``SIMPLE_RADIAL`` / ``PINHOLE`` / ``SIMPLE_PINHOLE`` / none are
  nerfstudio's perspective camera (radial-tangential), ``OPENCV_FISHEYE`` its fisheye (k1..k4);
  distorted images (colour, depth, masks, labels) are resampled to the pinhole camera of the same
  K (:mod:`diffuser_lab.data.distortion`); all-zero coefficients mean no resampling. Other models
  (``EQUIRECTANGULAR``, ``FISHEYE624``, ...) and, with ``undistort=false``, any distortion are
  refused with one line naming the file, the frame and the model.
- **poses** ``transform_matrix``: camera-to-world, OpenGL camera axes (x right, y up, z back):
  ``c2w_cv = c2w_gl @ diag(1, -1, -1, 1)``, ``T_cw = c2w_cv^-1``; 3x4 or 4x4, rigid (one line otherwise).
- **world frame**: the poses (and, since nerfstudio 1.0, the PLY) are stored in the frame
  ``ns-process-data`` chose: ``applied_transform`` (3x4) maps the original data's world (COLMAP's,
  the phone's) to it, ``saved = A original``; nerfstudio's dataparser loads poses and PLY as
  stored and composes A only into its exported ``dataparser_transform``. ``world=saved`` (default)
  keeps that frame, ``world=original`` maps poses and cloud back with ``A^-1`` (refused when the
  json has no ``applied_transform``, or an ``applied_scale`` other than 1). ``ply_world=original``
  reads a PLY written by nerfstudio < 1.0, which is still in the original frame.
- **depth** ``depth_file_path`` (relative, per frame): a 16-bit PNG or a ``.npy`` array, times
  ``depth_unit_scale`` metres per unit (nerfstudio's ``depth_unit_scale_factor``, 1e-3: mm; also
  read from the json's ``depth_unit_scale_factor`` key when present), 0 = no depth.
- **masks** ``mask_path`` (per frame): 0 = the pixel is not to be used (nerfstudio's rule);
  ``masks=true`` zeroes the depth there (no points, no depth check, so no evidence from it).
- **cloud** ``ply_file_path`` (relative) when present, else the depth back-projected
  (:func:`~diffuser_lab.data.capture.capture_scene`); ``scene.options.cloud`` overrides both.
- **labels**: nerfstudio has none; ``labels`` is a path template relative to the folder with
  ``{stem}`` (the image's stem) or ``{name}`` (the frame's name, the same), e.g. ``labels/{stem}.png``;
  a frame without that file has no ground truth.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any, Optional

import numpy as np
from omegaconf import MISSING

from diffuser_lab.config import SceneConfig, above, key, rule
from diffuser_lab.data import inputs
from diffuser_lab.data.capture import CaptureOptions, CapturedFrame, capture_scene
from diffuser_lab.data.clouds import read_cloud
from diffuser_lab.data.distortion import FISHEYE, PERSPECTIVE, LensModel, undistort_image
from diffuser_lab.data.images import open_image, read_depth, read_label_png, read_rgb, resize_nearest
from diffuser_lab.data.scene import IGNORE, Scene, Taxonomy
from diffuser_lab.data.sensor import SensorModel
from diffuser_lab.data.poses import check_rigid, rigid_inverse

__all__ = ["World", "NerfstudioOptions", "load", "read_transforms", "OPENGL_TO_OPENCV", "CAMERA_MODELS"]

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""c2w_cv = c2w_gl @ OPENGL_TO_OPENCV (and back: the matrix is its own inverse)."""

CAMERA_MODELS = {"OPENCV": PERSPECTIVE, "OPENCV_FISHEYE": FISHEYE, "PINHOLE": PERSPECTIVE,
                 "SIMPLE_PINHOLE": PERSPECTIVE, "RADIAL": PERSPECTIVE, "SIMPLE_RADIAL": PERSPECTIVE, None: PERSPECTIVE}
"""The camera_model values read (nerfstudio's CAMERA_MODEL_TO_TYPE, perspective and fisheye) -> lens kind."""

_INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
_COEFFS = ("k1", "k2", "k3", "k4", "p1", "p2")  # nerfstudio's distortion_params order


class World(Enum):
    saved = "saved"  # the frame the json's poses are stored in (applied_transform already applied)
    original = "original"  # the data's own frame before ns-process-data: applied_transform undone


_TEMPLATE = rule("a path relative to root with {stem} or {name} and no other {...}, or null",
                 lambda v: bool(v) and re.sub(r"\{(stem|name)\}", "", v).count("{") == 0
                 and bool(re.search(r"\{(stem|name)\}", v)), null=True)


@dataclass
class NerfstudioOptions(CaptureOptions):
    """``scene=nerfstudio``: a folder with nerfstudio's transforms.json (module docstring)."""

    root: str = MISSING  # the folder holding transforms.json, or the json file itself
    transforms: str = key("transforms.json", rule("a file name", bool))  # the json's name in root (a folder)
    # depth PNG / npy: metres per stored unit; null = the json's depth_unit_scale_factor, else 1e-3 (mm)
    depth_unit_scale: Optional[float] = key(None, above(0, "metres per unit", null=True))
    labels: Optional[str] = key(None, _TEMPLATE)  # ground-truth label images, e.g. labels/{stem}.png; null = none
    downscale: int = key(1, rule("1, 2, 4 or 8", lambda v: v in (1, 2, 4, 8)))  # read images_{d}/, K scaled
    undistort: bool = True  # resample distorted images to the pinhole of the same K; false = refuse them
    masks: bool = True  # mask_path: zero the depth where the mask is 0; false = masks ignored
    world: World = World.saved  # saved = the json's frame; original = applied_transform undone
    ply_world: World = World.saved  # the frame ply_file_path is in: saved (nerfstudio >= 1.0), original (older)


def _number(v: Any, where: str, name: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise ValueError(f"{where}: {name}={v!r}, expected a finite number")
    return float(v)


def _matrix(v: Any, where: str, name: str, shapes: tuple) -> np.ndarray:
    try:
        M = np.array(v, dtype=np.float64)
    except (TypeError, ValueError):
        M = np.zeros((0,))
    if M.shape not in shapes or not np.isfinite(M).all():
        want = " or ".join(f"{a}x{b}" for a, b in shapes)
        raise ValueError(f"{where}: {name} is not a finite {want} matrix of numbers (got shape {M.shape})")
    if M.shape == (3, 4):
        M = np.vstack([M, [0.0, 0.0, 0.0, 1.0]])
    return M


def read_transforms(path: str | Path) -> dict:
    """transforms.json -> its dict, with a ``frames`` list of dicts; one line naming the file otherwise."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"nerfstudio transforms file {path} does not exist")
    try:
        meta = json.loads(inputs.read_bytes(path, "capture").decode())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON ({e.msg} at line {e.lineno} column {e.colno})") from None
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not a text file ({e.reason})") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise ValueError(f"{path}: no 'frames' list, expected nerfstudio's transforms.json "
                         f"(https://docs.nerf.studio/quickstart/data_conventions.html)")
    if not meta["frames"]:
        raise ValueError(f"{path}: 'frames' is empty")
    for i, f in enumerate(meta["frames"]):  # loop over frame records: shape only
        if not isinstance(f, dict) or not isinstance(f.get("file_path"), str) or "transform_matrix" not in f:
            raise ValueError(f"{path}: frames[{i}] lacks file_path or transform_matrix")
    return meta


def _lens(frame: dict, meta: dict, where: str) -> LensModel:
    model = frame.get("camera_model", meta.get("camera_model"))
    if model not in CAMERA_MODELS:
        raise ValueError(f"{where}: camera_model {model!r} is not supported (expected "
                         f"{', '.join(m for m in CAMERA_MODELS if m)} or none)")
    params = frame.get("distortion_params", meta.get("distortion_params")) if not any(
        k in frame for k in _COEFFS) else None
    if params is not None:
        vals = _matrix(params, where, "distortion_params", ((6,),)).tolist()
    else:
        vals = [_number(frame.get(k, meta.get(k, 0.0)), where, k) for k in _COEFFS]
    c = dict(zip(_COEFFS, vals))
    kind = CAMERA_MODELS[model]
    if kind == FISHEYE:
        c["p1"] = c["p2"] = 0.0  # nerfstudio's fisheye has no tangential terms
    return LensModel(kind, **c)


def _frame_path(root: Path, rel: str, downscale: int, prefix: str) -> Path:
    """nerfstudio's _get_fname: ``<prefix>{d}/<file name>`` for a downscale d > 1, else the path itself."""
    if downscale > 1:
        return root / f"{prefix}{downscale}" / Path(rel).name
    return root / rel


def _read_mask(path: Path) -> np.ndarray:
    """A mask image -> (H, W) bool, True = use the pixel (non-zero)."""
    with open_image(path, "mask image") as im:
        return np.asarray(im.convert("L")) > 0


class _Frame:
    """One frame's files and camera -> its lazy readers (undistorted when the lens distorts)."""

    def __init__(self, name, K, K_size, lens, image, depth, mask, labels, unit):
        self.name, self.K, self.K_size, self.lens = name, K, K_size, lens
        self.image, self.depth_path, self.mask, self.labels_path, self.unit = image, depth, mask, labels, unit

    def rgb(self) -> np.ndarray:
        img = read_rgb(self.image)
        return undistort_image(img, self.K, self.lens, order=1, fill=0, K_size=self.K_size)

    def depth(self) -> np.ndarray:
        d = read_depth(self.depth_path, 1.0 / self.unit, invalid=(0,), npy_unit=self.unit)
        if self.mask is not None:
            d = np.where(resize_nearest(_read_mask(self.mask), d.shape), d, 0).astype(np.float32)
        return undistort_image(d, self.K, self.lens, order=0, fill=0, K_size=self.K_size)

    def label_ids(self) -> np.ndarray:
        ids = read_label_png(self.labels_path)
        return undistort_image(ids, self.K, self.lens, order=0, fill=IGNORE, K_size=self.K_size)


def _world_maps(meta: dict, o: NerfstudioOptions, src: Path) -> tuple[np.ndarray, np.ndarray]:
    """(poses' map, PLY's map): (4, 4) transforms taking the stored coordinates to the output world."""
    need_a = o.world != o.ply_world or o.world == World.original
    if not need_a:
        return np.eye(4), np.eye(4)
    if "applied_transform" not in meta:
        raise ValueError(f"{src}: no applied_transform, so scene.options.world=original / ply_world=original "
                         f"has no original frame to map to (keep them at saved)")
    A = _matrix(meta["applied_transform"], str(src), "applied_transform", ((3, 4), (4, 4)))
    check_rigid(A, f"{src}: applied_transform", "original_to_saved")
    scale = meta.get("applied_scale", 1.0)
    if _number(scale, str(src), "applied_scale") != 1.0:
        raise ValueError(f"{src}: applied_scale={scale} with scene.options.world/ply_world=original is not "
                         f"supported (keep world=saved and ply_world=saved)")
    A_inv = rigid_inverse(A)
    poses = A_inv if o.world == World.original else np.eye(4)
    # the PLY: from its own frame to the output one
    if o.ply_world == o.world:
        return poses, np.eye(4)
    return poses, (A_inv if o.world == World.original else A)


def load(cfg: SceneConfig, taxonomy: Taxonomy, sensor: Optional[SensorModel]) -> Scene:
    """``scene.source=nerfstudio``: the capture of ``scene.options`` (a :class:`NerfstudioOptions`)."""
    o: NerfstudioOptions = cfg.options
    given = Path(o.root)
    src = given if given.suffix.lower() == ".json" else given / o.transforms
    root = src.parent
    meta = read_transforms(src)
    unit = o.depth_unit_scale
    if unit is None:
        unit = _number(meta.get("depth_unit_scale_factor", 1e-3), str(src), "depth_unit_scale_factor")
        if unit <= 0:
            raise ValueError(f"{src}: depth_unit_scale_factor={unit}, expected > 0 metres per unit")
    pose_map, ply_map = _world_maps(meta, o, src)
    records = sorted(meta["frames"], key=lambda f: f["file_path"])  # nerfstudio sorts by file name
    frames, names, lenses = [], {}, {}
    for f in records:  # loop over frame records: metadata only, images are read lazily
        rel = f["file_path"]
        where = f"{src}: frame {rel}"
        lens = _lens(f, meta, where)
        if not lens.is_pinhole and not o.undistort:
            raise ValueError(f"{where}: camera_model {f.get('camera_model', meta.get('camera_model'))} "
                             f"({lens.text()}) is distorted and scene.options.undistort=false refuses "
                             f"distorted images (true resamples them to the pinhole camera)")
        vals = {}
        for k in _INTRINSICS:
            v = f.get(k, meta.get(k))
            if v is None:
                raise ValueError(f"{where}: no {k} (neither in the frame nor at the top level); nerfstudio "
                                 f"needs fl_x fl_y cx cy w h")
            vals[k] = _number(v, where, k)
        if vals["fl_x"] <= 0 or vals["fl_y"] <= 0 or vals["w"] < 1 or vals["h"] < 1:
            raise ValueError(f"{where}: fl_x={vals['fl_x']:g} fl_y={vals['fl_y']:g} w={vals['w']:g} "
                             f"h={vals['h']:g}, expected positive focal lengths and image size")
        K = np.array([[vals["fl_x"], 0.0, vals["cx"] - 0.5], [0.0, vals["fl_y"], vals["cy"] - 0.5], [0, 0, 1.0]])
        K_size = (int(vals["h"]), int(vals["w"]))
        c2w = _matrix(f["transform_matrix"], where, "transform_matrix", ((4, 4), (3, 4)))
        check_rigid(c2w, f"{where} transform_matrix", "camera_to_world")
        T_cw = rigid_inverse(pose_map @ c2w @ OPENGL_TO_OPENCV)
        name = Path(rel).stem
        if name in names:
            raise ValueError(f"{src}: frames {names[name]} and {rel} share the name {name} (the image's "
                             f"stem), expected one frame per name")
        names[name] = rel
        image = _frame_path(root, rel, o.downscale, "images_")
        if not image.is_file():
            raise FileNotFoundError(f"{where}: image {image} does not exist"
                                    + (f" (scene.options.downscale={o.downscale} reads images_{o.downscale}/)"
                                       if o.downscale > 1 else ""))
        depth = mask = None
        if f.get("depth_file_path"):
            depth = _frame_path(root, f["depth_file_path"], o.downscale, "depths_")
            depth = depth if depth.is_file() else root / f["depth_file_path"]
        if o.masks and f.get("mask_path"):
            mask = _frame_path(root, f["mask_path"], o.downscale, "masks_")
            mask = mask if mask.is_file() else root / f["mask_path"]
        labels = None
        if o.labels:
            lp = root / o.labels.replace("{stem}", name).replace("{name}", name)
            labels = lp if lp.is_file() else None
        fr = _Frame(name, K, K_size, lens, image, depth, mask, labels, unit)
        if not lens.is_pinhole:
            lenses[lens.text()] = lenses.get(lens.text(), 0) + 1
        frames.append(CapturedFrame(name=name, T_cw=T_cw, K=K, K_size=K_size,
                                    depth=fr.depth if depth is not None else None, rgb=fr.rgb,
                                    labels=fr.label_ids if labels is not None else None,
                                    K_from=f"{src} (frame {rel}: w h)", K_image=image))
    cloud = None
    if not o.cloud and meta.get("ply_file_path"):
        cloud = read_cloud(root / meta["ply_file_path"])
        if not np.array_equal(ply_map, np.eye(4)):
            p = cloud["points"].astype(np.float64) @ ply_map[:3, :3].T + ply_map[:3, 3]
            cloud["points"] = p.astype(np.float32)
            if cloud.get("normals") is not None:
                cloud["normals"] = (cloud["normals"] @ ply_map[:3, :3].T).astype(np.float32)
        cloud["source"] = f"{meta['ply_file_path']} (ply_file_path)"
    info = {"n_frames_found": len(records), "world": o.world.value}
    if lenses:
        info["undistorted"] = lenses
    name = root.resolve().name
    return capture_scene(name, frames, o, taxonomy, root=src, cloud=cloud, info=info)
