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

Every random draw of frame ``index`` comes from ``default_rng([seed, index, _STREAM])``
(``seeding.keyed("sensor.frame", ...)``), so a frame's noise does not depend on which other frames
were drawn or in which order.

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
from typing import Optional, Sequence

import numpy as np
from scipy import ndimage

from diffuser_lab import seeding
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
    "noisy_frames",
]

_STREAM = 0x5E45  # separates the sensor's random stream from the other users of the same seed


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
    c = np.clip(cos, 0.0, 1.0)
    return np.arctan2(np.sqrt(1.0 - c * c), c)  # = arccos(c); numpy's float64 arccos rounds by CPU


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
        return seeding.keyed("sensor.frame", int(self.seed) % 2**32, int(index) % 2**32, _STREAM)

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
