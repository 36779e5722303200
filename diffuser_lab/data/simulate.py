"""Simulated 2D segmentation-network mistakes on ground-truth label images.

A real network's errors are spatially coherent, not salt noise: blurry/shifted
object boundaries, whole objects given a plausible wrong class, and blotches of a
wrong class inside large surfaces. :func:`simulate_predictions` draws all three
from streams keyed by the view's seed and by what each draw is for, by default
independently per call (i.e. per view).

A real network's mistakes are also correlated across views: a chair it calls a sofa in
one frame it calls a sofa in the next ones. With ``regions`` (:func:`surface_regions`:
each pixel's 3D surface region, from its depth and pose), a region's confusion is decided
by a hash of (``region_seed``, region), the same in every frame that sees it, and shown in
a frame with probability ``persistence``. ``output_stride`` decides labels on a coarse
grid (low-resolution output, blocky boundaries). Knobs and their calibration:
docs/simulated-network.md.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
from scipy import ndimage

from diffuser_lab import seeding
from diffuser_lab.seeding import Seed, hash64

from .scene import IGNORE, SCANNET20

__all__ = ["simulate_predictions", "surface_regions", "SurfaceRegions", "coarse_output", "DEFAULT_CONFUSIONS"]

DEFAULT_CONFUSIONS: dict[str, tuple[str, ...]] = {
    "wall": ("door", "picture", "curtain", "window", "building", "fence"),  # the last two: cityscapes19
    "floor": ("otherfurniture",),
    "cabinet": ("otherfurniture", "bookshelf", "counter", "desk"),
    "bed": ("sofa",),
    "chair": ("sofa", "otherfurniture", "table"),
    "sofa": ("chair", "bed"),
    "table": ("desk", "counter", "otherfurniture"),
    "door": ("wall", "cabinet"),
    "window": ("picture", "curtain", "wall"),
    "bookshelf": ("cabinet", "otherfurniture"),
    "picture": ("window", "wall"),
    "counter": ("cabinet", "table", "desk"),
    "desk": ("table", "cabinet"),
    "curtain": ("window", "shower curtain", "wall"),
    "refrigerator": ("cabinet", "door"),
    "shower curtain": ("curtain",),
    "toilet": ("sink", "bathtub"),
    "sink": ("counter", "toilet"),
    "bathtub": ("toilet", "sink"),
    "otherfurniture": ("cabinet", "table", "chair"),
    # Cityscapes-19 (scene=city)
    "road": ("sidewalk", "terrain"),
    "sidewalk": ("road", "terrain"),
    "building": ("wall", "fence", "vegetation"),
    "fence": ("wall", "vegetation", "building"),
    "pole": ("traffic sign", "traffic light", "building"),
    "traffic light": ("pole", "traffic sign"),
    "traffic sign": ("pole", "traffic light"),
    "vegetation": ("terrain", "building"),
    "terrain": ("vegetation", "sidewalk", "road"),
    "sky": ("building", "vegetation"),
    "person": ("rider",),
    "rider": ("person", "bicycle", "motorcycle"),
    "car": ("truck", "bus"),
    "truck": ("car", "bus"),
    "bus": ("truck", "train", "car"),
    "train": ("bus", "truck"),
    "motorcycle": ("bicycle", "rider"),
    "bicycle": ("motorcycle", "rider"),
}
"""Plausible confusions of a 2D network, keyed by ScanNet-20 and Cityscapes-19 class name (a class's
candidates not in the run's taxonomy are dropped, so each table serves the other unchanged)."""


def _confusion_lut(num_classes: int, class_names: Sequence[str] | None,
                   confusions: Mapping[str, Sequence[str]]) -> list[np.ndarray]:
    """Per class id, the (k,) int array of its plausible wrong classes (may be empty)."""
    out = [np.zeros(0, np.int64) for _ in range(num_classes)]
    if class_names is None:
        return out
    index = {n: i for i, n in enumerate(class_names)}
    for name, others in confusions.items():
        if name in index and index[name] < num_classes:
            out[index[name]] = np.array([index[o] for o in others if o in index and index[o] < num_classes
                                         and o != name], np.int64)
    return out


def _wrong_class(c: int, present: np.ndarray, lut: list[np.ndarray], num_classes: int, u: float) -> int:
    """A plausible wrong class for class c: from the confusion table, else a class
    present elsewhere in the image, else any other class; ``u`` in (0, 1) picks which."""
    for cand in (lut[c] if c < len(lut) else np.zeros(0, np.int64), present[present != c]):
        if len(cand):
            return int(cand[min(int(u * len(cand)), len(cand) - 1)])
    others = np.delete(np.arange(num_classes), c)
    return int(others[min(int(u * len(others)), len(others) - 1)]) if len(others) else c


def _bspline_matrix(n: int, scale_px: float) -> np.ndarray:
    """(n, g) float32 cubic B-spline weights mapping a coarse grid with ``scale_px``
    pixel spacing (first/last knot beyond the image) to n pixel centres."""
    g = int(np.ceil(n / scale_px)) + 3
    u = (np.arange(n) + 0.5) / scale_px + 1.0  # pixel position in knot units
    d = np.abs(u[:, None] - np.arange(g)[None, :])
    e = 2 - d  # cubes as products: numpy's float64 power rounds differently on AVX-512 CPUs
    w = np.where(d < 1, 2 / 3 - d * d + d * d * d / 2, np.where(d < 2, e * e * e / 6, 0.0))
    return w.astype(np.float32)


def _smooth_field(shape: tuple[int, int], scale_px: float, rng: np.random.Generator,
                  n: int = 1) -> np.ndarray:
    """(n, H, W) float32 smooth random fields with ~unit std: gaussian noise on a
    coarse grid with ``scale_px`` spacing, smoothed to pixels by a cubic B-spline
    (separable, two small matrix products)."""
    Ay, Ax = _bspline_matrix(shape[0], scale_px), _bspline_matrix(shape[1], scale_px)
    coarse = rng.standard_normal((n, Ay.shape[1], Ax.shape[1])).astype(np.float32)
    # einsum's own loops, not BLAS: OpenBLAS's kernels round differently on AVX2 and AVX-512 CPUs,
    # and a warp rounded to whole pixels would move a pixel where the two disagree
    f = np.einsum("nhx,wx->nhw", np.einsum("hy,nyx->nhx", Ay, coarse), Ax)
    # B-spline smoothing shrinks the variance (to ~0.3); renormalise.
    return f / max(float(f.std()), 1e-6)


def _unit(seed: int, keys: np.ndarray, stream: int) -> np.ndarray:
    """Uniform [0, 1) float64 per key: a counter-based generator seeded by (seed, key, stream),
    so a key gets the same draw in every frame, whatever the order frames are simulated in."""
    return (hash64(seed, stream, keys.astype(np.uint64)) >> np.uint64(11)).astype(np.float64) * 2.0**-53


@dataclass(frozen=True)
class SurfaceRegions:
    """Per pixel of one view, the 3D surface region it sees (:func:`surface_regions`).

    Attributes:
        region: (H, W) uint64 region key = hash(gt class, world voxel of ``region_size``); 0 = IGNORE pixel.
        cell: (H, W) uint64 key of the finer world cell (``region_size / 3``) inside the region:
            the unit of a region's partial confusion (``confuse_region_frac``).
        viewing: (H, W) float32 viewing difficulty in [0, 1]: half the range term
            min(z / view_range_m, 1), half the grazing term 1 - |cos(incidence)|.
    """

    region: np.ndarray
    cell: np.ndarray
    viewing: np.ndarray


def surface_regions(gt: np.ndarray, depth: np.ndarray, K: np.ndarray, T_cw: np.ndarray, *,
                    region_size: float = 0.5, view_range_m: float = 4.0, seed: int = 0) -> SurfaceRegions:
    """The 3D surface region each pixel sees: its ground-truth class and the world voxel (edge
    ``region_size`` metres) of its back-projected point, so the same wall patch or chair has the
    same key in every view. Pixels with a label but no depth take their nearest depth pixel's point.

    Args:
        gt: (H, W) int ground-truth class ids, IGNORE = no label.
        depth: (H, W) z-depth, metres, 0 = none.
        K: (3, 3) intrinsics; T_cw: (4, 4) world-to-camera, metres.
        region_size: voxel edge of a region, metres (> 0).
        view_range_m: range at which the range term of ``viewing`` saturates, metres.
        seed: offsets the voxel grid (so walls on round coordinates do not lie on voxel faces).
    """
    from scipy import ndimage as ndi

    H, W = gt.shape
    d = np.where(np.isfinite(depth), depth, 0.0).astype(np.float64)
    valid = gt != IGNORE
    has = d > 0
    if not has.any():  # no geometry at all: one region per class, seen head-on
        key = np.where(valid, hash64(gt.astype(np.int64) + 1) | np.uint64(1), np.uint64(0))
        return SurfaceRegions(key, key, np.zeros((H, W), np.float32))
    if not has[valid].all():  # labelled pixels without depth: the nearest pixel with depth
        idx = ndi.distance_transform_edt(~has, return_distances=False, return_indices=True)
        d = d[idx[0], idx[1]]
    rows, cols = np.mgrid[0:H, 0:W].astype(np.float64)
    Kinv = np.linalg.inv(K)
    rays = np.stack([cols, rows, np.ones_like(cols)], -1) @ Kinv.T  # (H, W, 3) camera rays, z = 1
    pc = rays * d[..., None]
    T_wc = np.linalg.inv(T_cw)
    pw = pc @ T_wc[:3, :3].T + T_wc[:3, 3]
    # a seeded grid offset: a surface exactly on a voxel face would flicker between two regions
    shift = _unit(seed, np.arange(3, dtype=np.uint64), 7) * region_size
    vox = np.floor((pw + shift) / region_size).astype(np.int64)
    cell = np.floor((pw + shift) / (region_size / 3.0)).astype(np.int64)
    cls = gt.astype(np.int64) + 1
    region = hash64(cls, vox[..., 0], vox[..., 1], vox[..., 2]) | np.uint64(1)
    sub = hash64(cls, cell[..., 0], cell[..., 1], cell[..., 2]) | np.uint64(1)
    zero = np.uint64(0)
    region, sub = np.where(valid, region, zero), np.where(valid, sub, zero)
    # incidence from the organised depth image's tangent vectors (a garbage normal at depth
    # edges reads as grazing, where a network also errs more)
    n = np.cross(np.gradient(pc, axis=1), np.gradient(pc, axis=0))
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.abs((n * rays).sum(-1)) / (np.linalg.norm(n, axis=-1) * np.linalg.norm(rays, axis=-1))
    cos = np.nan_to_num(cos, nan=0.0)
    viewing = 0.5 * np.clip(d / view_range_m, 0.0, 1.0) + 0.5 * (1.0 - np.clip(cos, 0.0, 1.0))
    return SurfaceRegions(region, sub, viewing.astype(np.float32))


def _wrong_classes(cls: np.ndarray, u: np.ndarray, lut: list[np.ndarray], num_classes: int) -> np.ndarray:
    """Vectorised :func:`_wrong_class` without the image-dependent fallback: for each class id in
    ``cls`` (K,) the candidate ``floor(u * n)`` of its confusion table, else another class."""
    n_c = np.array([len(x) for x in lut], np.int64)
    table = np.zeros((num_classes, max(1, int(n_c.max(initial=0)))), np.int64)
    for c, cand in enumerate(lut):  # loop over classes
        table[c, : len(cand)] = cand
    n = n_c[cls]
    pick = table[cls, np.minimum((u * np.maximum(n, 1)).astype(np.int64), np.maximum(n - 1, 0))]
    other = (cls + 1 + np.minimum((u * (num_classes - 1)).astype(np.int64), num_classes - 2)) % num_classes
    return np.where(n > 0, pick, other if num_classes > 1 else cls)


def _region_confusion(gt: np.ndarray, valid: np.ndarray, regions: SurfaceRegions, num_classes: int,
                      seed: Seed, lut: list[np.ndarray], *, p: float, max_frac: float,
                      region_seed: int, persistence: float, region_frac: float, view_gain: float) -> np.ndarray:
    """Step 1 with view-correlated mistakes: (H, W) int16 labels (see :func:`simulate_predictions`)."""
    out = gt.astype(np.int16, copy=True)
    keys = regions.region[valid]
    uniq, first, inv = np.unique(keys, return_index=True, return_inverse=True)
    inv = inv.ravel()
    n_r = len(uniq)
    cls = gt[valid][first].astype(np.int64)
    size = np.bincount(inv, minlength=n_r)
    view = np.bincount(inv, weights=regions.viewing[valid], minlength=n_r) / np.maximum(size, 1)
    p_r = np.minimum(1.0, p * (1.0 + view_gain * view))
    # the region's persistent decision (same in every frame) and this frame's own draw, each keyed
    # by the region
    shown = seeding.uniform(seed, "predictions.region_shown", uniq) < persistence
    u = np.where(shown, _unit(region_seed, uniq, 1), seeding.uniform(seed, "predictions.region", uniq))
    u_cls = np.where(shown, _unit(region_seed, uniq, 2), seeding.uniform(seed, "predictions.region_class", uniq))
    confused = (u < p_r) & (size <= max_frac * valid.sum())
    wrong = _wrong_classes(cls, u_cls, lut, num_classes)
    bad = confused[inv]
    if region_frac < 1.0:  # only part of a confused region: its finer world cells, also persistent
        cells = regions.cell[valid]
        u_cell = np.where(shown[inv], _unit(region_seed, cells, 3), seeding.uniform(seed, "predictions.cell", cells))
        bad &= u_cell < region_frac
    vals = out[valid]
    vals[bad] = wrong[inv[bad]]
    out[valid] = vals
    return out


def coarse_output(labels: np.ndarray, valid: np.ndarray, stride: int, num_classes: int) -> np.ndarray:
    """Low-resolution network output: each ``stride`` x ``stride`` cell gets the most frequent
    label of its valid pixels (ties: the lower class id), upsampled nearest, so boundaries are
    blocky. (H, W) int16; pixels not ``valid`` are IGNORE."""
    H, W = labels.shape
    W2 = -(-W // stride)
    rows, cols = np.nonzero(valid)
    cell = (rows // stride) * W2 + cols // stride
    key = cell.astype(np.int64) * num_classes + labels[rows, cols].astype(np.int64)
    u, cnt = np.unique(key, return_counts=True)
    ucell = u // num_classes
    order = np.lexsort((-cnt, ucell))  # per cell, the largest count first (stable: lower id on ties)
    head = order[np.r_[True, ucell[order][1:] != ucell[order][:-1]]]
    mode = np.full(-(-H // stride) * W2, IGNORE, np.int16)
    mode[ucell[head]] = (u[head] % num_classes).astype(np.int16)
    out = np.full((H, W), IGNORE, np.int16)
    out[rows, cols] = mode[cell]
    return out


def simulate_predictions(
    gt: np.ndarray,
    num_classes: int,
    seed: Seed,
    *,
    strength: float = 1.0,
    jitter_px: float = 3.0,
    jitter_scale_px: float = 16.0,
    confuse_prob: float = 0.2,
    confuse_max_frac: float = 0.3,
    blob_count: float = 2.0,
    blob_radius: float = 0.1,
    blob_roughness: float = 0.35,
    class_names: Sequence[str] | None = None,
    confusions: Mapping[str, Sequence[str]] | None = None,
    regions: SurfaceRegions | None = None,
    region_seed: int = 0,
    persistence: float = 1.0,
    confuse_region_frac: float = 1.0,
    view_gain: float = 0.0,
    output_stride: int = 1,
) -> np.ndarray:
    """Corrupt a ground-truth label image like a 2D segmentation network would.

    Mistakes (applied in this order, each scaled by ``strength``):

    1. Whole-region confusion: every connected region of one class in ``gt``
       (8-connected) is, with probability ``confuse_prob * strength``, relabelled
       entirely with a plausible wrong class (``confusions`` table, e.g. chair->sofa,
       table->desk; otherwise a class present elsewhere in the image; otherwise any
       class). Regions covering more than ``confuse_max_frac`` of the valid pixels
       are kept (a network rarely mislabels most of what it sees).
       With ``regions`` (view-correlated mistakes) the unit is a 3D surface region
       instead, and the draw is the region's own (see the ``regions`` argument).
    2. Blobs: Poisson(``blob_count * strength``) irregular smooth blobs, each painted
       with a plausible wrong class of the class under its centre.
    3. Boundary jitter: the label image is resampled (nearest neighbour) through a
       smooth random displacement field, so labels bleed a few pixels across
       object boundaries and thin structures break up.

    4. Low-resolution output (``output_stride`` > 1): :func:`coarse_output`.

    Pixels that are IGNORE in ``gt`` (no depth / no hit) stay IGNORE; valid pixels
    always receive a class in ``[0, num_classes)``. With the defaults of the last six
    arguments the result is bit-identical to the independent model's.

    Args:
        gt: (H, W) int ground-truth class ids, IGNORE = no label.
        num_classes: number of classes C.
        seed: the view's seed, an int or a key (``(predictions.seed, frame index)``); every draw is
            keyed by it and by what it is for (:mod:`diffuser_lab.seeding`): each 2D region by its
            class and first pixel, each 3D region by its key, each blob by its number, the warp by
            the view, so one region more or less changes no other draw.
        strength: global scale of all mistakes, >= 0; 0 returns ``gt`` exactly.
        jitter_px: std of the displacement field, pixels (times ``strength``).
        jitter_scale_px: correlation length of the displacement field, pixels
            (spacing of the random coarse grid it is interpolated from).
        confuse_prob: per-region probability of a whole-region confusion, [0, 1].
        confuse_max_frac: regions larger than this fraction of valid pixels are never
            confused wholesale, [0, 1].
        blob_count: mean number of blobs per image (Poisson).
        blob_radius: mean blob radius as a fraction of the image width (each blob's
            radius is uniform in [0.5, 1.5] times it).
        blob_roughness: relative amplitude of the smooth noise that makes blob
            outlines irregular (0 = discs).
        class_names: names of the C classes, used to look up ``confusions``;
            default: SCANNET20's names when C == 20, else no table.
        confusions: {class name: plausible wrong class names}; default
            :data:`DEFAULT_CONFUSIONS`.
        regions: this view's 3D surface regions (:func:`surface_regions`); None = the
            independent model (step 1 on the image's 2D connected regions). Given, a region is
            confused with probability ``confuse_prob * strength * (1 + view_gain * viewing)``
            (``viewing`` = the region's mean viewing difficulty in this view, [0, 1]) into a
            wrong class from the confusion table (else any other class), both decided by a
            generator seeded by (``region_seed``, region): the same in every view.
        region_seed: seed of the regions' persistent decisions (the run's ``predictions.seed``).
        persistence: probability, per region and view, that the view shows the region's
            persistent decision; otherwise the view draws its own (keyed by ``seed``), [0, 1].
        confuse_region_frac: share of a confused region that is wrong, (0, 1]: the region's
            finer world cells (edge ``region_size / 3``) each wrong with this probability
            (persistent as the region's decision is).
        view_gain: how much more likely a region is confused when seen from far or at a grazing
            angle, >= 0 (0 = viewing does not matter).
        output_stride: labels decided on ``output_stride``-pixel cells (the mode of each cell)
            and upsampled nearest; 1 = full resolution.

    Returns:
        (H, W) int16 predicted class ids.
    """
    gt = np.asarray(gt)
    out = gt.astype(np.int16, copy=True)
    if strength <= 0:
        return out
    H, W = gt.shape
    valid = gt != IGNORE
    n_valid = int(valid.sum())
    if n_valid == 0:
        return out
    if class_names is None and num_classes == SCANNET20.num_classes:
        class_names = SCANNET20.names
    lut = _confusion_lut(num_classes, class_names,
                         DEFAULT_CONFUSIONS if confusions is None else confusions)
    present = np.unique(gt[valid]).astype(np.int64)

    # 1. whole-region confusion (loop over classes and regions, not pixels)
    p = min(1.0, confuse_prob * strength)
    if p > 0 and regions is not None:
        out = _region_confusion(gt, valid, regions, num_classes, seed, lut, p=p, max_frac=confuse_max_frac,
                                region_seed=region_seed, persistence=persistence,
                                region_frac=confuse_region_frac, view_gain=view_gain)
    elif p > 0:
        comp = np.zeros((H, W), np.int32)
        comp_class: list[int] = []
        for c in present:
            lab, n = ndimage.label(gt == c, structure=np.ones((3, 3), bool))
            comp[lab > 0] = lab[lab > 0] + len(comp_class)
            comp_class += [int(c)] * n
        sizes = np.bincount(comp.ravel(), minlength=len(comp_class) + 1)[1:]
        ids, at = np.unique(comp.ravel(), return_index=True)
        first = np.zeros(len(comp_class) + 1, np.int64)
        first[ids] = at
        first = first[1:]  # each region's first pixel in raster order (region 0: the IGNORE pixels)
        cls = np.array(comp_class, np.int64)
        # a region's draws keyed by (class, first pixel): the same region, the same draws
        flip = (seeding.uniform(seed, "predictions.component", cls, first) < p) & (sizes <= confuse_max_frac * n_valid)
        u_cls = seeding.uniform(seed, "predictions.component_class", cls, first)
        region_lut = np.concatenate([[IGNORE], cls]).astype(np.int16)
        for r in np.flatnonzero(flip):  # loop over confused regions
            region_lut[r + 1] = _wrong_class(comp_class[r], present, lut, num_classes, u_cls[r])
        out = region_lut[comp]

    # 2. blobs with irregular outlines
    n_blobs = seeding.rng(seed, "predictions.blob_count").poisson(blob_count * strength) if blob_count > 0 else 0
    if n_blobs:
        yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
        rough = _smooth_field((H, W), max(4.0, blob_radius * W / 2), seeding.rng(seed, "predictions.blob_shapes"),
                              n_blobs)
        for k in range(n_blobs):  # loop over blobs
            u = seeding.uniform(seed, "predictions.blob", k, np.arange(4))  # centre y, x, radius, class
            cy, cx = H * u[0], W * u[1]
            rad = blob_radius * W * (0.5 + u[2])
            d = np.hypot(yy - cy, xx - cx) / rad
            mask = valid & (d + blob_roughness * rough[k] < 1.0)
            if not mask.any():
                continue
            under = gt[min(int(cy), H - 1), min(int(cx), W - 1)]
            if under == IGNORE:  # centre in a hole: use the blob's majority class
                under = np.bincount(gt[mask].astype(np.int64)).argmax()
            out[mask] = _wrong_class(int(under), present, lut, num_classes, u[3])

    # 3. boundary jitter: nearest-neighbour resampling through a smooth warp
    amp = jitter_px * strength
    if amp > 0:
        disp = _smooth_field((H, W), jitter_scale_px, seeding.rng(seed, "predictions.jitter"), 2) * amp
        ys = np.clip(np.rint(np.arange(H)[:, None] + disp[0]), 0, H - 1).astype(np.intp)
        xs = np.clip(np.rint(np.arange(W)[None, :] + disp[1]), 0, W - 1).astype(np.intp)
        warped = out[ys, xs]
        # A warp from a hole would leave a valid pixel unlabelled: keep its label.
        out = np.where(warped == IGNORE, out, warped)

    out[~valid] = IGNORE
    if output_stride > 1:
        out = coarse_output(out, valid, int(output_stride), num_classes)
    return out.astype(np.int16)
