"""Simulated 2D segmentation-network mistakes on ground-truth label images.

A real network's errors are spatially coherent, not salt noise: blurry/shifted
object boundaries, whole objects given a plausible wrong class, and blotches of a
wrong class inside large surfaces. :func:`simulate_predictions` draws all three,
independently per call (i.e. per view), from a seeded generator.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np
from scipy import ndimage

from .scene import IGNORE, SCANNET20

__all__ = ["simulate_predictions", "DEFAULT_CONFUSIONS"]

DEFAULT_CONFUSIONS: dict[str, tuple[str, ...]] = {
    "wall": ("door", "picture", "curtain", "window"),
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
}
"""Plausible confusions of a 2D network, keyed by ScanNet-20 class name."""


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


def _wrong_class(c: int, present: np.ndarray, lut: list[np.ndarray], num_classes: int,
                 rng: np.random.Generator) -> int:
    """A plausible wrong class for class c: from the confusion table, else a class
    present elsewhere in the image, else any other class."""
    for cand in (lut[c] if c < len(lut) else np.zeros(0, np.int64), present[present != c]):
        if len(cand):
            return int(rng.choice(cand))
    others = np.delete(np.arange(num_classes), c)
    return int(rng.choice(others)) if len(others) else c


def _bspline_matrix(n: int, scale_px: float) -> np.ndarray:
    """(n, g) float32 cubic B-spline weights mapping a coarse grid with ``scale_px``
    pixel spacing (first/last knot beyond the image) to n pixel centres."""
    g = int(np.ceil(n / scale_px)) + 3
    u = (np.arange(n) + 0.5) / scale_px + 1.0  # pixel position in knot units
    d = np.abs(u[:, None] - np.arange(g)[None, :])
    w = np.where(d < 1, 2 / 3 - d**2 + d**3 / 2, np.where(d < 2, (2 - d) ** 3 / 6, 0.0))
    return w.astype(np.float32)


def _smooth_field(shape: tuple[int, int], scale_px: float, rng: np.random.Generator,
                  n: int = 1) -> np.ndarray:
    """(n, H, W) float32 smooth random fields with ~unit std: gaussian noise on a
    coarse grid with ``scale_px`` spacing, smoothed to pixels by a cubic B-spline
    (separable, two small matrix products)."""
    Ay, Ax = _bspline_matrix(shape[0], scale_px), _bspline_matrix(shape[1], scale_px)
    coarse = rng.standard_normal((n, Ay.shape[1], Ax.shape[1])).astype(np.float32)
    f = Ay @ coarse @ Ax.T
    # B-spline smoothing shrinks the variance (to ~0.3); renormalise.
    return f / max(float(f.std()), 1e-6)


def simulate_predictions(
    gt: np.ndarray,
    num_classes: int,
    rng: np.random.Generator,
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
) -> np.ndarray:
    """Corrupt a ground-truth label image like a 2D segmentation network would.

    Mistakes (applied in this order, each scaled by ``strength``):

    1. Whole-region confusion: every connected region of one class in ``gt``
       (8-connected) is, with probability ``confuse_prob * strength``, relabelled
       entirely with a plausible wrong class (``confusions`` table, e.g. chair->sofa,
       table->desk; otherwise a class present elsewhere in the image; otherwise any
       class). Regions covering more than ``confuse_max_frac`` of the valid pixels
       are kept (a network rarely mislabels most of what it sees).
    2. Blobs: Poisson(``blob_count * strength``) irregular smooth blobs, each painted
       with a plausible wrong class of the class under its centre.
    3. Boundary jitter: the label image is resampled (nearest neighbour) through a
       smooth random displacement field, so labels bleed a few pixels across
       object boundaries and thin structures break up.

    Pixels that are IGNORE in ``gt`` (no depth / no hit) stay IGNORE; valid pixels
    always receive a class in ``[0, num_classes)``.

    Args:
        gt: (H, W) int ground-truth class ids, IGNORE = no label.
        num_classes: number of classes C.
        rng: random generator; the only source of randomness.
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
    if p > 0:
        comp = np.zeros((H, W), np.int32)
        comp_class: list[int] = []
        for c in present:
            lab, n = ndimage.label(gt == c, structure=np.ones((3, 3), bool))
            comp[lab > 0] = lab[lab > 0] + len(comp_class)
            comp_class += [int(c)] * n
        sizes = np.bincount(comp.ravel(), minlength=len(comp_class) + 1)[1:]
        flip = (rng.random(len(comp_class)) < p) & (sizes <= confuse_max_frac * n_valid)
        region_lut = np.concatenate([[IGNORE], np.array(comp_class, np.int64)]).astype(np.int16)
        for r in np.flatnonzero(flip):  # loop over confused regions
            region_lut[r + 1] = _wrong_class(comp_class[r], present, lut, num_classes, rng)
        out = region_lut[comp]

    # 2. blobs with irregular outlines
    n_blobs = rng.poisson(blob_count * strength) if blob_count > 0 else 0
    if n_blobs:
        yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
        rough = _smooth_field((H, W), max(4.0, blob_radius * W / 2), rng, n_blobs)
        for k in range(n_blobs):  # loop over blobs
            cy, cx = rng.uniform(0, H), rng.uniform(0, W)
            rad = blob_radius * W * rng.uniform(0.5, 1.5)
            d = np.hypot(yy - cy, xx - cx) / rad
            mask = valid & (d + blob_roughness * rough[k] < 1.0)
            if not mask.any():
                continue
            under = gt[min(int(cy), H - 1), min(int(cx), W - 1)]
            if under == IGNORE:  # centre in a hole: use the blob's majority class
                under = np.bincount(gt[mask].astype(np.int64)).argmax()
            out[mask] = _wrong_class(int(under), present, lut, num_classes, rng)

    # 3. boundary jitter: nearest-neighbour resampling through a smooth warp
    amp = jitter_px * strength
    if amp > 0:
        disp = _smooth_field((H, W), jitter_scale_px, rng, 2) * amp
        ys = np.clip(np.rint(np.arange(H)[:, None] + disp[0]), 0, H - 1).astype(np.intp)
        xs = np.clip(np.rint(np.arange(W)[None, :] + disp[1]), 0, W - 1).astype(np.intp)
        warped = out[ys, xs]
        # A warp from a hole would leave a valid pixel unlabelled: keep its label.
        out = np.where(warped == IGNORE, out, warped)

    out[~valid] = IGNORE
    return out.astype(np.int16)
