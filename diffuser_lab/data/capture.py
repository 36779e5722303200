"""A capture as its format lays it out on disk -> a :class:`Scene`: the one builder behind the
frame-based dataset formats (nerfstudio, COLMAP, Replica, path templates, ScanNet without a mesh,
ROS bags).

A format module finds its frames: a name, a pose, intrinsics *for a stated image size* and readers
for the depth, colour and label images (any may be missing), as :class:`CapturedFrame`; it declares
its keys as a dataclass extending :class:`CaptureOptions` (the keys every such format shares) and
calls :func:`capture_scene`, which makes

- **one resolution per frame**: the depth image's when the frame has depth, else the colour (or
  label) image's; the intrinsics scaled to it with pixel centres aligned wherever they were given
  for another size (ScanNet's 1296x968 colour intrinsics beside 640x480 depth, 320x240 labels);
  colour resized bilinearly, labels nearest;
- **the stated size checked against the image**: where a format states the size its K is for
  (transforms.json ``w h``, COLMAP's cameras, a ROS CameraInfo, an intrinsics file that says it),
  the image it describes (``CapturedFrame.K_image``, its header read, else the frame's own image)
  must be that size or a downscale of it that keeps the aspect ratio (nerfstudio's ``images_2``,
  Record3D's 7.5x smaller depth): K is then scaled and ``scene.frames.info["intrinsics"]`` (the
  summary's ``capture.intrinsics``) says so; anything else is one line naming both files
  (:func:`check_stated_size`);
- **the cloud**: a file (``options.cloud``: PLY, LAS or LAZ; else the format's own, e.g. nerfstudio's
  ``ply_file_path`` or COLMAP's points), else the frames' depth back-projected and merged on a
  ``options.cloud_voxel`` grid (:func:`fuse_depth`);
- **depth for the depth check when frames have none** (``options.visibility``): rendered per frame
  from a mesh (ray casting) or from the cloud itself (a point z-buffer whose splat radius follows
  the local point spacing, :mod:`diffuser_lab.data.visibility`), so the paper's depth check runs
  as usual; ``scene.frames.info["visibility"]`` says which and the run's summary prints it;
- **ground truth on the points**: the cloud's own labels, else (``options.gt_from_frames``) carried
  from the frames' label images by :func:`carry_frame_labels` (the rule is stated there).

Frames are read lazily, as every source's are. A format that can be followed while a recorder writes it
(``scene.options.follow``: the posed RGB-D folder, ROS 2 bags in MCAP) declares :class:`FollowOptions`
and makes its scene with :func:`followed_scene` (docs/online.md, "Following a live recorder").
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from diffuser_lab import progress
from diffuser_lab.config import Section, at_least, key, above
from diffuser_lab.data.clouds import read_cloud
from diffuser_lab.data.frames import Follow, FrameLoop, LazyFrames, without
from diffuser_lab.data.geometry import backproject, scaled_intrinsics, visible_projection, voxel_downsample
from diffuser_lab.data.mapping import ClassMapping, load_mapping, native_mapping
from diffuser_lab.data.images import image_size, resize_bilinear, resize_nearest
from diffuser_lab.data.scene import IGNORE, Frame, Scene, Taxonomy
from diffuser_lab.data.visibility import CloudDepth, MeshDepth

__all__ = ["Visibility", "CaptureOptions", "CapturedFrame", "capture_scene", "carry_frame_labels",
           "taxonomy_mapping", "to_taxonomy", "fuse_depth", "check_stated_size", "FollowPolicy", "FollowOptions",
           "followed_scene", "followed_capture"]


class Visibility(Enum):
    """Where the depth check's depth comes from."""

    auto = "auto"  # the frames' depth images; without them the mesh (options.mesh) or else the cloud
    depth = "depth"  # the frames' depth images (an error when a frame has none)
    mesh = "mesh"  # rendered from the triangle mesh options.mesh (ray casting)
    cloud = "cloud"  # rendered from the cloud: a point z-buffer, splat radius from the local spacing


@dataclass
class CaptureOptions(Section):
    """The keys every frame-based format shares (``scene.options.*``); a format's own options
    dataclass extends this one. Paths are relative to the current directory, except where a
    format says they are relative to its root."""

    KEY = "scene.options"
    cloud: Optional[str] = None  # PLY / LAS / LAZ of the points to label; null = the format's own cloud, else the depth back-projected
    cloud_voxel: float = key(0.02, above(0, "metres"))  # back-projected cloud: voxel edge of the merge
    cloud_stride: int = key(4, at_least(1))  # back-projected cloud: every n-th pixel of each depth image
    max_depth: Optional[float] = key(None, above(0, "metres", null=True))  # back-projected cloud: farther depth ignored
    frame_step: int = key(1, at_least(1))  # every n-th frame
    max_frames: Optional[int] = key(None, at_least(1, null=True))  # at most this many (after frame_step)
    mapping: Optional[str] = None  # label ids of label images / cloud labels -> taxonomy (shipped table or CSV); null = taxonomy ids
    visibility: Visibility = Visibility.auto  # the depth check's depth: depth images | mesh | cloud (rendered) | auto
    mesh: Optional[str] = None  # visibility=mesh (or auto without depth): a triangle mesh PLY in the cloud's frame
    splat: float = key(0.4, above(0))  # visibility=cloud: splat radius / the mean distance to a point's 4 nearest neighbours (0.4: best on real 7-Scenes depth, docs/layouts.md)
    splat_max_px: int = key(8, at_least(0))  # visibility=cloud: largest splat radius, pixels
    gt_from_frames: bool = True  # no labels in the cloud: carry the frames' label images to the points (carry_frame_labels)
    depth_tol: float = key(0.05, above(0, "metres"))  # gt_from_frames: the depth check of a pixel that sees a point


class FollowPolicy(Enum):
    """How a followed capture's frames are taken when they come faster than the map takes them
    (:meth:`diffuser_lab.data.frames.Follow.schedule`)."""

    all = "all"  # every frame, in order (the run falls behind a faster recorder): the closed capture's run
    newest = "newest"  # when frames wait: the newest first, then the waiting keyframes (scene.keyframe_*); the others skipped


@dataclass
class FollowOptions(Section):
    """The keys of a format that can be followed as a recorder writes it (``scene.options.follow*``;
    protocol=online only; docs/online.md, "Following a live recorder")."""

    KEY = "scene.options"
    follow: bool = False  # read the capture while a recorder writes it: each frame once complete (protocol=online only)
    follow_timeout: float = key(10.0, above(0, "seconds"))  # follow: the run ends when no new frame came for this long (or the capture is closed)
    follow_policy: FollowPolicy = FollowPolicy.newest  # follow: frames that come faster than the map takes them: all | newest (with keyframes)

    def follower(self, poll: Callable[[], bool], what: str) -> Follow:
        """The :class:`~diffuser_lab.data.frames.Follow` these keys ask for (with the format's
        ``frame_step`` and ``max_frames``) over the source's ``poll``."""
        return Follow(poll, what, timeout=self.follow_timeout, policy=self.follow_policy.value,
                      step=getattr(self, "frame_step", 1), limit=getattr(self, "max_frames", None))


@dataclass
class CapturedFrame:
    """One frame as a format found it.

    Attributes:
        name: the frame's name (file stem, image name, message stamp).
        T_cw: (4, 4) float64 world-to-camera, OpenCV camera (x right, y down, z forward), metres.
        K: (3, 3) float64 pinhole intrinsics, pixels, for an image of ``K_size``.
        K_size: (H, W) the intrinsics are for; None = the frame's own resolution.
        depth: reader -> (H, W) float32 z-depth, metres, 0 = none; None = the frame has no depth.
        rgb: reader -> (h, w, 3) uint8 colour, any size; None = no colour.
        labels: reader -> (h, w) integer label ids (the mapping's source ids), any size; None = none.
        size: (H, W) of the frame when it has no depth (colour / label image size); None = read it.
        K_from: where ``K_size`` is stated (the file, or the bag and its CameraInfo topic), for errors.
        K_image: the image file ``K_size`` describes (its header is read); None = the frame's own
            image (depth, else colour) as read.
    """

    name: str
    T_cw: np.ndarray
    K: np.ndarray
    K_size: Optional[tuple[int, int]] = None
    depth: Optional[Callable[[], np.ndarray]] = None
    rgb: Optional[Callable[[], np.ndarray]] = None
    labels: Optional[Callable[[], np.ndarray]] = None
    size: Optional[tuple[int, int]] = None
    K_from: Optional[str] = None
    K_image: Optional[str | Path] = None


def taxonomy_mapping(mapping, taxonomy: Taxonomy) -> Optional[ClassMapping]:
    """A mapping name / path / ClassMapping -> ClassMapping onto ``taxonomy`` (None: the
    taxonomy's own label ids, when it has any)."""
    if mapping is None:
        return native_mapping(taxonomy)
    if isinstance(mapping, ClassMapping):
        return mapping
    return load_mapping(mapping, taxonomy)


def to_taxonomy(ids: np.ndarray, mapping: Optional[ClassMapping], taxonomy: Taxonomy, what: str,
                hint: str = "scene.options.mapping translates another label space") -> np.ndarray:
    """Raw label ids -> (same shape) int16 taxonomy ids, via ``mapping`` or checked as they are.
    A negative raw id is a reader's "no label here" (a label file holds none: e.g. outside the
    distorted image after undistortion) and stays IGNORE."""
    if mapping is not None:
        ids = np.asarray(ids)
        none = ids < 0
        try:
            if not none.any():
                return mapping.apply(ids)[0]
            out = np.full(ids.shape, IGNORE, np.int16)
            out[~none] = mapping.apply(ids[~none])[0]
            return out
        except ValueError as e:
            raise ValueError(f"{what}: {e}") from None
    if ids.size and (ids.min() < IGNORE or ids.max() >= taxonomy.num_classes):
        raise ValueError(f"{what}: label ids in [{ids.min()}, {ids.max()}], expected {taxonomy.name} ids "
                         f"0..{taxonomy.num_classes - 1} ({hint})")
    return ids.astype(np.int16)


def _merge(pts: np.ndarray, cols: np.ndarray, w: np.ndarray, voxel_size: float):
    """Weighted voxel merge: (N, 3) points, (N, 3) colours and (N,) weights (point counts)
    -> (M, 3) float32 weighted centroids, (M, 3) float32 mean colours, (M,) float64 summed weights."""
    grid = voxel_downsample(pts, voxel_size)
    m = grid.points.shape[0]
    wsum = np.bincount(grid.inverse, weights=w, minlength=m)
    # Weight by point count so the result equals one voxelisation of all points (up to grid offsets).
    P = np.stack([np.bincount(grid.inverse, weights=pts[:, j] * w, minlength=m) for j in range(3)], 1)
    C = np.stack([np.bincount(grid.inverse, weights=cols[:, j] * w, minlength=m) for j in range(3)], 1)
    return (P / wsum[:, None]).astype(np.float32), (C / wsum[:, None]).astype(np.float32), wsum


def fuse_depth(frames: Sequence[Frame], voxel_size: float, stride: int, max_depth: float | None):
    """Back-project every frame's depth and merge on a voxel grid, one frame at a time.

    Per-frame voxelisation bounds what is kept per frame; the partial clouds are merged
    again whenever they grow past a few times the merged size, so memory follows the
    scene's extent, not the number of frames.
    Returns (M, 3) float32 points and (M, 3) uint8 colours (grey 128 without colour).
    """
    return _fuse_depth_frames(frames, voxel_size, stride, max_depth)


def _fuse_depth_frames(frames: Sequence[Frame], voxel_size: float, stride: int, max_depth: float | None):
    acc_p, acc_c, acc_w = [], [], []
    merged_size, pending = 0, 0
    for _, f in FrameLoop(frames, f"fusing depth into a cloud ({voxel_size:g} m voxels)"):  # loop over frames
        depth = f.depth
        if max_depth is not None:
            depth = np.where(depth <= max_depth, depth, 0).astype(np.float32)
        pts, pix = backproject(depth, f.K, f.T_cw, stride)
        if pts.shape[0] == 0:
            continue
        rgb = f.rgb[pix[:, 0], pix[:, 1]].astype(np.float32) if f.rgb is not None \
            else np.full((pts.shape[0], 3), 128.0, np.float32)
        p, c, w = _merge(pts, rgb, np.ones(pts.shape[0]), voxel_size)
        acc_p.append(p), acc_c.append(c), acc_w.append(w)
        pending += p.shape[0]
        if pending > max(4 * merged_size, 2_000_000):
            p, c, w = _merge(np.concatenate(acc_p), np.concatenate(acc_c), np.concatenate(acc_w), voxel_size)
            acc_p, acc_c, acc_w = [p], [c], [w]
            merged_size = pending = p.shape[0]
    if not acc_p:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    p, c, _ = _merge(np.concatenate(acc_p), np.concatenate(acc_c), np.concatenate(acc_w), voxel_size)
    return p, np.clip(np.rint(c), 0, 255).astype(np.uint8)


def check_stated_size(K_size: tuple[int, int], image: tuple[int, int], stated_in: str, image_name: str) -> str:
    """A size stated for K against the image it describes: equal (``""``), or the image a downscale of
    it by one factor that keeps the aspect ratio (each side the stated one / s, rounded: a text saying
    so); anything else is one ValueError naming both."""
    (H, W), (h, w) = (int(K_size[0]), int(K_size[1])), (int(image[0]), int(image[1]))
    if (h, w) == (H, W):
        return ""
    if 0 < h <= H and 0 < w <= W and abs(H * w / W - h) < 1.0 and abs(W * h / H - w) < 1.0:
        return f"K stated for {W}x{H} in {stated_in}, scaled by 1/{W / w:.4g} to the {w}x{h} images"
    raise ValueError(f"{stated_in}: K is stated for {W}x{H} (W x H) images, {image_name} is {w}x{h}: expected "
                     f"that size or a downscale of it that keeps the aspect ratio {W / H:.4g}")


def _build_frame(cf: CapturedFrame, mapping, taxonomy: Taxonomy, render, skip: frozenset = frozenset(),
                 info: Optional[dict] = None) -> Frame:
    """A :class:`Frame` at the depth's resolution (else the colour's), K scaled to it (its stated size
    checked first: :func:`check_stated_size`); ``skip``: parts left out (``rgb``: not read)."""
    depth = cf.depth() if cf.depth is not None else None
    stated = cf.K_size is not None
    seen = image_size(cf.K_image, "image") if stated and cf.K_image is not None else None  # its header
    # without depth the frame takes the colour image's size: the stated image's header, else the image read
    sized = depth is not None or cf.size is not None or seen is not None
    rgb = np.asarray(cf.rgb(), np.uint8) if cf.rgb is not None and ("rgb" not in skip or not sized) else None
    ids = np.asarray(cf.labels()) if cf.labels is not None else None
    if depth is not None:
        shape = depth.shape[:2]
    elif cf.size is not None or seen is not None:
        shape = tuple(int(v) for v in (cf.size if cf.size is not None else seen))
    elif rgb is not None or ids is not None:
        shape = (rgb if rgb is not None else ids).shape[:2]
    elif stated:
        shape = (int(cf.K_size[0]), int(cf.K_size[1]))
    else:
        raise ValueError(f"frame {cf.name}: no depth, colour or label image and no image size")
    K = np.array(cf.K, np.float64)
    if stated:
        name = str(cf.K_image) if seen is not None else \
            f"frame {cf.name}'s {'depth' if depth is not None else 'colour'} image"
        said = check_stated_size(cf.K_size, seen if seen is not None else shape,
                                 cf.K_from or f"frame {cf.name}'s intrinsics", name)
        if tuple(cf.K_size) != tuple(shape):
            K = scaled_intrinsics(K, tuple(cf.K_size), tuple(shape))
            if info is not None:
                info.setdefault("intrinsics", said or f"K stated for {cf.K_size[1]}x{cf.K_size[0]} in "
                                f"{cf.K_from or 'the intrinsics'}, scaled to the frames' {shape[1]}x{shape[0]}")
    if render is not None:  # visibility=mesh / cloud: rendered, at the depth image's size when there is one
        depth = render(K, cf.T_cw, shape)
    rgb = resize_bilinear(rgb, shape) if rgb is not None and "rgb" not in skip else None
    gt = None
    if ids is not None:
        gt = to_taxonomy(resize_nearest(ids, shape), mapping, taxonomy, f"frame {cf.name} labels")
    return Frame(name=cf.name, K=K, T_cw=np.asarray(cf.T_cw, np.float64), depth=np.asarray(depth, np.float32),
                 gt_labels=gt, rgb=rgb)


def carry_frame_labels(points: np.ndarray, frames: Sequence[Frame], num_classes: int,
                       depth_tol: float = 0.05) -> tuple[np.ndarray, dict]:
    """Ground truth on points from the frames' label images.

    The rule: every pixel of a frame's ground-truth label image that sees a point (the point
    projects to it and passes the depth check ``|z - depth| <= depth_tol``, as the evidence's
    pixel-to-point edges do) casts one vote for its label; the point takes the label with the
    most votes (ties: the lower class id); a point no labelled pixel sees is IGNORE.

    Args:
        points: (N, 3) float32 world metres. frames: with ``gt_labels`` (frames without are skipped).
    Returns:
        (N,) int16 labels and statistics: ``points_labelled``, ``points_disagreeing`` (views gave
        more than one label), ``vote_agreement`` (share of the votes for the chosen label).
    """
    n = points.shape[0]
    votes = np.zeros(n * num_classes, np.int32)
    for _, f in FrameLoop(without(frames, "rgb"), "carrying the frames' labels to the points"):  # loop over frames
        if f.gt_labels is None:
            continue
        idx, rows, cols = visible_projection(points, f, depth_tol)
        lab = f.gt_labels[rows, cols].astype(np.int64)
        ok = lab >= 0
        votes += np.bincount(idx[ok] * num_classes + lab[ok], minlength=n * num_classes).astype(np.int32)
    votes = votes.reshape(n, num_classes)
    total = votes.sum(1)
    labels = np.where(total > 0, votes.argmax(1), IGNORE).astype(np.int16)
    seen = total > 0
    top = votes.max(1)
    stats = {"points_labelled": int(seen.sum()),
             "points_disagreeing": int(((votes > 0).sum(1) > 1).sum()),
             "vote_agreement": float(top[seen].sum() / max(total[seen].sum(), 1))}
    return labels, stats


def _renderer(options: CaptureOptions, points: np.ndarray, has_depth: bool, root: Path):
    """(visibility text, render(K, T_cw, shape) -> depth or None)."""
    kind = Visibility(getattr(options.visibility, "value", options.visibility))
    if kind == Visibility.auto:
        kind = Visibility.depth if has_depth else (Visibility.mesh if options.mesh else Visibility.cloud)
    if kind == Visibility.depth:
        if not has_depth:
            raise ValueError(f"{root}: frames have no depth images, scene.options.visibility=depth expected them "
                             f"(visibility=cloud or mesh renders depth for the depth check)")
        return "depth images", None
    if kind == Visibility.mesh:
        if not options.mesh:
            raise ValueError("scene.options.visibility=mesh: scene.options.mesh names no mesh file (a triangle mesh PLY)")
        r = MeshDepth.from_file(options.mesh)
        return f"depth rendered from the mesh {Path(options.mesh).name}", r
    r = CloudDepth(points, splat=options.splat, max_radius_px=options.splat_max_px)
    return f"depth rendered from the cloud (splat {options.splat:g} x spacing, median {r.median_spacing * 100:.1f} cm)", r


def followed_scene(name: str, frames: LazyFrames, cloud: Optional[str], mapping: Optional[ClassMapping],
                   taxonomy: Taxonomy) -> Scene:
    """The scene of a capture followed as it is written: ``frames`` (a :class:`LazyFrames` made with
    ``follow=``) and the points of the ``cloud`` file (PLY / LAS / LAZ: an online run's given map; its
    ``label`` is ground truth, through ``mapping``), else none (a growing map builds its own from the
    frames; no cloud is fused from frames that have not been written yet)."""
    if cloud is None:
        return Scene(name=name, points=np.zeros((0, 3), np.float32), taxonomy=taxonomy, frames=frames)
    with progress.stage(f"reading point cloud {Path(cloud).name}"):
        pc = read_cloud(cloud)
    gt = to_taxonomy(np.asarray(pc["labels"]), mapping, taxonomy, f"{cloud} labels") if "labels" in pc else None
    return Scene(name=name, points=np.ascontiguousarray(pc["points"], np.float32), taxonomy=taxonomy, frames=frames,
                 normals=pc.get("normals"), colors=pc.get("colors"), gt_labels=gt)


def followed_capture(name: str, follow: Follow, options: CaptureOptions, taxonomy: Taxonomy,
                     info: Optional[dict] = None) -> Scene:
    """A capture format's scene followed as it is written: ``follow``'s items are :class:`CapturedFrame`
    (added by the format's poll), read as :func:`capture_scene` reads them; the cloud as
    :func:`followed_scene` says. ``info`` (kept by reference: the poll may add to it) gets ``follow``."""
    mapping = taxonomy_mapping(options.mapping, taxonomy)
    if mapping is not None:
        taxonomy = mapping.target
    info = info if info is not None else {}
    info["follow"] = follow.info
    frames = LazyFrames(0, lambda i, skip: _build_frame(follow.items[i], mapping, taxonomy, None, skip, info),
                        info=info, parts=("rgb",), follow=follow)
    return followed_scene(name, frames, options.cloud, mapping, taxonomy)


def capture_scene(name: str, frames: Sequence[CapturedFrame], options: CaptureOptions, taxonomy: Taxonomy, *,
                  root: Path | str = ".", cloud: Optional[dict] = None, info: Optional[dict] = None) -> Scene:
    """The scene of a capture (module docstring).

    Args:
        name: the scene's name. frames: in sequence order, before ``frame_step``/``max_frames``.
        options: the format's keys (a :class:`CaptureOptions`).
        root: the capture's folder (error messages).
        cloud: the format's own cloud when ``options.cloud`` is null: a dict as
            :func:`~diffuser_lab.data.clouds.read_cloud` returns (``points`` (N, 3) float32, optional
            ``colors``, ``normals``, ``labels``); None = the depth back-projected.
        info: the format's statistics for ``scene.frames.info``.
    """
    root = Path(root)
    frames = list(frames)[:: options.frame_step]
    if options.max_frames is not None:
        frames = frames[: options.max_frames]
    if not frames:
        raise ValueError(f"{root}: no frames (frame_step={options.frame_step}, max_frames={options.max_frames})")
    mapping = taxonomy_mapping(options.mapping, taxonomy)
    if mapping is not None:
        taxonomy = mapping.target
    has_depth = all(f.depth is not None for f in frames)
    first = frames[0]
    if first.K_size is not None and first.K_image is not None:  # the stated size against the first image, now
        check_stated_size(first.K_size, image_size(first.K_image, "image"), first.K_from or f"frame {first.name}'s "
                          f"intrinsics", str(first.K_image))
    if options.cloud:
        with progress.stage(f"reading point cloud {Path(options.cloud).name}"):
            cloud = read_cloud(options.cloud)
    info = dict(info or {})
    names, poses = [f.name for f in frames], [np.asarray(f.T_cw, np.float64) for f in frames]
    plain = LazyFrames(names, lambda i, skip: _build_frame(frames[i], mapping, taxonomy, None, skip, info),
                       info=info, poses=poses, parts=("rgb",))
    if cloud is None:
        if not has_depth:
            raise ValueError(f"{root}: frames have no depth images and no cloud is given "
                             f"(scene.options.cloud: a PLY / LAS / LAZ of the points to label)")
        points, colors = fuse_depth(plain, options.cloud_voxel, options.cloud_stride, options.max_depth)
        if points.shape[0] == 0:
            raise ValueError(f"{root}: no valid depth to build a point cloud from (max_depth={options.max_depth})")
        cloud = {"points": points, "colors": colors}
        info["cloud"] = f"back-projected from {len(frames)} frames' depth ({options.cloud_voxel:g} m voxels)"
    else:
        info.setdefault("cloud", f"{len(cloud['points']):,} points from {cloud.get('source', 'the capture')}")
    points = np.ascontiguousarray(cloud["points"], np.float32)
    text, render = _renderer(options, points, has_depth, root)
    info["visibility"] = text
    out = plain if render is None else LazyFrames(
        names, lambda i, skip: _build_frame(frames[i], mapping, taxonomy, render, skip, info), info=info,
        poses=poses, parts=("rgb",))
    gt = None
    if cloud.get("labels") is not None:
        gt = to_taxonomy(np.asarray(cloud["labels"]), mapping, taxonomy, f"{cloud.get('source', 'cloud')} labels")
    elif options.gt_from_frames and any(f.labels is not None for f in frames):
        gt, stats = carry_frame_labels(points, out, taxonomy.num_classes, options.depth_tol)
        info["gt_from_frames"] = stats
    return Scene(name=name, points=points, taxonomy=taxonomy, frames=out, normals=cloud.get("normals"),
                 colors=cloud.get("colors"), gt_labels=gt)
