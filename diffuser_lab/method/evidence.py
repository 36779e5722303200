"""Pixel-to-point evidence (paper Eqs. 1-2, 11-13).

For every frame, a point x_i is linked to the pixel it projects to (Eq. 2) when the
projection falls inside the image and passes the depth-consistency (occlusion) check
|z_i - depth(pixel)| <= depth_tol. With ``pixel_radius`` r > 0 the point is linked to
every pixel of the (2r+1)x(2r+1) window around that pixel (as in LDLS); visibility is
decided at the centre pixel. Each link carries the pixel's one-hot label or its class
probabilities (Eq. 8), so ``mass[i, c]`` is the number of linked pixels voting for
class c: Sum_k Z^{I_k->X} of Eq. 12 divided by lambda, which the diffusion applies
(Eqs. 14-15). Frames are consumed one at a time, so memory does not grow with their number.

Features (:mod:`diffuser_lab.method.features`): a frame whose ``features`` map (H', W', D) is set links
each point to the feature bilinearly sampled at its pixel's centre (the map may be a network's
coarser patch grid), L2-normalised; ``mass[i]`` is then the sum of the point's linked unit features
(D columns) and ``links[i]`` their number, which replaces the row sum of class masses in Eqs. 14-15.
A pixel whose feature is missing (NaN in the map, a masked cell) gives no evidence.

Speed: hard labels with ``pixel_radius`` 0 (the paper's setting) go through one fused compiled
pass per frame when numba is installed (:func:`diffuser_lab.backends.evidence.hard_votes`: projection
in float64, bounds, depth check and the vote, no temporaries); everything else, and the pure
numpy path (``DIFFUSER_LAB_NUMBA=0``), uses the vectorised code below.

:class:`RunEvidence` is what a run accumulates frame by frame: the method's evidence and the
Bayesian baseline's (one pixel; likelihoods or votes), shared when they are the same; the batch
pipeline and the online mode add a frame to it through :meth:`RunEvidence.add`.

A link hook (``hook=``, :data:`LinkHook`) sees every link set as it is added: the frame, the points,
the linked points' indices, their pixels and each link's vector (the pixel's class distribution, a
one-hot label, or a unit feature), so a lifting rule of :mod:`diffuser_lab.method.lifters` keeps its
own per-point running state, and weighs links by the frame's depth at evidence time, from the one
frame loop (with a hook, hard labels take the vectorised path below, not the fused pass).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterable, Optional

import numpy as np

from diffuser_lab.backends import features as compiled_features
from diffuser_lab.backends.evidence import hard_votes
from diffuser_lab.backends.threads import blas_one_thread
from diffuser_lab.config import BayesianMode
from diffuser_lab.data.geometry import visible_projection
from diffuser_lab.data.scene import IGNORE, Frame

from .features import normalised


@dataclass
class Evidence:
    """Accumulated pixel-to-point evidence.

    Attributes:
        mass: (N, C) float32, sum over frames and linked pixels of the pixel's class vector.
        links: (N,) int32 number of pixel links of each point.
        points_per_frame: number of points that passed the visibility check, per frame.
    """

    mass: np.ndarray
    links: np.ndarray
    points_per_frame: list[int] = field(default_factory=list)

    @classmethod
    def empty(cls, n: int, num_classes: int) -> "Evidence":
        return cls(mass=np.zeros((n, num_classes), np.float32), links=np.zeros(n, np.int32))

    @property
    def seen(self) -> np.ndarray:
        """(N,) bool: the point received pixel mass (a link)."""
        return self.links > 0


def _class_vectors(frame: Frame, num_classes: int, hard: bool,
                   checked: bool = False) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The frame's per-pixel labels: (H,W) ids for hard evidence or (H,W,C) probabilities
    (``checked``: the label ids were checked before, when the frame's evidence was first added)."""
    if frame.probs is not None and not hard:
        probs = frame.probs
        if probs.ndim != 3 or probs.shape[2] != num_classes or probs.shape[:2] != frame.shape:
            raise ValueError(f"frame {frame.name}: probabilities of shape {probs.shape}, expected "
                             f"{frame.shape + (num_classes,)}")
        return None, probs
    if frame.labels is None and frame.probs is not None:
        return np.argmax(frame.probs, axis=2).astype(np.int16), None
    if frame.labels is None:
        raise ValueError(f"frame {frame.name}: no 2D labels or probabilities to take evidence from")
    if frame.labels.shape != frame.shape:
        raise ValueError(f"frame {frame.name}: label image {frame.labels.shape} != depth {frame.shape}")
    if checked:
        return frame.labels, None
    lo, hi = int(frame.labels.min()), int(frame.labels.max())
    if lo < IGNORE or hi >= num_classes:
        raise ValueError(f"frame {frame.name}: label ids in [{lo}, {hi}], expected {IGNORE} (no label) "
                         f"or 0..{num_classes - 1}")
    return frame.labels, None


LinkHook = Callable[[Frame, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray], None]
"""``hook(frame, points, idx, rows, cols, vectors)``: points ``idx`` (M,) (each once) of the (N, 3)
``points`` linked to pixels ``rows``, ``cols`` (M,) of ``frame`` with the (M, C) float32 class
vectors (rows summing to 1) or (M, D) unit features that entered the evidence."""


FEATURE_CHUNK = 16384
"""Points whose features are sampled at once (bounds the (chunk, D) float32 temporaries)."""


def prepare_features(fmap: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A feature map (h, w, D) (NaN = no feature) -> ((h * w, D) float32 with 0 for missing cells,
    (h, w) bool cells with a feature): what :func:`sample_features` reads, made once per frame."""
    valid = np.isfinite(fmap).all(axis=2)
    flat = np.asarray(fmap, np.float32).reshape(-1, fmap.shape[2])
    if not valid.all():
        flat = np.where(valid.reshape(-1, 1), flat, np.float32(0))
    return flat, valid


def sample_features(fmap: np.ndarray, rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int],
                    prepared: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples of a feature map at pixel centres of a (H, W) image.

    Args:
        fmap: (h, w, D) float16/float32 features covering the same field of view as the (H, W)
            image (a network's patch grid, or the image's own resolution); NaN = no feature.
        rows, cols: (M,) int pixel coordinates in the (H, W) image.
        prepared: :func:`prepare_features` of ``fmap`` (made here when None).
    Returns:
        (M, D) float32 unit features (0 rows where unusable) and (M,) bool usable: the pixel centre
        ``(c + 0.5) w / W - 0.5`` (align_corners=False, as torch and OpenCV resize) interpolated from
        the valid ones of its four cells, renormalised; no valid cell, or a zero feature: unusable.
    """
    h, w, D = fmap.shape
    H, W = shape
    flat, valid = prepare_features(fmap) if prepared is None else prepared
    y = np.clip((rows + 0.5) * (h / H) - 0.5, 0, h - 1)
    x = np.clip((cols + 0.5) * (w / W) - 0.5, 0, w - 1)
    y0, x0 = np.floor(y).astype(np.int64), np.floor(x).astype(np.int64)
    y1, x1 = np.minimum(y0 + 1, h - 1), np.minimum(x0 + 1, w - 1)
    wy, wx = (y - y0).astype(np.float32), (x - x0).astype(np.float32)
    acc = np.zeros((rows.size, D), np.float32)
    total = np.zeros(rows.size, np.float32)
    for yy, xx, wt in ((y0, x0, (1 - wy) * (1 - wx)), (y0, x1, (1 - wy) * wx),
                       (y1, x0, wy * (1 - wx)), (y1, x1, wy * wx)):
        wt = np.where(valid[yy, xx], wt, np.float32(0))
        part = np.take(flat, yy * w + xx, axis=0)
        part *= wt[:, None]
        acc += part
        total += wt
    f, ok = normalised(acc)
    return f, ok & (total > 0)


@dataclass(frozen=True)
class ProjectedMap:
    """A feature map projected on a :class:`~diffuser_lab.method.basis.FeatureBasis` (what
    :func:`sample_basis` reads; :func:`project_features` makes it once per frame).

    Attributes:
        coords: (h * w, k + s) float32 each cell's coordinates on the basis' columns (0: no feature).
        gram: (5, h * w) float32 the cells' dot products in R^D with themselves and their neighbours
            (self, right, down, down-right, and right-with-down: cell (y, x + 1) . cell (y + 1, x);
            a neighbour past the edge is the edge cell, as the sampler's clipped corners):
            what makes a bilinear sample's norm in R^D exact without its D values.
        valid: (h, w) bool cells with a feature.
    """

    coords: np.ndarray
    gram: np.ndarray
    valid: np.ndarray


def project_features(fmap: np.ndarray, basis) -> ProjectedMap:
    """A feature map (h, w, D) (NaN = no feature) -> its :class:`ProjectedMap` on ``basis``: one
    (h w, D) x (D, k + s) product and five (h, w) dot-product maps (O(h w D) each)."""
    h, w, D = fmap.shape
    flat, valid = prepare_features(fmap)
    coords = flat @ basis.columns
    f = flat.reshape(h, w, D)
    xr, yd = np.minimum(np.arange(w) + 1, w - 1), np.minimum(np.arange(h) + 1, h - 1)
    gram = np.empty((5, h, w), np.float32)
    gram[0] = np.einsum("yxd,yxd->yx", f, f)
    gram[1] = np.einsum("yxd,yxd->yx", f, f[:, xr])
    gram[2] = np.einsum("yxd,yxd->yx", f, f[yd])
    gram[3] = np.einsum("yxd,yxd->yx", f, f[yd][:, xr])
    gram[4] = np.einsum("yxd,yxd->yx", f[:, xr], f[yd])
    return ProjectedMap(coords, gram.reshape(5, h * w), valid)


def sample_basis(prep: ProjectedMap, fshape: tuple[int, int], rows: np.ndarray, cols: np.ndarray,
                 shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`sample_features` on a projected map: the same bilinear sample at the pixel centres,
    normalised by its exact norm in R^D (from the cells' dot products), in the basis' coordinates.

    Args:
        prep: the frame's :class:`ProjectedMap`; fshape: the map's (h, w).
        rows, cols: (M,) int pixel coordinates in the (H, W) image ``shape``.
    Returns:
        (M, k + s) float32 the unit samples' coordinates (0 rows where unusable), (M,) bool usable,
        (M,) float32 each usable sample's squared norm in R^D before normalising (> 0).
    """
    h, w = fshape
    H, W = shape
    y = np.clip((rows + 0.5) * (h / H) - 0.5, 0, h - 1)
    x = np.clip((cols + 0.5) * (w / W) - 0.5, 0, w - 1)
    y0, x0 = np.floor(y).astype(np.int64), np.floor(x).astype(np.int64)
    y1, x1 = np.minimum(y0 + 1, h - 1), np.minimum(x0 + 1, w - 1)
    wy, wx = (y - y0).astype(np.float32), (x - x0).astype(np.float32)
    c00, c01, c10, c11 = y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1
    flat_valid = prep.valid.reshape(-1)
    wts = []
    for c, wt in ((c00, (1 - wy) * (1 - wx)), (c01, (1 - wy) * wx), (c10, wy * (1 - wx)), (c11, wy * wx)):
        wts.append(np.where(flat_valid[c], wt, np.float32(0)))
    a, b, c, d = wts
    g = prep.gram
    n2 = (a * a * g[0, c00] + b * b * g[0, c01] + c * c * g[0, c10] + d * d * g[0, c11]
          + 2 * (a * b * g[1, c00] + c * d * g[1, c10] + a * c * g[2, c00] + b * d * g[2, c01]
                 + a * d * g[3, c00] + b * c * g[4, c00]))
    acc = np.take(prep.coords, c00, axis=0)
    acc *= a[:, None]
    for cell, wt in ((c01, b), (c10, c), (c11, d)):
        part = np.take(prep.coords, cell, axis=0)
        part *= wt[:, None]
        acc += part
    ok = (a + b + c + d > 0) & (n2 > 0) & np.isfinite(n2)
    inv = np.divide(np.float32(1), np.sqrt(n2, where=ok, out=np.ones_like(n2)), where=ok, out=np.zeros_like(n2))
    acc *= inv[:, None]
    return acc, ok, np.where(ok, n2, np.float32(0))


class BestView:
    """The most confident view's feature of every point (a baseline of features runs): the unit
    feature of the linked pixel (the projected one; not a window's) whose ``confidence`` is the
    highest over the frames seen so far.

    Args:
        n, dim: points and D. confidence: (M, D) unit features -> (M,) float32 (e.g. the top
            query's softmax probability; :meth:`~diffuser_lab.method.space.Features.confidence`).
    Attributes:
        features: (n, D) float16 (0 rows: never seen); score: (n,) float32 (-inf: never seen).
    """

    def __init__(self, n: int, dim: int, confidence):
        self.features = np.zeros((n, dim), np.float16)
        self.score = np.full(n, -np.inf, np.float32)
        self.confidence = confidence

    def offer(self, idx: np.ndarray, f: np.ndarray) -> None:
        """Points ``idx`` (M,) (each once) linked to unit features ``f`` (M, D) in one frame."""
        c = self.confidence(f)
        better = c > self.score[idx]
        self.score[idx[better]] = c[better]
        self.features[idx[better]] = f[better]


def _add_basis_samples(ev: Evidence, prep: ProjectedMap, fshape: tuple[int, int], rows: np.ndarray,
                       cols: np.ndarray, shape: tuple[int, int], idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`sample_basis` of the pixels and the usable ones added to ``ev``'s rows ``idx`` (each
    once): one compiled pass with numba (:func:`diffuser_lab.backends.features.sample_add`, bit
    for bit the same), else numpy. Returns the (M, k + s) samples and (M,) usable."""
    mass, links = ev.mass, ev.links
    done = compiled_features.sample_add(prep.coords, prep.gram, prep.valid, fshape, shape, rows, cols, idx, mass,
                                        links)
    if done is not None:
        return done
    f, good, _ = sample_basis(prep, fshape, rows, cols, shape)
    mass[idx[good]] += f[good]
    links[idx[good]] += 1
    return f, good


def _add_features(ev: Evidence, points: np.ndarray, frame: Frame, depth_tol: float, pixel_radius: int,
                  best: BestView | None = None, basis=None, energy: np.ndarray | None = None,
                  hook: Optional[LinkHook] = None) -> np.ndarray:
    fmap = frame.features
    D = ev.mass.shape[1] if basis is None else basis.dim
    if fmap.ndim != 3 or fmap.shape[2] != D:
        raise ValueError(f"frame {frame.name}: feature map of shape {fmap.shape}, expected (h, w, {D})")
    idx, rows, cols = visible_projection(points, frame, depth_tol)
    ev.points_per_frame.append(int(idx.size))
    h, w = frame.shape
    prepared = prepare_features(fmap) if basis is None else project_features(fmap, basis)
    r = pixel_radius
    for dr in range(-r, r + 1):
        for dc in range(-r, r + 1):
            rr, cc = rows + dr, cols + dc
            ok = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
            i, rr, cc = idx[ok], rr[ok], cc[ok]
            for lo in range(0, i.size, FEATURE_CHUNK):  # each point once per offset: no repeated rows
                sl = slice(lo, lo + FEATURE_CHUNK)
                if basis is None:
                    f, good = sample_features(fmap, rr[sl], cc[sl], (h, w), prepared)
                    ev.mass[i[sl][good]] += f[good]
                    ev.links[i[sl][good]] += 1
                else:
                    f, good = _add_basis_samples(ev, prepared, fmap.shape[:2], rr[sl], cc[sl], (h, w), i[sl])
                    if energy is not None:  # the share of the pixels' energy the basis keeps
                        kept = f[good, : basis.k]
                        energy[0] += float(np.einsum("ij,ij->", kept, kept, dtype=np.float64))
                        energy[1] += int(good.sum())
                if best is not None and dr == 0 and dc == 0:
                    best.offer(i[sl][good], f[good] if basis is None else f[good, : basis.k])
                if hook is not None:  # (a lifting rule's run diffuses no basis: unit features in R^D)
                    hook(frame, points, i[sl][good], rr[sl][good], cc[sl][good], f[good])
    return idx


def add_frame(ev: Evidence, points: np.ndarray, frame: Frame, *, depth_tol: float = 0.05,
              pixel_radius: int = 0, hard: bool = False, best: BestView | None = None, basis=None,
              energy: np.ndarray | None = None, hook: Optional[LinkHook] = None, checked: bool = False) -> np.ndarray:
    """Add one frame's pixel-to-point links to ``ev`` in place (Eq. 12, one term of Eq. 11):
    class masses, or unit features when the frame has a feature map (module docstring); ``hook``
    (:data:`LinkHook`) sees each link set with its vectors.

    ``basis`` (a :class:`~diffuser_lab.method.basis.FeatureBasis`, feature maps only): ``ev.mass``
    has its k + s columns and each unit feature is added as its coordinates (:func:`sample_basis`:
    exactly the projection of the full path's unit feature); ``energy`` (2,) float64, when given,
    gains the linked pixels' kept energy (sum of |coordinates on the k vectors|^2) and their number.
    ``checked``: the frame's label ids were checked when its evidence was first added (an online
    map adds a kept frame's evidence again for its new points).

    Returns (M,) int64 sorted indices of the points that passed the visibility check (their
    rows of ``ev`` may have changed; the others did not)."""
    if getattr(frame, "features", None) is not None:
        if basis is None:
            return _add_features(ev, points, frame, depth_tol, pixel_radius, best, hook=hook)
        with blas_one_thread():  # a basis' products are small: OpenBLAS's spinning workers cost more
            return _add_features(ev, points, frame, depth_tol, pixel_radius, best, basis, energy, hook)
    n, num_classes = ev.mass.shape
    labels, probs = _class_vectors(frame, num_classes, hard, checked)
    if probs is None and pixel_radius == 0 and hook is None:
        seen = hard_votes(points, frame.T_cw, frame.K, frame.depth, labels, depth_tol, ev.mass, ev.links)
        if seen is not None:
            ev.points_per_frame.append(int(seen.size))
            return seen
    idx, rows, cols = visible_projection(points, frame, depth_tol)
    ev.points_per_frame.append(int(idx.size))
    h, w = frame.shape
    r = pixel_radius
    for dr in range(-r, r + 1):  # a handful of window offsets; each point index appears once per offset
        for dc in range(-r, r + 1):
            rr, cc = rows + dr, cols + dc
            ok = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
            i, rr, cc = idx[ok], rr[ok], cc[ok]
            if probs is not None:
                vec = probs[rr, cc].astype(np.float32)
                s = vec.sum(1)
                good = s > 0  # a pixel without probability mass is no evidence
                vec = vec[good] / s[good, None]  # rows sum to 1 (Eq. 13)
                ev.mass[i[good]] += vec
                ev.links[i[good]] += 1
            else:
                lab = labels[rr, cc].astype(np.int64)
                good = lab != IGNORE
                ev.mass[i[good], lab[good]] += 1.0
                ev.links[i[good]] += 1
                if hook is not None:
                    vec = np.zeros((int(good.sum()), num_classes), np.float32)
                    vec[np.arange(vec.shape[0]), lab[good]] = 1.0
            if hook is not None:
                hook(frame, points, i[good], rr[good], cc[good], vec)
    return idx


def accumulate(points: np.ndarray, frames: Iterable[Frame], num_classes: int, *, depth_tol: float = 0.05,
               pixel_radius: int = 0, hard: bool = False, best: BestView | None = None,
               hook: Optional[LinkHook] = None) -> Evidence:
    """Evidence of all ``frames`` for (N, 3) world ``points``.

    Args:
        hard: use each pixel's argmax label even when probabilities are given
            (Bayesian fusion by votes).
        best: feature maps: also track each point's most confident view (:class:`BestView`).
        hook: sees every link set (:data:`LinkHook`; a lifting rule's streaming update).
    """
    ev = Evidence.empty(points.shape[0], num_classes)
    for frame in frames:
        add_frame(ev, points, frame, depth_tol=depth_tol, pixel_radius=pixel_radius, hard=hard, best=best,
                  hook=hook)
    return ev


class RunEvidence:
    """A run's evidence, frame by frame: the method's (``pixel_radius``) and the Bayesian
    baseline's (the standard single projected pixel; ``votes``: one-hot argmax votes instead of
    likelihoods), one and the same when neither differs. The baseline is therefore the same in
    every run on the same frames, whatever the method's pixel neighbourhood.

    Rows are points; ``capacity`` > N leaves room for a growing map (:meth:`grow`).

    Attributes:
        method, baseline: :class:`Evidence` over the first N rows (baseline is method when shared).
    """

    def __init__(self, n: int, num_classes: int, *, depth_tol: float = 0.05, pixel_radius: int = 0,
                 votes: bool = False, capacity: int = 0):
        self.depth_tol, self.pixel_radius, self.votes = float(depth_tol), int(pixel_radius), bool(votes)
        self.separate = self.votes or self.pixel_radius != 0
        self.num_classes = int(num_classes)
        self.n = 0
        self._mass = np.zeros((0, num_classes), np.float32)
        self._links = np.zeros(0, np.int32)
        self._base_mass, self._base_links = self._mass, self._links
        self._ppf: list[int] = []
        self._base_ppf: list[int] = []
        self.best: BestView | None = None  # set by a features run: the most confident view's feature
        self.basis = None  # a features run's FeatureBasis (predictions.basis=auto): mass has its k + s columns
        self.energy = np.zeros(2)  # with a basis: the linked pixels' kept energy and their number
        self.hook: Optional[LinkHook] = None  # set by a lifting rule's run: sees the method's links (rows 0..N-1)
        self.grow(n, max(n, capacity))

    @classmethod
    def of(cls, cfg, n: int, num_classes: int, capacity: int = 0) -> "RunEvidence":
        """As a run's config says (``evidence.depth_tol``, ``evidence.pixel_radius``, ``method.bayesian_mode``)."""
        return cls(n, num_classes, depth_tol=cfg.evidence.depth_tol, pixel_radius=cfg.evidence.pixel_radius,
                   votes=cfg.method.bayesian_mode == BayesianMode.votes, capacity=capacity)

    def grow(self, n: int, capacity: int = 0) -> None:
        """``n`` rows (new ones without evidence); room for ``capacity`` (doubling when short)."""
        if n > self._mass.shape[0] or capacity > self._mass.shape[0]:
            cap = max(n, capacity, 2 * self._mass.shape[0])

            def grown(a):
                out = np.zeros((cap,) + a.shape[1:], a.dtype)
                out[: self.n] = a[: self.n]
                return out

            self._mass, self._links = grown(self._mass), grown(self._links)
            if self.separate:
                self._base_mass, self._base_links = grown(self._base_mass), grown(self._base_links)
            else:
                self._base_mass, self._base_links = self._mass, self._links
        self.n = int(n)

    @property
    def mass_store(self) -> np.ndarray:
        """(capacity, C) float32 the method's mass with its room (a system reads it by row)."""
        return self._mass

    @property
    def method(self) -> Evidence:
        return Evidence(mass=self._mass[: self.n], links=self._links[: self.n], points_per_frame=self._ppf)

    @property
    def baseline(self) -> Evidence:
        if not self.separate:
            return self.method
        return Evidence(mass=self._base_mass[: self.n], links=self._base_links[: self.n],
                        points_per_frame=self._base_ppf)

    def fused(self, frame: Frame) -> bool:
        """Whether ``frame``'s evidence is the compiled single pass's (:func:`~diffuser_lab.backends.evidence.hard_votes`:
        hard labels, one pixel, the baseline shared, no hook, no basis), which
        :class:`~diffuser_lab.backends.evidence.KeptVotes` adds again for many frames at once."""
        return not (self.separate or self.pixel_radius or self.hook is not None or self.basis is not None
                    or frame.labels is None or frame.probs is not None
                    or getattr(frame, "features", None) is not None)

    def add_kept(self, points: np.ndarray, kept, which: np.ndarray, lo: int = 0) -> None:
        """The :meth:`fused` frames ``which`` of ``kept`` (a :class:`~diffuser_lab.backends.evidence.KeptVotes`),
        added before (their checks done then), added again for the points rows lo..lo+M-1."""
        if len(which):
            hi = lo + points.shape[0]
            kept.add_to(points, which, self.depth_tol, self._mass[lo:hi], self._links[lo:hi])

    def add(self, points: np.ndarray, frame: Frame, lo: int = 0, checked: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Add ``frame``'s evidence for the points ``points`` (M, 3) world metres, rows lo..lo+M-1
        (``checked``: its label ids were checked before, :func:`add_frame`).
        Returns the rows (sorted int64) that passed its visibility check for the method's and for
        the baseline's evidence (the same array when shared)."""
        hi = lo + points.shape[0]
        ev = Evidence(mass=self._mass[lo:hi], links=self._links[lo:hi], points_per_frame=self._ppf)
        best = self.best if lo == 0 and self.best is not None and hi <= self.best.score.size else None
        hook = self.hook if lo == 0 else None
        seen = lo + add_frame(ev, points, frame, depth_tol=self.depth_tol, pixel_radius=self.pixel_radius,
                              best=None if self.separate else best, basis=self.basis, energy=self.energy,
                              hook=hook, checked=checked)
        if not self.separate:
            return seen, seen
        base = Evidence(mass=self._base_mass[lo:hi], links=self._base_links[lo:hi], points_per_frame=self._base_ppf)
        return seen, lo + add_frame(base, points, frame, depth_tol=self.depth_tol, hard=self.votes, best=best,
                                    basis=self.basis, checked=checked)
