"""Path templates: a capture in any file layout, each file kind named by a template relative to ``root``.

A template holds ``{scene}`` (``scene.options.scene``, else the root folder's name) and ``{frame}``
(the frame's number) with Python format specs: ``depth/{scene}_{frame:06d}.pgm``,
``frame-{frame:06d}.color.jpg``, ``color/{frame}.jpg``; the files may sit in separate folders or one.
The frames are the files matching the depth template (the colour template when there is no depth),
sorted by number: the template becomes a regular expression (``{frame:06d}`` -> ``\\d{6,}``,
``{frame}`` -> ``\\d+``, a match kept only when the number formats back to the same name). Every other
per-frame file is the template formatted with that number, so ``label-filt/{frame}.png`` pairs with
``frame-{frame:06d}.depth.pgm``.

Depth: a 16-bit PNG / PGM (big-endian, as ScanNet's C++ SensReader writes it) / TIFF in
``depth_scale`` units per metre (null: the intrinsics file's, ScanNet ``_info.txt``'s
``m_depthShift``; else 1000), or ``.npy`` float metres. ``depth: null``: the frames have no depth
(the cloud comes from ``cloud``; the depth check's depth is rendered, :mod:`diffuser_lab.data.capture`).
Poses: 4x4 text, ``pose_convention`` camera_to_world | world_to_camera; non-finite poses (ScanNet
writes -inf where tracking was lost) skip the frame, counted in ``n_invalid_pose``. Intrinsics: a
template too (one shared file, or per frame with ``{frame}``) in ``intrinsics_format``
(:mod:`diffuser_lab.data.intrinsics`); the matrix is for the size the file states, else
``intrinsics_size``, else the depth image's; :func:`~diffuser_lab.data.capture.capture_scene`
scales it to each frame's resolution.
"""
from __future__ import annotations

import re
import string
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import List, Optional

from omegaconf import MISSING

from diffuser_lab import progress
from diffuser_lab.config import PoseConvention, SceneConfig, above, key, rule
from diffuser_lab.data.capture import CaptureOptions, CapturedFrame, capture_scene
from diffuser_lab.data.images import read_depth, read_label_png, read_rgb
from diffuser_lab.data.intrinsics import detect_format, read_intrinsics_file, scannet_depth_shift
from diffuser_lab.data.poses import pose_to_world_to_camera, read_pose_c2w
from diffuser_lab.data.scene import Scene, Taxonomy
from diffuser_lab.data.sensor import SensorModel


__all__ = ["TemplatesOptions", "IntrinsicsFormat", "template_fields", "template_regex", "find_frames", "load"]

PLACEHOLDERS = ("scene", "frame")
DEPTH_16BIT = (".png", ".pgm", ".tif", ".tiff")


def template_fields(template: str) -> list[tuple[str, str]]:
    """The ``(name, format spec)`` of each ``{...}`` of ``template`` (``string.Formatter().parse``).

    Raises:
        ValueError: unbalanced braces, a conversion (``!r``), a placeholder other than {scene}
            {frame}, or a spec that does not format a number ({frame}) / text ({scene}).
    """
    try:
        parts = list(string.Formatter().parse(template))
    except ValueError as e:
        raise ValueError(f"{e}") from None
    out = []
    for _, name, spec, conv in parts:  # a few fields
        if name is None:
            continue
        if name not in PLACEHOLDERS or conv:
            raise ValueError(f"placeholder {{{name}{'!' + conv if conv else ''}}}: expected {{scene}} or {{frame}} "
                             f"(with an optional format spec, e.g. {{frame:06d}})")
        try:
            format(1 if name == "frame" else "s", spec)
        except ValueError:
            raise ValueError(f"format spec {{{name}:{spec}}} does not format a "
                             f"{'frame number' if name == 'frame' else 'scene name'}") from None
        out.append((name, spec))
    return out


def _template_check(frame: str, null: bool = False):
    """A key's check: a relative path template ({scene}, {frame} with format specs; ``frame``:
    required | optional | none)."""
    def ok(v) -> bool:
        try:
            names = [n for n, _ in template_fields(v)]
        except ValueError:
            return False
        if not v or v.startswith("/") or (frame == "required" and "frame" not in names) or \
                (frame == "none" and "frame" in names):
            return False
        return True

    need = {"required": "with {frame}", "optional": "", "none": "without {frame}"}[frame]
    return rule(f"a path template relative to root {need} (placeholders {{scene}} {{frame}} only, "
                f"format specs allowed: {{frame:06d}})".replace("  ", " "), ok, null=null)


class IntrinsicsFormat(Enum):
    auto = "auto"  # by the file's name: *_info.txt scannet_info, .yaml ros_camera_info, .json json, else matrix
    matrix = "matrix"  # 3x3 text, or 4x4 with K upper-left
    scannet_info = "scannet_info"  # ScanNet's _info.txt (intrinsics_camera picks depth or colour)
    ros_camera_info = "ros_camera_info"  # ROS camera_info YAML (camera_calibration's); zero distortion only
    json = "json"  # fx fy cx cy (w h) or K, under intrinsics_key


class IntrinsicsCamera(Enum):
    depth = "depth"  # m_calibrationDepthIntrinsic, for m_depthWidth x m_depthHeight
    color = "color"  # m_calibrationColorIntrinsic, for m_colorWidth x m_colorHeight


_SIZE = rule("[H, W], positive, or null", lambda v: len(v) == 2 and min(v) > 0, null=True)


@dataclass
class TemplatesOptions(CaptureOptions):
    """``scene.source=templates``: each file kind a path template relative to ``root``."""

    root: str = MISSING  # the capture's folder; templates are relative to it
    scene: Optional[str] = None  # the {scene} placeholder; null = the root folder's name
    depth: Optional[str] = key(MISSING, _template_check("required", null=True))  # per-frame depth image (PNG/PGM/TIFF 16-bit, .npy metres); null = no depth
    color: Optional[str] = key(None, _template_check("required", null=True))  # per-frame colour image (any size); null = none
    pose: str = key(MISSING, _template_check("required"))  # per-frame 4x4 pose text file
    labels: Optional[str] = key(None, _template_check("required", null=True))  # per-frame ground-truth label image (mapping's ids); a frame without the file has none
    intrinsics: str = key(MISSING, _template_check("optional"))  # one shared file, or per frame with {frame}
    intrinsics_format: IntrinsicsFormat = IntrinsicsFormat.auto  # matrix | scannet_info | ros_camera_info | json | auto
    intrinsics_camera: IntrinsicsCamera = IntrinsicsCamera.depth  # scannet_info: which camera's K (depth | color)
    intrinsics_key: Optional[str] = None  # json: dotted key path of the object holding the intrinsics
    intrinsics_size: Optional[List[int]] = key(None, _SIZE)  # [H, W] the K is for when the file does not say; null = the depth (else colour) image's
    depth_scale: Optional[float] = key(None, above(0, null=True))  # 16-bit depth units per metre; null = the intrinsics file's (ScanNet m_depthShift), else 1000
    invalid_depth: List[int] = field(default_factory=lambda: [0, 65535])  # raw 16-bit values meaning no depth
    pose_convention: PoseConvention = PoseConvention.camera_to_world  # what the pose files hold


def template_regex(template: str, scene: str) -> re.Pattern:
    """``template`` -> a regex matching the relative paths it writes, ``{scene}`` = ``scene``,
    group ``frame`` the frame number as written (``{frame:06d}`` -> ``\\d{6,}``, ``{frame}`` -> ``\\d+``)."""
    out, seen = [], False
    for lit, name, spec, _ in string.Formatter().parse(template):  # a few fields
        out.append(re.escape(lit))
        if name == "scene":
            out.append(re.escape(format(scene, spec)))
        elif name == "frame":
            if seen:
                out.append("(?P=frame)")
                continue
            m = re.fullmatch(r"0?(\d*)d?", spec or "")
            width = m.group(1) if m and m.group(1) and spec.startswith("0") else ""
            out.append(rf"(?P<frame>\d{{{width},}})" if width else r"(?P<frame>\d+)")
            seen = True
    return re.compile("".join(out))


def find_frames(root: Path, template: str, scene: str, key_name: str) -> list[tuple[int, str]]:
    """``(number, the number as written)`` of the files ``template`` writes, sorted by number;
    a FileNotFoundError naming the template and root when there are none."""
    rx = template_regex(template, scene)
    glob = "".join(lit.replace("*", "[*]") + ("*" if name is not None else "")
                   for lit, name, _, _ in string.Formatter().parse(template))
    found = {}
    for p in root.glob(glob):  # one pass over the folder's matching names
        rel = p.relative_to(root).as_posix()
        m = rx.fullmatch(rel)
        if m and template.format(scene=scene, frame=int(m.group("frame"))) == rel:  # 06d: not 0000012
            found[int(m.group("frame"))] = m.group("frame")
    if not found:
        raise FileNotFoundError(f"{root}: no file matches scene.options.{key_name}={template!r} "
                                f"(scene={scene!r}; searched {root / glob})")
    return sorted(found.items())


def _check_depth_suffix(template: str) -> None:
    suffix = Path(template).suffix.lower()
    if suffix == ".exr":
        raise ValueError(f"scene.options.depth={template!r}: OpenEXR depth is not supported (no EXR reader "
                         f"installed); convert to .npy float metres or 16-bit PNG")
    if suffix not in DEPTH_16BIT + (".npy",):
        raise ValueError(f"scene.options.depth={template!r}: depth of suffix {suffix or '(none)'}, expected "
                         f"{', '.join(DEPTH_16BIT)} (16-bit) or .npy (float metres)")


def _intrinsics(o: TemplatesOptions, root: Path, scene: str, numbers: list[int]):
    """K (3, 3) and the (H, W) it is for (None = the frame's own) per frame number, and the depth
    scale the file states (ScanNet m_depthShift) or None."""
    fmt, cam = o.intrinsics_format.value, o.intrinsics_camera.value
    per_frame = "frame" in [n for n, _ in template_fields(o.intrinsics)]
    paths = [root / o.intrinsics.format(scene=scene, frame=n) for n in (numbers if per_frame else numbers[:1])]
    want = tuple(o.intrinsics_size) if o.intrinsics_size else None
    out = []
    for p in paths:  # one shared file, or one per frame
        K, size = read_intrinsics_file(p, fmt, cam, o.intrinsics_key)
        if size is not None and want is not None and size != want:
            raise ValueError(f"{p}: intrinsics for {size[0]}x{size[1]} (H x W) but scene.options.intrinsics_size="
                             f"{list(want)}: expected one statement of the size (set intrinsics_size: null)")
        out.append((K, size or want, str(p) if size is not None else "scene.options.intrinsics_size"))
    shift = scannet_depth_shift(paths[0]) if (fmt if fmt != "auto" else detect_format(paths[0])) == "scannet_info" \
        else None
    return (out if per_frame else out * len(numbers)), shift


def load(cfg: SceneConfig, taxonomy: Taxonomy, sensor: Optional[SensorModel]) -> Scene:
    """``scene.source=templates``: the capture the ``scene.options`` templates describe (real depth:
    the pipeline applies ``sensor`` with ``depth.apply_to_real``)."""
    o: TemplatesOptions = cfg.options
    root = Path(o.root)
    if not root.is_dir():
        raise FileNotFoundError(f"scene.options.root={o.root!r}: folder does not exist")
    scene = o.scene or root.resolve().name
    if o.depth is not None:
        _check_depth_suffix(o.depth)
    lead = "depth" if o.depth is not None else "color"
    if getattr(o, lead) is None:
        raise ValueError("scene.options.depth and scene.options.color are both null: expected a template for "
                         "one of them (the frames are found by it)")
    found = find_frames(root, getattr(o, lead), scene, lead)
    numbers = [n for n, _ in found]
    Ks, shift = _intrinsics(o, root, scene, numbers)
    depth_scale = o.depth_scale or shift or 1000.0
    conv = o.pose_convention.value
    frames, n_invalid, no_labels = [], 0, 0
    with progress.stage("reading poses", total=len(found), unit="pose") as bar:
        for (n, name), (K, K_size, K_from) in zip(found, Ks):  # one pass over the frames' small files
            bar.update()
            path = {k: root / getattr(o, k).format(scene=scene, frame=n)
                    for k in ("depth", "color", "pose", "labels") if getattr(o, k) is not None}
            if not path["pose"].is_file():
                raise FileNotFoundError(f"{path['pose']}: no pose file for frame {name} "
                                        f"(scene.options.pose={o.pose!r})")
            if "color" in path and not path["color"].is_file():
                raise FileNotFoundError(f"{path['color']}: no colour image for frame {name} "
                                        f"(scene.options.color={o.color!r}; null = no colour)")
            T = read_pose_c2w(path["pose"], convention=conv)
            if T is None:  # tracking lost (ScanNet's -inf poses)
                n_invalid += 1
                continue
            lp = path.get("labels")
            if lp is not None and not lp.is_file():
                no_labels, lp = no_labels + 1, None
            dp, cp = path.get("depth"), path.get("color")
            # the stated size is the colour camera's with intrinsics_camera=color (ScanNet's _info.txt), else
            # the depth image's (the colour's without depth)
            described = cp if (o.intrinsics_camera.value == "color" or dp is None) else dp
            frames.append(CapturedFrame(
                name=name, T_cw=pose_to_world_to_camera(T, conv), K=K, K_size=K_size, K_from=K_from,
                K_image=described if K_size is not None else None,
                depth=(lambda p=dp: read_depth(p, depth_scale, 0, tuple(o.invalid_depth))) if dp is not None else None,
                rgb=(lambda p=cp: read_rgb(p)) if cp is not None else None,
                labels=(lambda p=lp: read_label_png(p)) if lp is not None else None))
    if not frames:
        raise ValueError(f"{root}: all {len(found)} frames have non-finite poses (scene.options.pose={o.pose!r})")
    if o.labels is not None and no_labels == len(found):
        raise FileNotFoundError(f"{root}: no file matches scene.options.labels={o.labels!r} for any frame "
                                f"(null = no ground-truth label images)")
    info = {"n_frames_found": len(found), "n_invalid_pose": n_invalid, "n_without_labels": no_labels,
            "depth_scale": depth_scale if o.depth is not None else None}
    return capture_scene(scene, frames, o, taxonomy, root=root, info=info)
