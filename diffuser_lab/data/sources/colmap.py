"""COLMAP sparse models (binary or text) with their images, MVS depth maps and clouds (``scene=colmap``).

Two layouts of ``root`` (https://colmap.github.io/format.html)::

    dense workspace (colmap image_undistorter,        project (colmap mapper)
    patch_match_stereo, stereo_fusion)
    images/<image name>       undistorted           images/<image name>       (key images)
    sparse/cameras.bin ...    PINHOLE cameras       sparse/0/cameras.bin ...  (key sparse)
    stereo/depth_maps/<image name>.geometric.bin
    fused.ply                 the fused cloud

or ``root`` = a sparse model folder itself (``images`` pointing at the images, e.g. ``../images``).
The model is ``cameras``, ``images``, ``points3D`` (``.bin``, else ``.txt``; COLMAP prefers binary
too), read with pycolmap after a check of the binary files' records (one line naming the file and
field for a truncated or foreign file, where pycolmap would say ``std::bad_alloc``).

Conventions converted:

- **pose**: ``images`` stores world-to-camera (qvec w x y z, tvec) in COLMAP's camera axes (x right,
  y down, z forward, as OpenCV): ``T_cw`` as it is; units are the model's (metres only when the
  model was scaled / georegistered).
- **pixel centre**: COLMAP puts the top-left pixel's centre at (0.5, 0.5) (src/colmap/sensor/models.h);
  here pixel centres are integers (OpenCV), so ``cx = cx_colmap - 0.5``, ``cy = cy_colmap - 0.5``.
- **cameras**: SIMPLE_PINHOLE / PINHOLE as they are; SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV
  resampled to a pinhole camera (``undistort``): the same principal point and image size, focal
  lengths scaled by the least factor >= 1 that leaves no blank pixel (as image_undistorter's
  default ``blank_pixels=0``); the models map onto :mod:`diffuser_lab.data.distortion`'s (the one
  undistortion of every source: :func:`~diffuser_lab.data.distortion.colmap_lens`), its map is
  computed once per camera and image size, colour bilinear, labels and depth nearest. Other models (fisheye, FOV,
  ...) are refused: undistort them with ``colmap image_undistorter`` and load its workspace.
- **depth**: ``stereo/depth_maps/<image name>.<geometric|photometric>.bin``: an ASCII header
  ``width&height&channels&`` then float32 little-endian, row-major (COLMAP's read_write_dense.py),
  z-depth in model units, <= 0 = none. Frames without a map are dropped (a warning says how many).
- **cloud** (``scene.options.cloud`` null): ``cloud_from=auto`` takes ``fused.ply`` in root, else the
  model's points3D (colours), else the depth maps back-projected.
"""
from __future__ import annotations

import mmap
import re
import struct
import tempfile
import warnings
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Optional

import numpy as np
from omegaconf import MISSING

from diffuser_lab.config import SceneConfig, key, rule
from diffuser_lab.data import inputs
from diffuser_lab.data.capture import CaptureOptions, CapturedFrame, capture_scene
from diffuser_lab.data.clouds import read_cloud, read_point_cloud_ply
from diffuser_lab.data.distortion import colmap_lens, focal_scale, undistort_image
from diffuser_lab.data.images import read_label_png, read_rgb
from diffuser_lab.data.scene import IGNORE, Scene, Taxonomy
from diffuser_lab.data.sensor import SensorModel

__all__ = ["ColmapOptions", "DepthMaps", "CloudFrom", "load", "read_model", "read_depth_map", "find_sparse"]

PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
DISTORTED_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
"""Camera models resampled to a pinhole camera; any other model is refused."""


class DepthMaps(Enum):
    """Which MVS depth maps of ``stereo/depth_maps`` the frames read."""

    geometric = "geometric"  # <image name>.geometric.bin (patch_match_stereo's geometric consistency pass)
    photometric = "photometric"  # <image name>.photometric.bin
    none = "none"  # no depth maps: depth rendered for the depth check (visibility)


class CloudFrom(Enum):
    """The cloud when ``scene.options.cloud`` is null."""

    auto = "auto"  # fused.ply in root, else the model's points3D, else the depth maps back-projected
    fused = "fused"  # root/fused.ply (stereo_fusion's output)
    points3D = "points3D"  # the sparse model's points (with colours)
    depth = "depth"  # the depth maps back-projected and voxel-merged (cloud_voxel, cloud_stride)


def _template(v: str) -> bool:
    return bool(v) and set(re.findall(r"{(\w*)}", v)) <= {"name", "stem"} and ("{name}" in v or "{stem}" in v)


@dataclass
class ColmapOptions(CaptureOptions):
    """``scene=colmap``: a COLMAP model, its images and (optionally) MVS depth maps; paths are
    relative to ``root`` (module docstring, docs/layouts.md)."""

    root: str = MISSING  # a dense workspace, a project with sparse/0, or a sparse model folder
    sparse: Optional[str] = None  # the model folder, relative to root; null = root, sparse or sparse/0 (the first with cameras.bin/.txt)
    images: str = "images"  # the image folder, relative to root (the model's image names are relative to it)
    stereo: str = "stereo"  # the MVS folder (depth_maps/ inside), relative to root
    depth_maps: DepthMaps = DepthMaps.geometric  # geometric | photometric | none; absent maps = no depth
    labels: Optional[str] = key(None, rule("a path template with {name} or {stem} (labels/{stem}.png) or null",
                                           _template, null=True))  # label images, relative to root: {name} = image name, {stem} = it without extension; null = none
    undistort: bool = True  # distorted cameras (SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV) resampled to pinhole; false = refused
    cloud_from: CloudFrom = CloudFrom.auto  # scene.options.cloud null: auto | fused | points3D | depth (CloudFrom)


# ---------------------------------------------------------------------------------------- the model

def find_sparse(root: Path, sparse: Optional[str]) -> tuple[Path, str]:
    """The model folder and its kind (``bin`` | ``txt``): ``root/sparse`` when given, else the first
    of root, root/sparse, root/sparse/0 holding ``cameras.bin`` (else ``cameras.txt``)."""
    candidates = [root / sparse] if sparse else [root, root / "sparse", root / "sparse" / "0"]
    for folder in candidates:  # loop over up to three folders
        for kind in ("bin", "txt"):
            if (folder / f"cameras.{kind}").is_file():
                return folder, kind
    where = ", ".join(str(c) for c in candidates)
    raise FileNotFoundError(f"no COLMAP sparse model (cameras/images/points3D .bin or .txt) in {where} "
                            f"(scene.options.root / scene.options.sparse)")


def _model_ids() -> dict:
    """COLMAP camera model name -> (model id, number of parameters), from pycolmap."""
    import pycolmap  # imported where used: the other scene sources never need it

    out = {}
    for name, mid in pycolmap.CameraModelId.__members__.items():  # loop over ~20 models
        if name != "INVALID":
            cam = pycolmap.Camera.create_from_model_name(0, name, 1.0, 1, 1)
            out[name] = (int(mid.value), len(cam.params))
    return out


class _Reader:
    """Bounds-checked little-endian reads of a binary model file (one line naming file, record, field)."""

    def __init__(self, path: Path, data):
        self.path, self.data, self.pos, self.where = path, data, 0, ""

    def take(self, fmt: str, field: str):
        n = struct.calcsize(fmt)
        if self.pos + n > len(self.data):
            raise ValueError(f"{self.path}: truncated at byte {len(self.data)}{self.where}, field {field} "
                             f"({n} bytes expected at byte {self.pos})")
        out = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += n
        return out

    def skip(self, n: int, field: str) -> None:
        if self.pos + n > len(self.data):
            raise ValueError(f"{self.path}: truncated at byte {len(self.data)}{self.where}, field {field} "
                             f"({n} bytes expected at byte {self.pos})")
        self.pos += n


def _check_cameras_bin(path: Path, models: dict) -> dict:
    """cameras.bin -> {camera id: model name}; checks every record (model id, parameter count, size)."""
    r = _Reader(path, path.read_bytes())
    (n,), by_id = r.take("<Q", "number of cameras"), {v[0]: k for k, v in models.items()}
    cams = {}
    for i in range(n):  # loop over cameras (a few)
        r.where = f" in camera record {i + 1} of {n}"
        cid, mid = r.take("<Ii", "camera_id, model_id")
        if mid not in by_id:
            raise ValueError(f"{path}: camera {cid} has model id {mid}, not a COLMAP camera model "
                             f"(ids {min(by_id)}..{max(by_id)})")
        w, h = r.take("<QQ", "width, height")
        r.skip(8 * models[by_id[mid]][1], f"params ({models[by_id[mid]][1]} doubles of {by_id[mid]})")
        if w == 0 or h == 0:
            raise ValueError(f"{path}: camera {cid} has width {w}, height {h}, expected positive pixel counts")
        cams[cid] = by_id[mid]
    if r.pos != len(r.data):
        raise ValueError(f"{path}: {len(r.data) - r.pos} bytes after the {n} camera records, expected none "
                         f"(not a COLMAP cameras.bin?)")
    return cams


POINT2D = np.dtype([("x", "<f8"), ("y", "<f8"), ("point3D_id", "<i8")])
"""One of images.bin's 2D points (point3D_id -1 = observes no 3D point)."""


def _check_images_bin(path: Path, cameras: dict) -> int:
    """images.bin: walks every record (pose, camera id, name, 2D points); the number of observations
    (2D points with a 3D point), the length of all tracks together in a consistent model."""
    if path.stat().st_size == 0:
        raise ValueError(f"{path}: empty file, expected COLMAP images.bin records")
    observations = 0
    with open(path, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as data:
        r = _Reader(path, data)
        (n,) = r.take("<Q", "number of images")
        for i in range(n):  # loop over images: metadata, each image's 2D points read at once
            r.where = f" in image record {i + 1} of {n}"
            iid, *_ = r.take("<I4d3d", "image_id, qvec, tvec")
            (cid,) = r.take("<I", "camera_id")
            end = data.find(b"\0", r.pos)
            if end < 0:
                r.skip(len(data) + 1 - r.pos, "name (no terminating NUL)")
            name = bytes(data[r.pos:min(end, r.pos + 200)]).decode(errors="replace")
            r.pos = end + 1
            (npts,) = r.take("<Q", "num_points2D")
            start = r.pos
            r.skip(POINT2D.itemsize * npts, f"points2D ({npts} x (x, y, point3D_id))")
            ids = np.frombuffer(data, POINT2D, count=npts, offset=start)["point3D_id"]
            observations += int(np.count_nonzero(ids != -1))
            del ids  # the mmap closes only without views into it
            if cid not in cameras:
                raise ValueError(f"{path}: image {iid} ({name}) has camera_id {cid}, not in cameras.bin "
                                 f"(ids {sorted(cameras)[:10]})")
        if r.pos != len(data):
            raise ValueError(f"{path}: {len(data) - r.pos} bytes after the {n} image records, expected none "
                             f"(not a COLMAP images.bin?)")
    return observations


def _check_points_bin(path: Path, observations: int) -> int:
    """points3D.bin: its size against the header's count and the observations of images.bin (51 bytes
    a point, 8 a track element). pycolmap would loop for ever on a truncated track, so the file is
    checked whole; walking the records would take a Python loop over points."""
    size = path.stat().st_size
    if size < 8:
        raise ValueError(f"{path}: truncated at byte {size}, field number of points (8 bytes)")
    with open(path, "rb") as fh:
        (n,) = struct.unpack("<Q", fh.read(8))
    need = 8 + 51 * n + 8 * observations
    if size != need:
        raise ValueError(f"{path}: {size} bytes, expected 8 + 51 x {n} points + 8 x {observations} track elements "
                         f"(the observations in images.bin) = {need}: truncated, or a foreign file")
    # a size that adds up can still hide a track length that lies (pycolmap then loops for minutes):
    # each record's length depends on the one before, so walk them (~0.5 s a million points)
    with open(path, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as data:
        pos, unpack = 8, struct.Struct("<Q").unpack_from
        for i in range(n):  # loop over 3D points: where record i + 1 starts depends on record i's track
            t = unpack(data, pos + 43)[0] if pos + 51 <= size else 0
            if pos + 51 + 8 * t > size:
                raise ValueError(f"{path}: point record {i + 1} of {n} (byte {pos}) with a track of {t:,} elements "
                                 f"ends past the end of the file ({size} bytes): a track length lies")
            pos += 51 + 8 * t
    if pos != size:
        raise ValueError(f"{path}: {size - pos} bytes after the {n} point records, expected none (a track length lies)")
    return n


def _check_cameras_txt(path: Path, models: dict) -> dict:
    """cameras.txt -> {camera id: model name}; each line ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]``."""
    cams = {}
    for k, line in enumerate(path.read_text(errors="replace").splitlines()):  # loop over cameras (a few)
        t = line.split()
        if not t or t[0].startswith("#"):
            continue
        where = f"{path}: line {k + 1}"
        if len(t) < 4 or not (t[0].isdigit() and t[2].isdigit() and t[3].isdigit()):
            raise ValueError(f"{where}: {line.strip()[:60]!r}, expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
        if t[1] not in models:
            raise ValueError(f"{where}: camera {t[0]} has model {t[1]}, not a COLMAP camera model "
                             f"(e.g. {', '.join(PINHOLE_MODELS + DISTORTED_MODELS)})")
        if len(t) - 4 != models[t[1]][1]:
            raise ValueError(f"{where}: camera {t[0]} ({t[1]}) has {len(t) - 4} parameters, expected "
                             f"{models[t[1]][1]}")
        cams[int(t[0])] = t[1]
    return cams


def _check_images_txt(path: Path, cameras: dict) -> None:
    """images.txt: two lines an image, ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` then its 2D points
    as ``X Y POINT3D_ID`` triples (the line may be empty), as COLMAP reads it."""
    lines = path.read_text(errors="replace").splitlines()
    k = 0
    while k < len(lines):  # loop over images: two lines each
        t = lines[k].split()
        k += 1
        if not t or t[0].startswith("#"):
            continue
        where = f"{path}: line {k}"
        try:
            ok = len(t) >= 10 and int(t[0]) >= 0 and all(np.isfinite(float(x)) for x in t[1:8]) and int(t[8]) >= 0
        except ValueError:
            ok = False
        if not ok:
            raise ValueError(f"{where}: {lines[k - 1].strip()[:60]!r}, expected IMAGE_ID QW QX QY QZ TX TY TZ "
                             f"CAMERA_ID NAME")
        if int(t[8]) not in cameras:
            raise ValueError(f"{where}: image {t[0]} ({t[9]}) has CAMERA_ID {t[8]}, not in cameras.txt")
        if k >= len(lines):
            raise ValueError(f"{where}: image {t[0]} has no POINTS2D line after it (truncated?), expected X Y "
                             f"POINT3D_ID triples or an empty line")
        pts = lines[k].split()
        k += 1
        if len(pts) % 3:
            raise ValueError(f"{path}: line {k}: {len(pts)} numbers as POINTS2D of image {t[0]}, expected X Y "
                             f"POINT3D_ID triples (truncated?)")


def read_model(folder: Path, kind: str):
    """The COLMAP model in ``folder`` (``kind`` bin | txt) -> (pycolmap.Reconstruction, the cameras
    file). The binary files' records (and cameras.txt's lines) are checked first."""
    import pycolmap  # imported where used: the other scene sources never need it

    files = {n: folder / f"{n}.{kind}" for n in ("cameras", "images", "points3D")}
    for f in files.values():
        if not f.is_file():
            raise FileNotFoundError(f"COLMAP model file {f} does not exist (a sparse model is cameras, images "
                                    f"and points3D .{kind})")
        inputs.record(f, "capture")
    models = _model_ids()
    if kind == "bin":
        cams = _check_cameras_bin(files["cameras"], models)
        observations = _check_images_bin(files["images"], cams)
        n_points = _check_points_bin(files["points3D"], observations)
    else:
        cams = _check_cameras_txt(files["cameras"], models)
        _check_images_txt(files["images"], cams)
        n_points = None
    rec = pycolmap.Reconstruction()
    try:
        (rec.read_binary if kind == "bin" else rec.read_text)(str(folder))
    except Exception as e:  # pycolmap raises ValueError / RuntimeError / MemoryError for foreign files
        msg = str(e).strip().splitlines()[-1] if str(e).strip() else ""
        # cameras and images passed the checks above: what is left is points3D and its tracks
        raise ValueError(f"{files['points3D']}: not readable with {files['images'].name} (pycolmap "
                         f"{type(e).__name__}: {msg[:200]})") from None
    if n_points is not None and rec.num_points3D() != n_points:
        raise ValueError(f"{files['points3D']}: header says {n_points} points, pycolmap read {rec.num_points3D()} "
                         f"(truncated or foreign file)")
    return rec, files["cameras"]


# ---------------------------------------------------------------------------------------- cameras

def _pinhole_K(cam) -> np.ndarray:
    """(3, 3) K of a pycolmap camera's focal lengths and principal point, pixel centres at integers."""
    return np.array([[cam.focal_length_x, 0.0, cam.principal_point_x - 0.5],
                     [0.0, cam.focal_length_y, cam.principal_point_y - 0.5],
                     [0.0, 0.0, 1.0]])


class _Lens:
    """A distorted COLMAP camera resampled to a pinhole one (:mod:`diffuser_lab.data.distortion`): ``K``
    (3, 3) for (``height``, ``width``), the camera's principal point, focal lengths times the least
    ``scale`` >= 1 that leaves no blank pixel; ``__call__(image, order, fill)`` resamples an image of
    any size (intrinsics scaled with pixel centres aligned)."""

    def __init__(self, cam, model: str, what: str):
        self.model, self.size = model, (int(cam.height), int(cam.width))
        self.K0, self.lens = colmap_lens(model, cam.params)
        try:
            self.scale = focal_scale(self.K0, self.size, self.lens, what)
        except ValueError as e:
            raise ValueError(f"{e} (undistort it with colmap image_undistorter)") from None
        self.K = self.K0.copy()
        self.K[0, 0] *= self.scale
        self.K[1, 1] *= self.scale

    def __call__(self, image: np.ndarray, order: int, fill=0) -> np.ndarray:
        return undistort_image(image, self.K0, self.lens, order=order, fill=fill, K_out=self.K, K_size=self.size)


# ---------------------------------------------------------------------------------------- depth maps

def read_depth_map(path: str | Path) -> np.ndarray:
    """COLMAP MVS depth map (``width&height&channels&`` then float32 little-endian, row-major) ->
    (H, W) float32 z-depth in model units, 0 = none (non-positive or non-finite stored values)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"depth map {path} does not exist")
    raw = inputs.read_bytes(path, "frames")
    m = re.match(rb"(\d+)&(\d+)&(\d+)&", raw[:64])
    if m is None:
        raise ValueError(f"{path}: no 'width&height&channels&' header, expected a COLMAP depth map")
    w, h, c = (int(g) for g in m.groups())
    data = raw[m.end():]
    if c != 1 or w == 0 or h == 0 or len(data) != 4 * w * h:
        raise ValueError(f"{path}: header {w}&{h}&{c}& with {len(data)} data bytes, expected one channel and "
                         f"4 x width x height = {4 * w * h * c} bytes of float32")
    d = np.frombuffer(data, "<f4").reshape(h, w).astype(np.float32)
    return np.where(np.isfinite(d) & (d > 0), d, 0).astype(np.float32)


# ---------------------------------------------------------------------------------------- the scene

def _camera(cam, cid: int, model: str, cams_file: Path, undistort: bool, cache: dict):
    """(K, _Lens or None) of a camera used by the frames; one line naming the file otherwise."""
    if cid in cache:
        return cache[cid]
    if model in PINHOLE_MODELS:
        out = (_pinhole_K(cam), None)
    elif model in DISTORTED_MODELS and undistort:
        u = _Lens(cam, model, f"{cams_file}: camera {cid} ({model})")
        out = (u.K, u)
    elif model in DISTORTED_MODELS:
        raise ValueError(f"{cams_file}: camera {cid} has model {model} (distorted) and scene.options.undistort="
                         f"false, expected SIMPLE_PINHOLE or PINHOLE (undistort=true resamples it)")
    else:
        raise ValueError(f"{cams_file}: camera {cid} has model {model}, expected one of "
                         f"{', '.join(PINHOLE_MODELS + DISTORTED_MODELS)} (undistort other models with "
                         f"colmap image_undistorter and load its dense workspace)")
    cache[cid] = out
    return out


def _points_cloud(rec, points_file: Path) -> dict:
    """The model's points3D -> read_cloud's dict (points, colours), through pycolmap's PLY export (no
    Python loop over points)."""
    with tempfile.TemporaryDirectory() as d:
        ply = Path(d) / "points3D.ply"
        rec.export_PLY(str(ply))
        out = read_point_cloud_ply(ply)
    out["source"] = points_file.name
    return out


def _rooted(root: Path, p: str) -> Path:
    q = Path(p).expanduser()
    return q if q.is_absolute() else root / q


def load(cfg: SceneConfig, taxonomy: Taxonomy, sensor: Optional[SensorModel]) -> Scene:
    """``scene.source=colmap``: the model, images and depth maps of ``scene.options`` (a
    :class:`ColmapOptions`; module docstring) -> a Scene through :func:`capture_scene`."""
    o: ColmapOptions = cfg.options
    root = Path(o.root).expanduser()
    if not root.is_dir():
        raise FileNotFoundError(f"COLMAP folder {root} does not exist (scene.options.root)")
    folder, kind = find_sparse(root, o.sparse)
    rec, cams_file = read_model(folder, kind)
    images_dir = _rooted(root, o.images)
    if not images_dir.is_dir():
        raise FileNotFoundError(f"image folder {images_dir} does not exist (scene.options.images={o.images!r}, "
                                f"relative to scene.options.root)")
    depth_dir = _rooted(root, o.stereo) / "depth_maps"
    depth_kind = o.depth_maps.value if isinstance(o.depth_maps, DepthMaps) else str(o.depth_maps)
    use_depth = depth_kind != "none" and depth_dir.is_dir()
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    if not images:
        raise ValueError(f"{folder / f'images.{kind}'}: no registered image (with a pose), expected at least one")
    cache: dict = {}
    frames, no_depth, missing = [], 0, []
    for im in images:  # loop over frames: metadata and file checks only, images are read lazily
        cid = int(im.camera_id)
        cam = rec.cameras[cid]
        K, und = _camera(cam, cid, cam.model.name, cams_file, o.undistort, cache)
        img_path = images_dir / im.name
        if not img_path.is_file():
            missing.append(img_path)
            continue
        depth_path = depth_dir / f"{im.name}.{depth_kind}.bin"
        if use_depth and not depth_path.is_file():
            no_depth += 1
            continue
        T = np.eye(4)
        T[:3] = im.cam_from_world().matrix()
        stem = str(Path(im.name).with_suffix(""))
        label_path = root / o.labels.format(name=im.name, stem=stem) if o.labels else None
        frames.append(CapturedFrame(
            name=stem, T_cw=T, K=K, K_size=(int(cam.height), int(cam.width)),
            K_from=f"{cams_file} (camera {cid})", K_image=img_path,
            depth=_reader(read_depth_map, depth_path, und, 0) if use_depth else None,
            rgb=_reader(read_rgb, img_path, und, 1),
            labels=_reader(read_label_png, label_path, und, 0, IGNORE) if label_path is not None and label_path.is_file()
            else None))
    if missing:
        raise FileNotFoundError(f"image {missing[0]} of the model does not exist ({len(missing)} of {len(images)} "
                                f"missing; scene.options.images={o.images!r} is the folder the model's names are "
                                f"relative to)")
    if no_depth:
        warnings.warn(f"{depth_dir}: {no_depth} of {len(images)} images have no {depth_kind} depth map: those "
                      f"frames are left out (scene.options.depth_maps=none uses every image)", stacklevel=2)
    if not frames:
        raise ValueError(f"{depth_dir}: no image has a {depth_kind} depth map (scene.options.depth_maps=none)")
    cloud, cloud_note = _cloud(o, root, rec, folder, kind)
    distorted = sorted(f"{u.model} (camera {c}, focal x{u.scale:.4g})" for c, (_, u) in cache.items()
                       if u is not None)
    info = {"colmap_model": f"{folder} ({kind}, {rec.num_images()} images, {rec.num_points3D()} points)",
            "images_registered": len(images),
            "depth_maps": f"{depth_kind} ({len(frames)})" if use_depth else "none",
            "frames_without_depth_map": no_depth,
            "undistorted_cameras": distorted}
    if cloud_note:
        info["cloud"] = cloud_note
    return capture_scene(root.resolve().name, frames, o, taxonomy, root=root, cloud=cloud, info=info)


def _reader(read, path: Path, und: Optional[_Lens], order: int, fill=0):
    """A lazy reader of ``path`` (resampled by ``und`` when the camera is distorted; ``fill`` where
    a pixel has no source, which the focal scale leaves none of but at rounding)."""
    if und is None:
        return lambda: read(path)
    return lambda: und(np.asarray(read(path)), order, fill)


def _cloud(o: ColmapOptions, root: Path, rec, folder: Path, kind: str):
    """(the format's cloud for capture_scene or None = depth back-projected, a note) by ``cloud_from``."""
    if o.cloud:
        return None, None  # capture_scene reads scene.options.cloud
    how = o.cloud_from.value if isinstance(o.cloud_from, CloudFrom) else str(o.cloud_from)
    fused = root / "fused.ply"
    if how == "fused" or (how == "auto" and fused.is_file()):
        if not fused.is_file():
            raise FileNotFoundError(f"fused cloud {fused} does not exist (scene.options.cloud_from=fused)")
        c = read_cloud(fused)
        return c, f"{len(c['points']):,} points from {fused.name} (stereo_fusion)"
    points_file = folder / f"points3D.{kind}"
    if how == "points3D" or (how == "auto" and rec.num_points3D() > 0):
        if rec.num_points3D() == 0:
            raise ValueError(f"{points_file}: no points, scene.options.cloud_from=points3D expected some")
        c = _points_cloud(rec, points_file)
        return c, f"{len(c['points']):,} points3D of the sparse model ({points_file.name})"
    return None, None
