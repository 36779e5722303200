"""ScanNet v2 scenes in the official export layout.

``root`` = ``.../scans/<scene>`` after ScanNet's ``SensReader`` export and unzipping
``<scene>_2d-label-filt.zip``::

    <scene>_vh_clean_2.ply            mesh: the points to label (vertices) with colours
    <scene>_vh_clean_2.labels.ply     same mesh, per-vertex ``ushort label`` = NYU40 id
    color/<i>.jpg                     1296x968 colour
    depth/<i>.png                     640x480 16-bit millimetres, 0 = no depth
    pose/<i>.txt                      4x4 camera-to-world (some are all -inf: tracking lost)
    intrinsic/intrinsic_depth.txt     4x4, upper-left 3x3 = K of the depth image
    intrinsic/intrinsic_color.txt     4x4, K of the colour image
    label-filt/<i>.png                NYU40 ids at colour resolution (train/val scenes only)

Resolution choice: frames are built at the DEPTH resolution (640x480) with the depth
intrinsics, because depth is what the occlusion check reads and it is never resampled
(resampling depth mixes foreground and background at edges). Colour and label-filt are
resized to it (bilinear / nearest, pixel-centre aligned). This is consistent because
ScanNet's depth intrinsics are the colour intrinsics scaled by 640/1296 x 480/968 with
pixel centres aligned (f' = f s, c' = (c + 0.5) s - 0.5, see :func:`scaled_intrinsics`):
the common calibration colour fx, fy, cx, cy = 1169.621, 1167.105, 646.295, 489.927 gives
exactly the common depth K 577.591, 578.730, 318.905, 242.684. Resizing labels to colour
resolution instead would need depth upsampling and 4x the pixels for no extra geometry.
The loader compares the two K files per scene and warns when they disagree by > 2 px.

Every file name above is a key of :class:`ScannetOptions` (``scene.options.*``, docs/formats/scannet.md).
Only the mesh, depth, pose and intrinsic_depth are required: without ``color/`` the frames carry
no RGB (the points keep the mesh's colours; predictions from files, ground truth or simulated
ones do not need it), without ``label-filt/`` they carry no ground truth.
"""
from __future__ import annotations

import re
import threading
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
from omegaconf import MISSING

from diffuser_lab import progress
from diffuser_lab.config import SceneConfig, Section, above, at_least, file_pattern, key, rule
from diffuser_lab.data.frames import LazyFrames
from diffuser_lab.data.geometry import scaled_intrinsics
from diffuser_lab.data.images import label_ids_in, read_depth, read_label_png, read_rgb, resize_nearest
from diffuser_lab.data.intrinsics import read_intrinsics
from diffuser_lab.data.mapping import ClassMapping, identity_mapping, load_mapping, native_mapping
from diffuser_lab.data.meshes import mesh_label_ids, read_labelled_mesh, vertex_normals
from diffuser_lab.data.poses import read_pose_c2w, rigid_inverse
from diffuser_lab.data.scene import SCANNET20, Frame, Scene, Taxonomy
from diffuser_lab.data.sensor import SensorModel

__all__ = ["ScannetOptions", "load_scannet", "scaled_intrinsics", "load", "label_ids"]


_SCENE_FILE = rule("a file name, optionally with {scene}", lambda v: v.replace("{scene}", "").count("{") == 0)


@dataclass
class ScannetOptions(Section):
    """A scene in ScanNet's export layout (diffuser_lab.data.sources.scannet). File names are
    relative to ``root``; ``{scene}`` = the root folder's name, ``{frame}`` = the frame number."""

    KEY = "scene.options"
    root: str = MISSING  # folder holding color/ depth/ pose/ intrinsic/ label-filt/ and the PLYs
    frame_step: int = key(10, at_least(1))  # paper: every 10th frame
    max_frames: Optional[int] = key(None, at_least(1, null=True))
    mapping: Optional[str] = "nyu40_to_scannet20"  # label ids -> taxonomy; null = the taxonomy's own ids
    mesh: str = key("{scene}_vh_clean_2.ply", _SCENE_FILE)  # the points to label (mesh vertices)
    labels_mesh: str = key("{scene}_vh_clean_2.labels.ply", _SCENE_FILE)  # per-vertex ground truth; optional file
    depth: str = key("depth/{frame}.png", file_pattern("frame"))  # 16-bit, depth_scale units per metre; frames are found by this
    color: str = key("color/{frame}.jpg", file_pattern("frame"))  # optional: without it frames carry no RGB
    pose: str = key("pose/{frame}.txt", file_pattern("frame"))  # 4x4 camera-to-world
    labels: str = key("label-filt/{frame}.png", file_pattern("frame"))  # optional ground-truth label images (mapping's source ids)
    intrinsic_depth: str = "intrinsic/intrinsic_depth.txt"
    intrinsic_color: str = "intrinsic/intrinsic_color.txt"  # optional, only checked against intrinsic_depth
    depth_scale: float = key(1000.0, above(0))  # raw depth units per metre



def _find_mesh(root: Path, pattern: str) -> Path | None:
    """``root / pattern`` with ``{scene}`` = the folder name, else the only file matching it with any scene."""
    p = root / pattern.format(scene=root.name)
    if p.is_file():
        return p
    hits = sorted(root.glob(pattern.replace("{scene}", "*")))
    return hits[0] if len(hits) == 1 else None


def _frame_ids(root: Path, pattern: str) -> list[str]:
    """Frame numbers (as written) of the files matching ``pattern`` (one ``{frame}``), by number."""
    rx = re.compile(re.escape(pattern).replace(re.escape("{frame}"), r"(\d+)"))
    found = (rx.fullmatch(p.relative_to(root).as_posix()) for p in root.glob(pattern.replace("{frame}", "*")))
    return sorted((m.group(1) for m in found if m), key=int)


def load_scannet(root, *, frame_step: int = 10, max_frames: int | None = None,
                 mapping: str | ClassMapping | None = "nyu40_to_scannet20", with_frames: bool = True,
                 layout: Optional[ScannetOptions] = None, taxonomy: Taxonomy = SCANNET20) -> Scene:
    """Load one ScanNet scene (layout in the module docstring).

    Args:
        root: the scene folder (its name, e.g. ``scene0470_00``, prefixes the PLY files).
        frame_step: use every frame_step-th frame (by sorted frame number).
        max_frames: at most this many frames (after dropping invalid poses).
        mapping: NYU40 -> ``taxonomy`` (shipped CSV name, path or ClassMapping, whose target
            becomes the scene's taxonomy); None = the label ids are ``taxonomy``'s own label ids.
        with_frames: False = mesh only (color/depth/pose folders may be absent).
        layout: the file names and depth scale (:class:`ScannetOptions`' keys other than ``root``,
            ``frame_step``, ``max_frames``, ``mapping``; None = ScanNet's export); colour and label-filt are optional.
    Returns:
        Scene: points = mesh vertices (V, 3) float32 metres, colors (V, 3) uint8,
        normals (V, 3) float32 unit vertex normals (winding-oriented), gt_labels (V,) int16
        (None without the labels PLY), frames lazily loaded at depth resolution with
        ``gt_labels`` from label-filt (None without it), ``rgb`` from color/ (None without it)
        and ``labels=None``. Frames whose
        pose is non-finite are skipped; ``scene.frames.info["n_invalid_pose"]`` counts them.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"ScanNet scene folder {root} does not exist")
    layout = layout if layout is not None else ScannetOptions(root=str(root))
    if frame_step < 1:
        raise ValueError(f"frame_step={frame_step}, expected >= 1")
    if mapping is None:
        mapping = native_mapping(taxonomy) or identity_mapping(taxonomy)
    elif not isinstance(mapping, ClassMapping):
        mapping = load_mapping(mapping, taxonomy)
    taxonomy = mapping.target

    mesh_path = _find_mesh(root, layout.mesh)
    if mesh_path is None:
        raise FileNotFoundError(f"{root}: no {layout.mesh.format(scene=root.name)} mesh (scene.options.mesh); "
                                f"without a mesh use scene=scannet_frames scene.options.root={root} (the cloud "
                                f"back-projected from the depth, ground truth carried from label-filt)")
    label_path = _find_mesh(root, layout.labels_mesh)
    with progress.stage(f"reading mesh {mesh_path.name}" + (" + labels" if label_path is not None else "")):
        vertices, triangles, _, colors = read_labelled_mesh(mesh_path)
        normals = vertex_normals(vertices, triangles)
        if label_path is not None:
            lv, _, vlabels, _ = read_labelled_mesh(label_path)
    gt = None
    if label_path is not None:
        if vlabels is None or lv.shape != vertices.shape:
            raise ValueError(f"{label_path}: expected a per-vertex 'label' for each of the {len(vertices)} "
                             f"vertices of {mesh_path.name}")
        try:
            gt = mapping.apply(vlabels)[0]
        except ValueError as e:
            raise ValueError(f"{label_path}: {e}") from None

    frames: LazyFrames | list = []
    if with_frames:
        frames = _scannet_frames(root, frame_step, max_frames, mapping, layout)
    return Scene(name=root.name, points=vertices, taxonomy=taxonomy, frames=frames, normals=normals,
                 colors=colors, gt_labels=gt)


def _scannet_frames(root: Path, frame_step: int, max_frames: int | None, mapping: ClassMapping,
                    L: ScannetOptions) -> LazyFrames:
    K = read_intrinsics(root / L.intrinsic_depth)
    ids = _frame_ids(root, L.depth)
    if not ids:
        raise FileNotFoundError(f"{root}: no {L.depth} depth images (scene.options.depth; "
                                f"use with_frames=False for the mesh only)")
    K_color = None
    if (root / L.intrinsic_color).is_file():
        K_color = read_intrinsics(root / L.intrinsic_color)

    kept, poses, n_invalid = [], [], 0
    selected = ids[::frame_step]
    with progress.stage("reading poses", total=len(selected), unit="pose") as bar:
        for fid in selected:  # loop over frames: validate poses up front (tiny files)
            if max_frames is not None and len(kept) >= max_frames:
                break
            bar.update()
            T_wc = read_pose_c2w(root / L.pose.format(frame=fid))
            if T_wc is None:
                n_invalid += 1  # tracking lost: ScanNet writes -inf poses
                continue
            kept.append(fid)
            poses.append(rigid_inverse(T_wc))
    if not kept:
        raise ValueError(f"{root}: no frame with a valid pose among {len(ids[::frame_step])} selected "
                         f"(frame_step={frame_step}, {n_invalid} non-finite poses)")
    # colour and labels are optional: present when the first frame has them (then every frame must)
    has_color = (root / L.color.format(frame=kept[0])).is_file()
    has_labels = (root / L.labels.format(frame=kept[0])).is_file()
    once = threading.Lock()  # the colour K is checked at the first frame read (frames are read on several threads)

    def load(i: int, skip: frozenset = frozenset()) -> Frame:
        fid = kept[i]
        depth = read_depth(root / L.depth.format(frame=fid), L.depth_scale, 0, (0,))
        rgb = read_rgb(root / L.color.format(frame=fid), depth.shape) if has_color and "rgb" not in skip else None
        gt = None
        if has_labels:
            lp = root / L.labels.format(frame=fid)
            ids_img = read_label_png(lp)
            if K_color is not None and once.acquire(blocking=False):  # never released: once
                Ks = scaled_intrinsics(K_color, ids_img.shape, depth.shape)
                err = np.abs(Ks[:2, :3] - K[:2, :3]).max()
                if err > 2.0:  # label pixels would not line up with depth pixels
                    warnings.warn(f"{root}: colour K scaled to depth resolution differs from intrinsic_depth by "
                                  f"{err:.1f} px; label-filt resized to depth may be misaligned", stacklevel=3)
            try:
                gt = mapping.apply(resize_nearest(ids_img, depth.shape))[0]
            except ValueError as e:
                raise ValueError(f"{lp}: {e}") from None
        return Frame(name=fid, K=K.copy(), T_cw=poses[i], depth=depth, gt_labels=gt, rgb=rgb)

    return LazyFrames(kept, load, info={"n_invalid_pose": n_invalid, "n_frames_found": len(ids),
                                        "has_color": has_color, "has_labels": has_labels},
                      poses=poses, parts=("rgb",))


def load(cfg: SceneConfig, taxonomy: Taxonomy, sensor: Optional[SensorModel]) -> Scene:
    """``scene.source=scannet``: the scene of the ``scene.options`` keys (its depth is real: the
    pipeline applies ``sensor`` with ``depth.apply_to_real``)."""
    c = cfg.options
    return load_scannet(c.root, frame_step=c.frame_step, max_frames=c.max_frames, mapping=c.mapping, layout=c,
                        taxonomy=taxonomy)


def label_ids(cfg: SceneConfig, n: int) -> list[tuple[np.ndarray, str]]:
    """``taxonomy=ids``: the first ``n`` ground-truth label images and the labels mesh, if there."""
    root = Path(cfg.options.root)
    labels = root / cfg.options.labels.replace("{frame}", "*")
    out = label_ids_in(list(labels.parent.glob(labels.name)), n, f"ground-truth ({labels.parent})")
    ply = root / cfg.options.labels_mesh.format(scene=root.name)
    return out + (mesh_label_ids(ply) if ply.is_file() else [])
