"""Lens distortion, the one undistortion of every source: images of a distorted camera resampled to a
pinhole camera (the same K, or its focal lengths scaled so no pixel is blank: :func:`focal_scale`).

Two models, in normalised camera coordinates ``(x, y) = (X / Z, Y / Z)`` (OpenCV's and
nerfstudio's definitions, :data:`PERSPECTIVE` and :data:`FISHEYE`):

- ``perspective`` (OpenCV's radial-tangential and rational; COLMAP's SIMPLE_RADIAL, RADIAL, OPENCV,
  FULL_OPENCV: :func:`colmap_lens`): ``r2 = x^2 + y^2``,
  ``d = (1 + k1 r2 + k2 r2^2 + k3 r2^3 + k4 r2^4) / (1 + q1 r2 + q2 r2^2 + q3 r2^3)`` (k4 is
  nerfstudio's r^8 term; q1..q3 are OpenCV's and COLMAP FULL_OPENCV's k4..k6),
  ``xd = x d + 2 p1 x y + p2 (r2 + 2 x^2)``, ``yd = y d + p1 (r2 + 2 y^2) + 2 p2 x y``;
- ``fisheye`` (OpenCV's fisheye, OPENCV_FISHEYE): ``theta = atan(r)``,
  ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``, ``(xd, yd) = (x, y) theta_d / r``.

Undistorting an image is a resampling: output pixel (col, row) of the pinhole image (same K, same
size) takes the distorted image at ``K distort(K^-1 (col, row, 1))``, the *forward* model, so the
map needs no iteration; it is computed once per camera and image size (:func:`undistort_map`,
cached) and applied with ``scipy.ndimage.map_coordinates`` (:func:`undistort_image`): bilinear for
colour, nearest for depth, labels and masks. Pixels whose source lies outside the distorted image,
or beyond the radius where the model folds back (its radial derivative turns <= 0), get the fill
value (0 colour / depth, -1 labels). :func:`undistort_points` is the iterative inverse (distorted
-> undistorted normalised coordinates), for projecting the other way and for synthesising a
distorted image from a pinhole one. Pixel centres lie at integer coordinates (OpenCV's convention,
as K is everywhere in diffuser-lab).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.ndimage import map_coordinates

from .geometry import scaled_intrinsics

__all__ = ["PERSPECTIVE", "FISHEYE", "LensModel", "distort_points", "undistort_points", "undistort_map",
           "undistort_image", "focal_scale", "colmap_lens", "COLMAP_LENS_MODELS", "ros_lens", "ROS_LENS_MODELS"]

PERSPECTIVE, FISHEYE = "perspective", "fisheye"


@dataclass(frozen=True)
class LensModel:
    """A camera's distortion: ``kind`` (:data:`PERSPECTIVE` | :data:`FISHEYE`) and its coefficients
    (``k1..k4``; ``p1, p2`` and the rational denominator ``q1..q3`` for perspective only). Hashable,
    so maps are cached per model."""

    kind: str
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    q1: float = 0.0
    q2: float = 0.0
    q3: float = 0.0

    def __post_init__(self):
        if self.kind not in (PERSPECTIVE, FISHEYE):
            raise ValueError(f"lens model {self.kind!r}: expected {PERSPECTIVE} or {FISHEYE}")
        if self.kind == FISHEYE and (self.p1 or self.p2 or self.q1 or self.q2 or self.q3):
            raise ValueError(f"lens model {self.text()}: a fisheye has no tangential or rational terms")

    @property
    def is_pinhole(self) -> bool:
        """All coefficients zero: no resampling (a fisheye without coefficients is still equidistant)."""
        zero = self.k1 == self.k2 == self.k3 == self.k4 == self.p1 == self.p2 == self.q1 == self.q2 == self.q3 == 0.0
        return zero and self.kind == PERSPECTIVE

    def text(self) -> str:
        names = ("k1", "k2", "k3", "k4") + (("p1", "p2", "q1", "q2", "q3") if self.kind == PERSPECTIVE else ())
        return f"{self.kind} " + " ".join(f"{n}={getattr(self, n):g}" for n in names if getattr(self, n))


def _radial(model: LensModel, s: np.ndarray) -> np.ndarray:
    """(1 + k1 s + k2 s^2 + k3 s^3 + k4 s^4) / (1 + q1 s + q2 s^2 + q3 s^3) (s = r^2 or theta^2)."""
    num = 1.0 + s * (model.k1 + s * (model.k2 + s * (model.k3 + s * model.k4)))
    if model.q1 == model.q2 == model.q3 == 0.0:
        return num
    return num / (1.0 + s * (model.q1 + s * (model.q2 + s * model.q3)))


def _radial_slope(model: LensModel, s: np.ndarray) -> np.ndarray:
    """d(rho * radial(rho^2)) / d rho at s = rho^2 (polynomial models: the fisheye's Newton step)."""
    return 1.0 + s * (3 * model.k1 + s * (5 * model.k2 + s * (7 * model.k3 + s * 9 * model.k4)))


def distort_points(x: np.ndarray, y: np.ndarray, model: LensModel) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised coordinates -> distorted ones (the forward model, module docstring)."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    r2 = x * x + y * y
    if model.kind == FISHEYE:
        r = np.sqrt(r2)
        theta = np.arctan2(r, 1.0)  # = arctan(r); numpy's float64 arctan and tan round by CPU, arctan2, sin, cos do not
        theta_d = theta * _radial(model, theta * theta)
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(r > 1e-12, theta_d / r, 1.0)
        return x * scale, y * scale
    d = _radial(model, r2)
    xy = x * y
    return (x * d + 2 * model.p1 * xy + model.p2 * (r2 + 2 * x * x),
            y * d + model.p1 * (r2 + 2 * y * y) + 2 * model.p2 * xy)


def undistort_points(xd: np.ndarray, yd: np.ndarray, model: LensModel, iterations: int = 30
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Distorted normalised coordinates -> undistorted ones: the forward model inverted by Newton's
    method on theta (fisheye) or OpenCV's fixed-point iteration (perspective; converges for the
    distortion of real lenses inside the image). Accurate to ~1e-10 where the model does not fold."""
    xd = np.asarray(xd, np.float64)
    yd = np.asarray(yd, np.float64)
    if model.kind == FISHEYE:
        rd = np.sqrt(xd * xd + yd * yd)
        theta = rd.copy()
        for _ in range(iterations):  # Newton on theta (1 + k1 t^2 + ...) = rd, per point
            t2 = theta * theta
            f = theta * _radial(model, t2) - rd
            theta = theta - f / np.maximum(_radial_slope(model, t2), 1e-9)
        theta = np.clip(theta, 0.0, np.pi / 2 - 1e-9)
        r = np.sin(theta) / np.cos(theta)
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(rd > 1e-12, r / rd, 1.0)
        return xd * scale, yd * scale
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):  # x = (xd - tangential(x, y)) / radial(r2)
        r2 = x * x + y * y
        d = _radial(model, r2)
        xy = x * y
        x = (xd - 2 * model.p1 * xy - model.p2 * (r2 + 2 * x * x)) / d
        y = (yd - model.p1 * (r2 + 2 * y * y) - 2 * model.p2 * xy) / d
    return x, y


def _fold_limit(model: LensModel, s_max: float) -> float:
    """The smallest s = r^2 (theta^2 for fisheye) up to ``s_max`` where the radial map rho radial(rho^2)
    stops increasing (inf when it increases throughout); sampled, so rational models are covered."""
    rho = np.linspace(0.0, np.sqrt(s_max), 4097)
    f = rho * _radial(model, rho * rho)
    bad = np.flatnonzero(~(np.diff(f) > 0))
    return float(rho[bad[0]] ** 2) if bad.size else np.inf


@lru_cache(maxsize=8)
def _cached_map(fx: float, fy: float, cx: float, cy: float, h: int, w: int, model: LensModel, out: tuple):
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = (cols - out[2]) / out[0], (rows - out[3]) / out[1]  # rays of the pinhole (output) camera
    xd, yd = distort_points(x, y, model)
    src_c, src_r = fx * xd + cx, fy * yd + cy
    s = x * x + y * y
    if model.kind == FISHEYE:
        s = np.arctan2(np.sqrt(s), 1.0) ** 2
    limit = _fold_limit(model, float(s.max()) * 1.01 + 1e-12)
    valid = (s < limit) & (src_c >= -0.5) & (src_c <= w - 0.5) & (src_r >= -0.5) & (src_r <= h - 0.5)
    coords = np.stack([src_r, src_c]).astype(np.float32)
    coords.setflags(write=False)
    valid.setflags(write=False)
    return coords, valid


def _fxy(K: np.ndarray) -> tuple:
    return float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])


def undistort_map(K: np.ndarray, shape: tuple[int, int], model: LensModel, K_out: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel of the undistorted pinhole image of (H, W) ``shape`` and intrinsics ``K_out``
    (default ``K``) lies in the distorted image of intrinsics ``K``: (2, H, W) float32 (row, col)
    source coordinates and an (H, W) bool mask of the pixels whose source lies inside it (and inside
    the model's unfolded radius). Cached per camera and size (the 8 most recent), so a sequence of
    one camera computes it once."""
    return _cached_map(*_fxy(K), int(shape[0]), int(shape[1]), model, _fxy(K if K_out is None else K_out))


def focal_scale(K: np.ndarray, shape: tuple[int, int], model: LensModel, what: str) -> float:
    """The least factor s >= 1 such that the pinhole camera of ``K`` with its focal lengths times s
    (same principal point) leaves no blank pixel in an (H, W) ``shape`` image (COLMAP
    image_undistorter's ``blank_pixels=0``): its border, sampled, maps inside the distorted image.

    Raises:
        ValueError: starting with ``what``, when even s = 64 leaves blank pixels.
    """
    H, W = int(shape[0]), int(shape[1])
    t = np.linspace(0, 1, 257)  # the image border, sampled
    u = np.concatenate([t * (W - 1), t * (W - 1), np.zeros_like(t), np.full_like(t, W - 1)])
    v = np.concatenate([np.zeros_like(t), np.full_like(t, H - 1), t * (H - 1), t * (H - 1)])
    fx, fy, cx, cy = _fxy(K)

    def inside(s: float) -> bool:
        xd, yd = distort_points((u - cx) / (fx * s), (v - cy) / (fy * s), model)
        c, r = fx * xd + cx, fy * yd + cy
        return bool(((c >= -0.5) & (c <= W - 0.5) & (r >= -0.5) & (r <= H - 0.5)).all())

    if inside(1.0):
        return 1.0
    hi = 2.0
    while not inside(hi):  # loop: doubling, a few steps
        hi *= 2
        if hi > 64:
            raise ValueError(f"{what}: distortion too strong to resample to a pinhole camera without blank pixels")
    lo = 1.0
    for _ in range(30):  # bisection on the focal scale
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if inside(mid) else (mid, hi)
    return hi


COLMAP_LENS_MODELS = {  # COLMAP camera model -> its parameters after fx fy cx cy, as LensModel fields
    "SIMPLE_RADIAL": ("k1",), "RADIAL": ("k1", "k2"), "OPENCV": ("k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("k1", "k2", "p1", "p2", "k3", "q1", "q2", "q3"),
}


def colmap_lens(model: str, params) -> tuple[np.ndarray, LensModel]:
    """A COLMAP camera (model name, ``params`` as in cameras.txt) of :data:`COLMAP_LENS_MODELS` ->
    (3, 3) K with pixel centres at integers (COLMAP puts them at +0.5) and its LensModel
    (src/colmap/sensor/models.h: SIMPLE_RADIAL and RADIAL have one focal length)."""
    p = [float(x) for x in params]
    one_f = model in ("SIMPLE_RADIAL", "RADIAL")
    fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if one_f else p[:4]
    coeffs = p[3:] if one_f else p[4:]
    K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    return K, LensModel(PERSPECTIVE, **dict(zip(COLMAP_LENS_MODELS[model], coeffs)))


ROS_LENS_MODELS = {  # sensor_msgs/CameraInfo distortion_model -> (kind, D's coefficients as LensModel fields)
    "plumb_bob": (PERSPECTIVE, ("k1", "k2", "p1", "p2", "k3")),
    "rational_polynomial": (PERSPECTIVE, ("k1", "k2", "p1", "p2", "k3", "q1", "q2", "q3")),
    "equidistant": (FISHEYE, ("k1", "k2", "k3", "k4")),
}


def ros_lens(model: str, D, where: str) -> LensModel:
    """A CameraInfo's ``distortion_model`` and ``D`` -> its LensModel (image_geometry's definitions:
    plumb_bob = OpenCV's k1 k2 p1 p2 k3, rational_polynomial adds k4 k5 k6 = the denominator's q1 q2 q3,
    equidistant = OpenCV's fisheye k1..k4); one line naming ``where`` for another model or length."""
    D = [float(x) for x in np.ravel(D)]
    if model not in ROS_LENS_MODELS:
        raise ValueError(f"{where}: distortion_model {model!r} with D = {np.round(D, 5).tolist()}; expected "
                         f"{', '.join(ROS_LENS_MODELS)} (or D all zero)")
    kind, names = ROS_LENS_MODELS[model]
    if len(D) > len(names) and any(D[len(names):]):
        raise ValueError(f"{where}: {model} D has {len(D)} coefficients, expected at most {len(names)}")
    if not np.all(np.isfinite(D)):
        raise ValueError(f"{where}: {model} D = {D} is not finite")
    return LensModel(kind, **dict(zip(names, D)))


def undistort_image(img: np.ndarray, K: np.ndarray, model: LensModel, *, order: int, fill=0,
                    K_out: np.ndarray | None = None, K_size: tuple[int, int] | None = None) -> np.ndarray:
    """A distorted image (H, W) or (H, W, C) whose intrinsics are ``K`` -> the pinhole image of
    intrinsics ``K_out`` (default ``K``) and the same size and dtype: ``order`` 1 = bilinear
    (colour), 0 = nearest (depth, labels, masks); pixels without a source get ``fill``. ``K_size``:
    the (H, W) that ``K`` and ``K_out`` are for (None = this image's); an image of another size takes
    them scaled with pixel centres aligned (a label image at half the colour's size). The image
    itself when ``model`` is pinhole and ``K_out`` is ``K``."""
    img = np.asarray(img)
    if K_size is not None and tuple(img.shape[:2]) != tuple(K_size):
        K = scaled_intrinsics(K, K_size, img.shape[:2])
        K_out = None if K_out is None else scaled_intrinsics(K_out, K_size, img.shape[:2])
    if model.is_pinhole and (K_out is None or np.array_equal(K_out, K)):
        return img
    coords, valid = undistort_map(K, img.shape[:2], model, K_out)
    planes = img[..., None] if img.ndim == 2 else img
    out = np.empty(planes.shape, np.float64 if order else planes.dtype)
    for c in range(planes.shape[2]):  # loop over channels (1 or 3)
        src = planes[..., c] if order == 0 else planes[..., c].astype(np.float64)
        out[..., c] = map_coordinates(src, coords, order=order, mode="nearest")
    if order:
        out = np.rint(out) if img.dtype.kind in "ui" else out
        if img.dtype.kind in "ui":
            info = np.iinfo(img.dtype)
            out = np.clip(out, info.min, info.max)
        out = out.astype(img.dtype)
    out[~valid] = fill
    return out[..., 0] if img.ndim == 2 else out
