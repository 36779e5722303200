"""A structured-light RGB-D sensor model for rendered (perfect) depth images.

Rendered depth is exact; depth from a Kinect-class sensor is not. :class:`SensorModel` turns a
perfect z-depth image into one with the sensor's main defects, in this order:

1. **Lateral noise** at depth edges: within ``ceil(3 sigma_L)`` pixels of a depth discontinuity
   each pixel takes the depth (and normal) of the pixel at a gaussian offset with
   ``sigma_L(theta) = lateral_scale * (0.8 + 0.035 theta / (pi/2 - theta))`` Kinect pixels (640 px
   wide; scaled by ``W / 640`` to the image, i.e. the same angular noise), so that object outlines
   become ragged. On continuous surfaces the same offset would only move the
   depth along the local slope, which the axial angle term already covers, so it is not applied.
2. **Projector shadows**: the IR projector sits ``projector_baseline`` metres to the camera's right
   (+x); a background pixel whose surface the projector cannot see past a nearer object gets no
   depth. The test is exact for a rectified pair: along an image row a pixel ``u`` with disparity
   ``d = fx * b / z`` is lit iff ``u - d`` is smaller than ``u2 - d(u2)`` for every ``u2 > u``.
   Shadows therefore lie on the left of foreground objects and are ``fx * b * (1/z_near - 1/z_far)``
   pixels wide.
3. **Edge holes**: pixels on either side of a depth jump (a 4-neighbour whose depth differs by more
   than ``edge_jump`` times the nearer depth), dilated by ``edge_hole_px - 1`` pixels (0 = none).
4. **Grazing-angle holes**: pixels whose incidence angle (between the viewing ray and the surface
   normal) exceeds ``max_incidence_deg``.
5. **Axial noise**, gaussian with (Nguyen et al. 2012, Eq. 6, fitted for 10 < theta < 60 deg and
   extended with their angle term above 60 deg)::

       sigma_z(z, theta) = axial_scale * (0.0012 + 0.0019 (z - 0.4)^2)                 [m]
                         + axial_scale * 0.0001 / sqrt(z) * theta^2 / (pi/2 - theta)^2  (theta > 60 deg)

6. **Valid range**: measured depth outside ``[min_range, max_range]`` metres is no return (Kinect v1:
   0.5-4.5 m in default mode).
7. **Quantisation**: ``mm`` rounds to millimetres (16-bit PNG depth as ScanNet / 7-Scenes store it);
   ``disparity`` rounds the disparity ``f b / z`` of the Kinect's IR pair (f = 580 px, b = 7.5 cm,
   1/8 px sub-pixel steps; Khoshelham & Elberink 2012), i.e. depth steps of ``z^2 / (f b) / 8``
   (2.9 mm at 1 m, 4.6 cm at 4 m); ``none`` keeps float depth.

Every random draw of frame ``index`` comes from ``default_rng([seed, index, _STREAM])``, so a
frame's noise does not depend on which other frames were drawn or in which order.

References:
    C. V. Nguyen, S. Izadi, D. Lovell, "Modeling Kinect Sensor Noise for Improved 3D Reconstruction
    and Tracking", 3DIMPVT 2012, pp. 524-530 (axial sigma_z(z, theta), lateral sigma_L(theta)).
    K. Khoshelham, S. O. Elberink, "Accuracy and Resolution of Kinect Depth Data for Indoor Mapping
    Applications", Sensors 12(2):1437-1454, 2012 (disparity quantisation, 1/8 px, f b).

Conventions: depth (H, W) float32 z-depth in metres along the optical axis, 0 = no depth; K (3, 3)
pixels with pixel centres at integer coordinates; camera x right, y down, z forward.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Iterable, Optional, Sequence

import numpy as np
from scipy import ndimage

from diffuser_lab.config import DepthModel, DepthNoiseConfig

from .frames import LazyFrames
from .geometry import normals_from_depth

__all__ = [
    "SensorModel",
    "sensor_model",
    "axial_sigma",
    "lateral_sigma_px",
    "incidence_angles",
    "normals_from_depth",
    "depth_jumps",
    "projector_shadow",
    "depth_error_report",
    "format_depth_report",
    "depth_hole_stats",
    "format_hole_stats",
    "noisy_frames",
    "DEFAULT_BINS",
]

_STREAM = 0x5E45  # separates the sensor's random stream from the other users of the same seed
DEFAULT_BINS = (0.5, 1.0, 2.0, 3.0, 4.5)  # metres, the report's range bins


def axial_sigma(z: np.ndarray, theta: np.ndarray | float = 0.0) -> np.ndarray:
    """Nguyen et al. (2012) axial noise std in metres at z-depth ``z`` (m) and incidence ``theta`` (rad).

    ``0.0012 + 0.0019 (z - 0.4)^2``, plus ``0.0001 / sqrt(z) * theta^2 / (pi/2 - theta)^2`` where
    theta > 60 deg (the paper fits the first term for 10-60 deg and adds the second beyond).
    """
    z = np.asarray(z, np.float64)
    theta = np.broadcast_to(np.asarray(theta, np.float64), z.shape)
    s = 0.0012 + 0.0019 * (z - 0.4) ** 2
    steep = theta > np.deg2rad(60.0)
    th = np.minimum(theta, np.deg2rad(89.9))  # the term diverges at 90 deg; grazing pixels are holes anyway
    angle = 0.0001 / np.sqrt(np.maximum(z, 1e-6)) * th**2 / (np.pi / 2 - th) ** 2
    return s + np.where(steep, angle, 0.0)


def lateral_sigma_px(theta: np.ndarray | float) -> np.ndarray:
    """Nguyen et al. (2012) lateral noise std in pixels (640x480 Kinect) at incidence ``theta`` (rad):
    ``0.8 + 0.035 theta / (pi/2 - theta)``."""
    th = np.minimum(np.asarray(theta, np.float64), np.deg2rad(89.9))
    return 0.8 + 0.035 * th / (np.pi / 2 - th)


def _rays(K: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) float64 camera-frame ray directions with unit z through every pixel centre."""
    h, w = shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)


def incidence_angles(normals: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W) float64 angle in radians between each pixel's viewing ray and the surface normal.

    Args:
        normals: (H, W, 3) camera-frame normals (any sign, any length; zero = unknown -> pi/2).
        K: (3, 3) intrinsics, pixels.
    """
    r = _rays(K, normals.shape[:2])
    n = np.asarray(normals, np.float64)
    num = np.abs(np.einsum("hwk,hwk->hw", r, n))
    den = np.linalg.norm(r, axis=-1) * np.linalg.norm(n, axis=-1)
    cos = np.where(den > 0, num / np.maximum(den, 1e-30), 0.0)
    return np.arccos(np.clip(cos, 0.0, 1.0))


def depth_jumps(depth: np.ndarray, rel: float) -> np.ndarray:
    """(H, W) bool: the pixel has a valid 4-neighbour whose depth differs by more than ``rel`` times
    the nearer of the two depths (both pixels of a jump are marked; pixels without depth never)."""
    d = np.asarray(depth, np.float64)
    out = np.zeros(d.shape, bool)
    for axis in (0, 1):
        a = d[:-1] if axis == 0 else d[:, :-1]
        b = d[1:] if axis == 0 else d[:, 1:]
        jump = (a > 0) & (b > 0) & (np.abs(a - b) > rel * np.minimum(a, b))
        if axis == 0:
            out[:-1] |= jump
            out[1:] |= jump
        else:
            out[:, :-1] |= jump
            out[:, 1:] |= jump
    return out


def projector_shadow(depth: np.ndarray, fx: float, baseline: float) -> np.ndarray:
    """(H, W) bool: pixels the projector (``baseline`` metres to the camera's +x) cannot light.

    A pixel ``u`` with disparity ``d = fx b / z`` is lit iff ``u - d(u) < min_{u2 > u, valid} (u2 - d(u2))``
    in its row (the projector's rays keep their left-to-right order on visible surfaces).
    """
    d = np.asarray(depth, np.float64)
    valid = d > 0
    u = np.arange(d.shape[1], dtype=np.float64)[None, :]
    s = np.where(valid, u - fx * baseline / np.where(valid, d, 1.0), np.inf)
    # min over u2 > u: reversed running minimum, shifted by one column
    run = np.minimum.accumulate(s[:, ::-1], axis=1)[:, ::-1]
    right = np.concatenate([run[:, 1:], np.full((d.shape[0], 1), np.inf)], axis=1)
    return valid & (s >= right - 1e-9)


@dataclass(frozen=True)
class SensorModel:
    """A Kinect-v1-like depth sensor (module doc: what each key does and its source).

    Attributes:
        seed: with the frame index, seeds every random draw.
        axial_scale: multiplies Nguyen's sigma_z(z, theta); 0 = no axial noise.
        lateral_scale: multiplies Nguyen's sigma_L(theta) (pixels); 0 = no lateral noise.
        projector_baseline: metres from the IR camera to the projector (+x); 0 = no shadows.
        edge_jump: relative depth jump between 4-neighbours that marks a discontinuity.
        edge_hole_px: hole band along discontinuities: the pixels either side, dilated by this - 1; 0 = none.
        max_incidence_deg: no depth where the incidence angle exceeds this (90 = never).
        min_range, max_range: metres; measured depth outside is no return.
        quantization: "mm", "disparity" or "none".
        disparity_focal_px, disparity_baseline, disparity_subpixel: the IR pair of the ``disparity``
            quantisation (pixels, metres, pixels).
    """

    seed: int = 0
    axial_scale: float = 1.0
    lateral_scale: float = 1.0
    projector_baseline: float = 0.075
    edge_jump: float = 0.05
    edge_hole_px: int = 0  # real ScanNet depth: 44% of jumps have no hole (docs/sensor.md)
    max_incidence_deg: float = 80.0
    min_range: float = 0.5
    max_range: float = 4.5
    quantization: str = "mm"
    disparity_focal_px: float = 580.0
    disparity_baseline: float = 0.075
    disparity_subpixel: float = 0.125

    def __post_init__(self) -> None:
        if self.quantization not in ("mm", "disparity", "none"):
            raise ValueError(f"quantization={self.quantization!r}: expected mm, disparity or none")

    def rng(self, index: int) -> np.random.Generator:
        return np.random.default_rng([int(self.seed) % 2**32, int(index) % 2**32, _STREAM])

    def quantize(self, z: np.ndarray) -> np.ndarray:
        """Quantised depth (same shape, metres; 0 stays 0)."""
        z = np.asarray(z, np.float64)
        if self.quantization == "mm":
            return np.round(z * 1000.0) / 1000.0
        if self.quantization == "disparity":
            fb = self.disparity_focal_px * self.disparity_baseline
            step = self.disparity_subpixel
            disp = np.round(fb / np.where(z > 0, z, np.inf) / step) * step
            return np.where((z > 0) & (disp > 0), fb / np.where(disp > 0, disp, 1.0), 0.0)
        return z

    def apply(self, depth: np.ndarray, K: np.ndarray, index: int, normals: Optional[np.ndarray] = None) -> np.ndarray:
        """The sensor's depth image of a perfect one.

        Args:
            depth: (H, W) perfect z-depth, metres, 0 = no hit.
            K: (3, 3) intrinsics, pixels.
            index: the frame's index in its sequence (seeds its noise with ``seed``).
            normals: (H, W, 3) camera-frame surface normals (e.g. the renderer's); None = estimated
                from ``depth`` (:func:`normals_from_depth`).

        Returns:
            (H, W) float32 sensor depth, metres, 0 = no depth.
        """
        d = np.asarray(depth, np.float64)
        if d.ndim != 2:
            raise ValueError(f"depth has shape {d.shape}, expected (H, W)")
        rng = self.rng(index)
        n = normals_from_depth(d, K) if normals is None else np.asarray(normals, np.float64)
        if n.shape != d.shape + (3,):
            raise ValueError(f"normals have shape {n.shape}, expected {d.shape + (3,)}")
        theta = incidence_angles(n, K)
        h, w = d.shape

        # 1. lateral noise: resample near discontinuities (depth, normal and angle move together)
        if self.lateral_scale > 0:
            # Nguyen's pixels are the Kinect's 640-wide ones: the same angular noise in this image's pixels
            sig = self.lateral_scale * lateral_sigma_px(theta) * (w / 640.0)
            jumps = depth_jumps(d, self.edge_jump)
            band = int(np.ceil(3.0 * float(np.max(sig, initial=0.0))))
            near = ndimage.binary_dilation(jumps, iterations=max(band, 1)) & (d > 0) if jumps.any() else jumps
            off = rng.normal(size=(2, h, w)) * sig
            rr, cc = np.nonzero(near)
            r2 = np.clip(np.rint(rr + off[0, rr, cc]), 0, h - 1).astype(np.int64)
            c2 = np.clip(np.rint(cc + off[1, rr, cc]), 0, w - 1).astype(np.int64)
            d = d.copy()
            theta = theta.copy()
            d[rr, cc] = d[r2, c2]
            theta[rr, cc] = theta[r2, c2]
        else:
            rng.normal(size=(2, h, w))  # keep the later draws the same whatever this key

        hole = np.zeros((h, w), bool)
        # 2. projector shadows
        if self.projector_baseline > 0:
            hole |= projector_shadow(d, float(K[0, 0]), self.projector_baseline)
        # 3. holes along discontinuities
        if self.edge_hole_px > 0:
            e = depth_jumps(d, self.edge_jump)
            if self.edge_hole_px > 1 and e.any():
                e = ndimage.binary_dilation(e, structure=np.ones((3, 3), bool), iterations=self.edge_hole_px - 1)
            hole |= e
        # 4. grazing angles
        if self.max_incidence_deg < 90.0:
            hole |= theta > np.deg2rad(self.max_incidence_deg)

        # 5. axial noise
        noise = rng.normal(size=(h, w))
        hole |= (d <= 0) | (np.asarray(depth) <= 0)  # no hit, or took a no-hit neighbour's depth
        if self.axial_scale > 0:
            d = d + noise * self.axial_scale * axial_sigma(np.where(d > 0, d, 1.0), theta)
        out = np.where(hole | (d <= 0), 0.0, d)
        # 6. range, 7. quantisation
        out = np.where((out >= self.min_range) & (out <= self.max_range), out, 0.0)
        out = self.quantize(out)
        return out.astype(np.float32)


def sensor_model(cfg: DepthNoiseConfig) -> Optional[SensorModel]:
    """The :class:`SensorModel` of the ``depth`` keys, or None for ``depth.model=perfect``."""
    if cfg.model == DepthModel.perfect:
        return None
    return SensorModel(seed=cfg.seed, axial_scale=cfg.axial_scale, lateral_scale=cfg.lateral_scale,
                       projector_baseline=cfg.projector_baseline, edge_jump=cfg.edge_jump,
                       edge_hole_px=cfg.edge_hole_px, max_incidence_deg=cfg.max_incidence_deg,
                       min_range=cfg.min_range, max_range=cfg.max_range,
                       quantization=cfg.quantization.value, disparity_focal_px=cfg.disparity_focal_px,
                       disparity_baseline=cfg.disparity_baseline, disparity_subpixel=cfg.disparity_subpixel)


def noisy_frames(frames: Sequence, model: SensorModel):
    """``frames`` with every frame's depth replaced by ``model.apply`` (normals estimated from the depth),
    computed on access (a lazy sequence; frame i is seeded by its index i)."""
    # the loader's statistics (depth unit checked, skipped frames) still hold
    return LazyFrames.mapped(frames, lambda i, f: replace(f, depth=model.apply(f.depth, f.K, i)),
                             info=getattr(frames, "info", None))


def depth_error_report(perfect: np.ndarray | Iterable[np.ndarray], noisy: np.ndarray | Iterable[np.ndarray],
                       bins: Sequence[float] = DEFAULT_BINS, outlier: float = 0.1) -> dict:
    """What a sensor model did to depth, against the perfect render, by range of the perfect depth.

    Args:
        perfect, noisy: (H, W) depth images in metres (0 = none), or equal-length iterables of them.
        bins: increasing range-bin edges, metres; pixels outside them form no bin but count in ``all``.
        outlier: |error| in metres above which a pixel counts as an outlier (edge pixels that took
            another surface's depth).

    Returns:
        ``{"bins": [row, ...], "all": row}``, each row with ``range`` [lo, hi] m, ``pixels`` (perfect
        depth in range), ``holes`` (share of them without sensor depth), ``rmse`` and ``bias`` (metres,
        over pixels with both), ``inlier_rmse`` (m, |error| <= outlier), ``outliers`` (share with
        |error| > outlier), and for the bins ``sigma_model`` (Nguyen's sigma_z at the bin's centre,
        theta = 0). ``spurious``: pixels with sensor but no perfect depth.
    """
    if isinstance(perfect, np.ndarray) and perfect.ndim == 2:
        perfect, noisy = [perfect], [noisy]
    p = np.concatenate([np.asarray(a, np.float64).ravel() for a in perfect])
    q = np.concatenate([np.asarray(a, np.float64).ravel() for a in noisy])
    if p.shape != q.shape:
        raise ValueError(f"perfect and noisy depth differ in size ({p.size} vs {q.size} pixels)")
    edges = np.asarray(bins, np.float64)
    if edges.ndim != 1 or len(edges) < 2 or np.any(np.diff(edges) <= 0):
        raise ValueError(f"bins={list(bins)}: expected at least two increasing edges (metres)")

    def row(sel: np.ndarray, lo: float, hi: float) -> dict:
        n = int(sel.sum())
        both = sel & (q > 0)
        err = q[both] - p[both]
        inl = np.abs(err) <= outlier
        out = {"range": [float(lo), float(hi)], "pixels": n,
               "holes": float(1.0 - both.sum() / n) if n else None,
               "rmse": float(np.sqrt(np.mean(err**2))) if err.size else None,
               "bias": float(np.mean(err)) if err.size else None,
               "inlier_rmse": float(np.sqrt(np.mean(err[inl] ** 2))) if inl.any() else None,
               "outliers": float(np.mean(~inl)) if err.size else None}
        return out

    rows = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        r = row((p >= lo) & (p < hi), lo, hi)
        r["sigma_model"] = float(axial_sigma(np.array(0.5 * (lo + hi))))
        rows.append(r)
    all_row = row(p > 0, 0.0, float(p.max(initial=0.0)))
    return {"bins": rows, "all": all_row, "spurious": int(((p <= 0) & (q > 0)).sum())}


def format_depth_report(rep: dict) -> str:
    """The report of :func:`depth_error_report` as a markdown table (millimetres and percent)."""
    def mm(x):
        return "-" if x is None else f"{1000 * x:.1f}"

    def pc(x):
        return "-" if x is None else f"{100 * x:.1f}"

    lines = ["| range [m] | pixels | holes % | RMSE mm | inlier RMSE mm | sigma_z(bin centre, 0 deg) mm | bias mm | outliers % |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rep["bins"] + [rep["all"]]:
        lo, hi = r["range"]
        name = "all" if r is rep["all"] else f"{lo:g}-{hi:g}"
        lines.append(f"| {name} | {r['pixels']:,} | {pc(r['holes'])} | {mm(r['rmse'])} | {mm(r['inlier_rmse'])} | "
                     f"{mm(r.get('sigma_model'))} | {mm(r['bias'])} | {pc(r['outliers'])} |")
    return "\n".join(lines)


HOLE_ANGLE_BINS = (0.0, 45.0, 60.0, 70.0, 75.0, 80.0, 90.0)  # degrees, the hole report's incidence bins
GAP_BINS = (0, 1, 3, 5, 9)  # hole-gap lengths (640-px pixels): 0, 1-2, 3-4, 5-8, >= 9 (up to max_gap_px)
HOLE_RANGE_BINS = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.5)  # metres, the hole report's range bins


def _jump_gaps(d: np.ndarray, rel: float, max_gap: int) -> np.ndarray:
    """Hole gaps across depth jumps along the rows of ``d`` (H, W; 0 = no depth).

    Consecutive valid pixels of a row, ``(r, a)`` and ``(r, b)`` with ``b - a - 1 <= max_gap`` holes
    between them, whose depths differ by more than ``rel`` x the nearer: returns the (J,) int gaps
    ``b - a - 1`` (0 = the jump is between two valid neighbours, no hole).
    """
    r, c = np.nonzero(d > 0)  # row-major: consecutive entries of a row are its consecutive valid pixels
    same = r[1:] == r[:-1]
    gap = c[1:] - c[:-1] - 1
    za, zb = d[r[:-1], c[:-1]], d[r[1:], c[1:]]
    jump = same & (gap <= max_gap) & (np.abs(za - zb) > rel * np.minimum(za, zb))
    return gap[jump]


def depth_hole_stats(depths: np.ndarray | Iterable[np.ndarray], Ks: np.ndarray | Iterable[np.ndarray],
                     ignore: Optional[Iterable[Optional[np.ndarray]]] = None, edge_jump: float = 0.05,
                     radius_px: float = 2.0, blob_px: float = 400.0, max_gap_px: int = 16,
                     bins: Sequence[float] = HOLE_RANGE_BINS, angle_bins: Sequence[float] = HOLE_ANGLE_BINS,
                     normals_window: int = 5) -> dict:
    """The holes of a depth image set on its own (no perfect reference: real or modelled depth alike).

    Pixel sizes are given for a 640-px-wide image and scaled by ``W / 640`` (areas by its square), so
    a 320x240 render and a 640x480 sensor frame are measured over the same angles. Every pixel
    (``ignore`` and dead-border pixels excepted) falls in one class, from the valid depths of its
    ``(2r+1) x (2r+1)`` window, ``r = max(1, round(radius_px W / 640))`` (5x5 at 640 px, 3x3 at 320):

    - ``discontinuity``: the window's valid depths span more than ``edge_jump`` x its nearest one
      (``max - min > edge_jump * min``: the model's ``edge_jump`` rule, over a window instead of a
      4-neighbour pair, so that a hole band between the two sides still sees both);
    - ``smooth``: the window holds valid depth that spans less;
    - ``interior``: the window holds no valid depth (inside a hole wider than the window).

    Args:
        depths: (H, W) metres, 0 = no depth, or an iterable of them.
        Ks: (3, 3) intrinsics (pixels) of each image, or one for all.
        ignore: per image, None or (H, W) bool pixels that count nowhere and give no depth (e.g. where
            a render hit no mesh: those are not the sensor's holes).
        edge_jump: relative depth span of a discontinuity (the model's ``depth.edge_jump``).
        radius_px: window radius, 640-px pixels.
        blob_px: a hole's 8-connected component larger than this (640-px pixels^2) is a ``blob``
            (window, mirror, out of range, dead margin piece), else ``thin``.
        max_gap_px: the longest hole run (640-px pixels) still counted as a gap across one jump.
        bins: range-bin edges, metres: a pixel's range is its depth, for a hole the depth of its
            nearest valid pixel (Euclidean in the image; ties: scipy's ``distance_transform_edt``).
        angle_bins: incidence-bin edges, degrees: the angle between the ray and the normal estimated
            from the depth (:func:`normals_from_depth`, box-smoothed over ``normals_window`` 640-px
            pixels); a hole takes its nearest valid pixel's; over ``smooth`` pixels only (normals
            across a discontinuity are meaningless).

    Returns:
        A dict of shares (0-1) and counts: ``frames``, ``pixels`` (counted), ``holes`` (share of all
        pixels not ignored, dead border included), ``holes_in`` (share of counted pixels), ``border`` (the dead
        margin: the rows/columns, running in from an image edge, without depth in any image of a
        same-size set of >= 2 images; share of all pixels), ``classes`` {class: {pixels, holes (share of the class's pixels without depth),
        of_holes (share of all counted holes)}}, ``blobs`` {blob, thin: share of counted holes},
        ``gaps`` {jumps (row-wise, 640-px units; see :func:`_jump_gaps`), mean_px, hist [(lo, hi,
        share)]}, ``range`` and ``angle`` [{range/deg [lo, hi], pixels, holes}], ``valid_beyond``
        {deg: share of valid smooth pixels with incidence above deg, for 70 75 80},
        ``valid_below_0_5m`` (share of valid depth < 0.5 m).
    """
    if isinstance(depths, np.ndarray) and depths.ndim == 2:
        depths = [depths]
    ds = [np.asarray(a, np.float64) for a in depths]
    if not ds:
        raise ValueError("depth_hole_stats: no depth images")
    if any(d.ndim != 2 for d in ds):
        raise ValueError(f"depth images have shapes {sorted({d.shape for d in ds})}, expected (H, W)")
    Ks = [np.asarray(Ks, np.float64)] * len(ds) if np.ndim(Ks) == 2 else [np.asarray(k, np.float64) for k in Ks]
    igs = [None] * len(ds) if ignore is None else list(ignore)
    if len(Ks) != len(ds) or len(igs) != len(ds):
        raise ValueError(f"{len(ds)} depth images but {len(Ks)} intrinsics and {len(igs)} ignore masks")
    edges, aedges = np.asarray(bins, np.float64), np.asarray(angle_bins, np.float64)
    # dead margin (ScanNet's registered depth: 27 columns, 5 rows): edge rows/columns no image has depth in
    same = len({d.shape for d in ds}) == 1 and len(ds) >= 2
    border = None
    if same:
        anyv = np.any([d > 0 for d in ds], axis=0)

        def margin(has: np.ndarray) -> np.ndarray:  # the empty lines running in from either edge
            lead = np.cumsum(has) == 0
            return lead | (np.cumsum(has[::-1]) == 0)[::-1]

        border = margin(anyv.any(axis=0))[None, :] | margin(anyv.any(axis=1))[:, None]

    cls_names = ("discontinuity", "smooth", "interior")
    tot = dict(all=0, seen=0, all_holes=0, pixels=0, holes=0, blob=0, border=0, below=0, valid=0)
    cls_n, cls_h = np.zeros(3, np.int64), np.zeros(3, np.int64)
    rng_n, rng_h = np.zeros(len(edges) - 1, np.int64), np.zeros(len(edges) - 1, np.int64)
    ang_n, ang_h = np.zeros(len(aedges) - 1, np.int64), np.zeros(len(aedges) - 1, np.int64)
    beyond = {70.0: 0, 75.0: 0, 80.0: 0}
    valid_smooth = 0
    gaps = []
    for d, K, ig in zip(ds, Ks, igs):
        h, w = d.shape
        s = w / 640.0
        ig = np.zeros((h, w), bool) if ig is None else np.asarray(ig, bool)
        if ig.shape != d.shape:
            raise ValueError(f"ignore mask has shape {ig.shape}, expected {d.shape}")
        d = np.where(ig, 0.0, d)
        valid = d > 0
        counted = ~ig if border is None else ~ig & ~border
        hole = counted & ~valid
        tot["all"] += h * w
        tot["seen"] += int((~ig).sum())
        tot["all_holes"] += int((~valid & ~ig).sum())
        tot["border"] += 0 if border is None else int(border.sum())
        tot["pixels"] += int(counted.sum())
        tot["holes"] += int(hole.sum())
        tot["valid"] += int(valid.sum())
        tot["below"] += int((valid & (d < 0.5)).sum())

        # classes from the window's valid depths
        size = 2 * max(1, int(round(radius_px * s))) + 1
        dmax = ndimage.maximum_filter(np.where(valid, d, -np.inf), size=size, mode="constant", cval=-np.inf)
        dmin = ndimage.minimum_filter(np.where(valid, d, np.inf), size=size, mode="constant", cval=np.inf)
        has = np.isfinite(dmax)
        disc = has & (dmax - dmin > edge_jump * np.where(has, dmin, 1.0))
        cls = np.where(disc, 0, np.where(has, 1, 2))
        cls_n += np.bincount(cls[counted], minlength=3)
        cls_h += np.bincount(cls[hole], minlength=3)

        # blobs: 8-connected hole components
        lab, n = ndimage.label(hole, structure=np.ones((3, 3), bool))
        if n:
            area = np.bincount(lab.ravel())
            tot["blob"] += int(area[1:][area[1:] > blob_px * s * s].sum())

        # gaps across jumps, along rows (the projector's baseline is horizontal) and columns
        mg = int(round(max_gap_px * s))
        g = np.concatenate([_jump_gaps(d, edge_jump, mg), _jump_gaps(d.T, edge_jump, mg)])
        gaps.append(g / s)

        if not valid.any():
            continue
        # range: own depth, or the nearest valid pixel's
        near = ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)
        zr = d[near[0], near[1]]
        bi = np.digitize(zr, edges) - 1
        inb = counted & (bi >= 0) & (bi < len(edges) - 1)
        rng_n += np.bincount(bi[inb], minlength=len(edges) - 1)
        rng_h += np.bincount(bi[inb & hole], minlength=len(edges) - 1)

        # incidence from normals estimated on the depth; smooth pixels with a known normal only
        win = max(1, int(round(normals_window * s)) | 1)
        nrm = normals_from_depth(d, K, window=win)
        known = np.linalg.norm(nrm, axis=-1) > 0
        th = np.rad2deg(incidence_angles(nrm, K))
        th_near, known_near = th[near[0], near[1]], known[near[0], near[1]]
        ai = np.digitize(th_near, aedges) - 1
        ina = counted & (cls == 1) & known_near & (ai >= 0) & (ai < len(aedges) - 1)
        ang_n += np.bincount(ai[ina], minlength=len(aedges) - 1)
        ang_h += np.bincount(ai[ina & hole], minlength=len(aedges) - 1)
        vs = counted & (cls == 1) & valid & known
        valid_smooth += int(vs.sum())
        for a in beyond:
            beyond[a] += int((vs & (th > a)).sum())

    def share(a, b):
        return float(a / b) if b else None

    g = np.concatenate(gaps) if gaps else np.zeros(0)
    gb = np.asarray(GAP_BINS + (np.inf,), np.float64)
    hist = [(float(lo), float(hi), share(int(((g >= lo) & (g < hi)).sum()), g.size))
            for lo, hi in zip(gb[:-1], gb[1:])]
    return {
        "frames": len(ds), "pixels": tot["pixels"],
        "holes": share(tot["all_holes"], tot["seen"]),
        "holes_in": share(tot["holes"], tot["pixels"]),
        "border": share(tot["border"], tot["all"]),
        "classes": {c: {"pixels": int(cls_n[i]), "holes": share(cls_h[i], cls_n[i]),
                        "of_holes": share(cls_h[i], tot["holes"])} for i, c in enumerate(cls_names)},
        "blobs": {"blob": share(tot["blob"], tot["holes"]), "thin": share(tot["holes"] - tot["blob"], tot["holes"])},
        "gaps": {"jumps": int(g.size), "mean_px": float(g.mean()) if g.size else None, "hist": hist},
        "range": [{"range": [float(lo), float(hi)], "pixels": int(n), "holes": share(k, n)}
                  for lo, hi, n, k in zip(edges[:-1], edges[1:], rng_n, rng_h)],
        "angle": [{"deg": [float(lo), float(hi)], "pixels": int(n), "holes": share(k, n)}
                  for lo, hi, n, k in zip(aedges[:-1], aedges[1:], ang_n, ang_h)],
        "valid_beyond": {f"{a:g}": share(v, valid_smooth) for a, v in beyond.items()},
        "valid_below_0_5m": share(tot["below"], tot["valid"]),
    }


def format_hole_stats(columns: Sequence[tuple[str, dict]]) -> str:
    """:func:`depth_hole_stats` of one or more depth sets side by side, a markdown table (percent)."""
    def pc(x):
        return "-" if x is None else f"{100 * x:.1f}"

    cols = list(columns)
    rows = [("frames", lambda r: f"{r['frames']}"),
            ("counted pixels", lambda r: f"{r['pixels']:,}"),
            ("holes %, all pixels", lambda r: pc(r["holes"])),
            ("dead border % of the image", lambda r: pc(r["border"])),
            ("holes %, counted pixels (border out)", lambda r: pc(r["holes_in"]))]
    for c in ("discontinuity", "smooth", "interior"):
        rows.append((f"{c} pixels: % of counted", lambda r, c=c: pc(share_of(r, c))))
        rows.append((f"{c} pixels: holes %", lambda r, c=c: pc(r["classes"][c]["holes"])))
        rows.append((f"{c}: % of the holes", lambda r, c=c: pc(r["classes"][c]["of_holes"])))
    rows += [("holes in blobs > 400 px (640-px) %", lambda r: pc(r["blobs"]["blob"])),
             ("jumps crossed (rows + cols)", lambda r: f"{r['gaps']['jumps']:,}"),
             ("mean hole gap across a jump, 640-px", lambda r: "-" if r["gaps"]["mean_px"] is None
              else f"{r['gaps']['mean_px']:.2f}")]
    for i, (lo, hi, _) in enumerate(cols[0][1]["gaps"]["hist"]):
        name = f"{lo:g}" if hi == lo + 1 else (f">= {lo:g}" if not np.isfinite(hi) else f"{lo:g}-{hi - 1:g}")
        rows.append((f"jumps with a gap of {name} px %", lambda r, i=i: pc(r["gaps"]["hist"][i][2])))
    for i, b in enumerate(cols[0][1]["range"]):
        rows.append((f"holes % at range {b['range'][0]:g}-{b['range'][1]:g} m (pixels)",
                     lambda r, i=i: f"{pc(r['range'][i]['holes'])} ({r['range'][i]['pixels']:,})"))
    for i, b in enumerate(cols[0][1]["angle"]):
        rows.append((f"smooth holes % at incidence {b['deg'][0]:g}-{b['deg'][1]:g} deg (pixels)",
                     lambda r, i=i: f"{pc(r['angle'][i]['holes'])} ({r['angle'][i]['pixels']:,})"))
    for a in cols[0][1]["valid_beyond"]:
        rows.append((f"valid smooth depth beyond {a} deg %", lambda r, a=a: pc(r["valid_beyond"][a])))
    rows.append(("valid depth < 0.5 m %", lambda r: pc(r["valid_below_0_5m"])))
    lines = ["| statistic | " + " | ".join(n for n, _ in cols) + " |", "|---|" + "---:|" * len(cols)]
    lines += [f"| {name} | " + " | ".join(f(r) for _, r in cols) + " |" for name, f in rows]
    return "\n".join(lines)


def share_of(rep: dict, cls: str) -> Optional[float]:
    """The share of counted pixels in class ``cls`` of a :func:`depth_hole_stats` report."""
    return rep["classes"][cls]["pixels"] / rep["pixels"] if rep["pixels"] else None
