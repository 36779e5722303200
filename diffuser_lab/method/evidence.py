"""Pixel-to-point evidence (paper Eqs. 1-2, 11-13).

For every frame, a point x_i is linked to the pixel it projects to (Eq. 2) when the
projection falls inside the image and passes the depth-consistency (occlusion) check
|z_i - depth(pixel)| <= depth_tol. With ``pixel_radius`` r > 0 the point is linked to
every pixel of the (2r+1)x(2r+1) window around that pixel (as in LDLS); visibility is
decided at the centre pixel. Each link carries the pixel's one-hot label or its class
probabilities (Eq. 8), so ``mass[i, c]`` is the number of linked pixels voting for
class c: Sum_k Z^{I_k->X} of Eq. 12 divided by lambda, which the diffusion applies
(Eqs. 14-15). Frames are consumed one at a time, so memory does not grow with their number.

Speed: hard labels with ``pixel_radius`` 0 (the paper's setting) go through one fused compiled
pass per frame when numba is installed (:func:`diffuser_lab.backends.numba.evidence.evidence_hard`: projection
in float64, bounds, depth check and the vote, no temporaries); everything else, and the pure
numpy path (``DIFFUSER_LAB_NUMBA=0``), uses the vectorised code below.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

from diffuser_lab.data.geometry import project
from diffuser_lab.data.scene import IGNORE, Frame


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
        """(N,) bool: the point received pixel mass."""
        return self.mass.sum(1) > 0


def visible_projection(points: np.ndarray, frame: Frame, depth_tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points of ``frame`` that project inside the image and pass the depth check.

    Returns:
        idx: (M,) int64 indices into ``points``; rows, cols: (M,) int64 pixel of each.
    """
    h, w = frame.shape
    u, v, z = project(points, frame.K, frame.T_cw)
    cols = np.rint(u)
    rows = np.rint(v)
    inside = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)  # NaN (behind camera) -> False
    idx = np.flatnonzero(inside)
    rows = rows[idx].astype(np.int64)
    cols = cols[idx].astype(np.int64)
    d = frame.depth[rows, cols]
    ok = (d > 0) & (np.abs(z[idx] - d) <= depth_tol)
    return idx[ok], rows[ok], cols[ok]


def _class_vectors(frame: Frame, num_classes: int, hard: bool) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The frame's per-pixel labels: (H,W) ids for hard evidence or (H,W,C) probabilities."""
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
    lo, hi = int(frame.labels.min()), int(frame.labels.max())
    if lo < IGNORE or hi >= num_classes:
        raise ValueError(f"frame {frame.name}: label ids in [{lo}, {hi}], expected {IGNORE} (no label) "
                         f"or 0..{num_classes - 1}")
    return frame.labels, None


def add_frame(ev: Evidence, points: np.ndarray, frame: Frame, *, depth_tol: float = 0.05,
              pixel_radius: int = 0, hard: bool = False) -> np.ndarray:
    """Add one frame's pixel-to-point links to ``ev`` in place (Eq. 12, one term of Eq. 11).

    Returns (M,) int64 sorted indices of the points that passed the visibility check (their
    rows of ``ev`` may have changed; the others did not)."""
    n, num_classes = ev.mass.shape
    labels, probs = _class_vectors(frame, num_classes, hard)
    if probs is None and pixel_radius == 0 and ev.mass.flags.c_contiguous:
        from diffuser_lab.backends import numba as nb
        from diffuser_lab.backends.numba import evidence as nb_evidence

        if nb.available():
            T = np.asarray(frame.T_cw, np.float64)
            seen = nb_evidence.evidence_hard(np.ascontiguousarray(points, np.float32), T[:3, :3].copy(),
                                         T[:3, 3].copy(), np.asarray(frame.K, np.float64),
                                         np.ascontiguousarray(frame.depth, np.float32),
                                         np.ascontiguousarray(labels), depth_tol, ev.mass, ev.links)
            seen = np.flatnonzero(seen)
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
                ev.mass[i[good]] += vec[good] / s[good, None]  # rows sum to 1 (Eq. 13)
                ev.links[i[good]] += 1
            else:
                lab = labels[rr, cc].astype(np.int64)
                good = lab != IGNORE
                ev.mass[i[good], lab[good]] += 1.0
                ev.links[i[good]] += 1
    return idx


def accumulate(points: np.ndarray, frames: Iterable[Frame], num_classes: int, *, depth_tol: float = 0.05,
               pixel_radius: int = 0, hard: bool = False) -> Evidence:
    """Evidence of all ``frames`` for (N, 3) world ``points``.

    Args:
        hard: use each pixel's argmax label even when probabilities are given
            (Bayesian fusion by votes).
    """
    ev = Evidence.empty(points.shape[0], num_classes)
    for frame in frames:
        add_frame(ev, points, frame, depth_tol=depth_tol, pixel_radius=pixel_radius, hard=hard)
    return ev
