"""How well the methods' class distributions are calibrated: ECE, NLL, Brier, reliability bins.

Each method's scores become one class distribution per point: Diffuser's and LDLS's Z
row-normalised, the Bayesian baseline's pixel mass normalised (the vote fractions, or the
normalised sum of likelihoods), direct projection's one view normalised (its one-hot label or
soft input). :func:`with_temperature` optionally sharpens (T < 1) or flattens (T > 1) it as
p <- softmax(log p / T); the argmax, so every label, is unchanged.

Scored against the ground truth (``IGNORE`` excluded) as

- **ECE** (expected calibration error, top-label, Guo et al. 2017, "On calibration of modern
  neural networks"): confidences max_c p_c split into ``bins`` equal-width bins
  ((m-1)/B, m/B] (a confidence within EDGE_TOL of an edge, e.g. a vote fraction 4/5 in float32,
  in the lower bin), ECE = sum_m |B_m|/n |accuracy(B_m) - confidence(B_m)|, in percent;
- **NLL**: mean of -ln max(p_gt, EPS) in nats (EPS = 1e-6: a one-hot input wrong at a point
  costs 13.8 nats there, so the NLL of hard-label methods is mostly their error rate x 13.8);
- **Brier** (multi-class, Brier 1950): mean of sum_c (p_c - [c = gt])^2, in [0, 2].

Points (pixels) with no distribution (no evidence reached them, no depth in the frame) count
as **uniform** (p_c = 1/C), as an unlabeled point counts as a miss in the mIoU: a method gains
nothing by abstaining; ``n_uniform`` says how many. A tie among the top classes counts as the
expected accuracy of picking one of them at random (1/#ties if the true class is among them),
so a uniform row has confidence = accuracy = 1/C.

Everything is accumulated per point with vectorised numpy (:class:`Calibration`), so frames can
be added one at a time, and a (M, C) score array on a voxel cloud is scored on the N original
points through a row index, CHUNK points at a time (no (N, C) or extra (M, C) array).

A run's methods (:func:`of_methods`, summary.json's ``metrics.calibration``) are scored on their
distributions as ``scores.npy`` keeps them (:func:`stored`: float16 rows), so the figures of a run
computed again from its saved scores (:func:`diffuser_lab.runs.scores.calibration_of_run`) are
the same numbers; :func:`confidence` is a point's top score, margin and entropy of that row.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from diffuser_lab.backends.records import to_float16
from diffuser_lab.data.scene import IGNORE

BINS = 15
"""Equal-width confidence bins of the ECE and the reliability diagram (Guo et al. 2017)."""
EDGE_TOL = 3e-4
"""Confidences within this (a probability) above a bin's upper edge count in that bin: a vote fraction
such as 3/5 sits on an edge, and float16 (:func:`stored`, rounding by at most 2^-12 = 2.4e-4) or
float32 puts it just above."""
STORED = np.float16
"""The precision of the distributions a run saves (scores.npy) and scores (:func:`stored`)."""
CHUNK = 1 << 16
"""Points scored at a time by :meth:`Calibration.add`, and made at a time by :func:`point_rows` (memory CHUNK x C)."""
EPS = 1e-6
"""Floor on p_gt in the NLL (float32 distributions carry ~7 digits: below this p is rounding)."""


def posterior(scores: np.ndarray) -> np.ndarray:
    """(M, C) non-negative scores (Z, pixel mass) -> (M, C) float32 rows summing to 1; a row
    without any score stays all zero (no distribution: scored as uniform)."""
    s = np.asarray(scores, np.float32)
    if s.ndim != 2:
        raise ValueError(f"class scores must be (points, classes), got shape {s.shape}")
    total = _row_sums(s)
    return np.divide(s, total, out=np.zeros_like(s), where=total > 0).astype(np.float32, copy=False)


def _row_sums(s: np.ndarray) -> np.ndarray:
    """(M, 1) float64 row sums of (M, C) ``s``, each a function of its row alone (a sum cast on the
    fly goes through numpy's buffers, which may cut a row where another chunk of rows would not)."""
    return np.ascontiguousarray(s, np.float64).sum(1, keepdims=True)


def stored(scores: np.ndarray) -> np.ndarray:
    """(M, C) non-negative scores -> (M, C) :data:`STORED` (float16) rows, each its row divided by its
    sum (all zero where the row is: no distribution): what ``scores.npy`` holds and what
    :func:`of_methods` scores. Each row is a function of its own scores only (any chunk of rows gives
    the same bits)."""
    s = np.ascontiguousarray(scores, np.float64)
    if s.ndim != 2:
        raise ValueError(f"class scores must be (points, classes), got shape {s.shape}")
    total = s.sum(1, keepdims=True)
    # via float32: numpy's own float16 cast takes a slow path for subnormals (a distribution's tiny shares)
    return to_float16(np.divide(s, total, out=np.zeros_like(s), where=total > 0).astype(np.float32))


def confidence(p: np.ndarray) -> np.ndarray:
    """(M, C) class distributions (:func:`stored` rows) -> (M, 3) float32 per point: the top score
    max_c p_c, the margin top - second, the entropy -sum_c p_c ln p_c in nats (0: one class; ln C:
    uniform); a row without a distribution (all zero) gets 0, 0, NaN."""
    q = np.asarray(p, np.float32)
    q = np.concatenate([q, np.zeros((q.shape[0], 2 - q.shape[1]), np.float32)], 1) if q.shape[1] < 2 else q
    two = -np.partition(-q, 1, axis=1)[:, :2]  # the top score, then the second
    ent = 0.0 - np.sum(q * np.log(q, out=np.zeros_like(q), where=q > 0), axis=1, dtype=np.float64)
    return np.stack([two[:, 0], two[:, 0] - two[:, 1], np.where(two[:, 0] > 0, ent, np.nan)], 1).astype(np.float32)


def with_temperature(p: np.ndarray, temperature: float) -> np.ndarray:
    """p <- softmax(log p / T) row-wise, for (M, C) distributions ``p``; T = 1 returns ``p`` itself.

    Computed as (p / max p)^(1/T) renormalised, so small T cannot underflow a whole row; zero
    entries stay zero and all-zero rows stay all zero. The order of each row's entries, hence
    its argmax, is kept for every T > 0.
    """
    if not temperature > 0:
        raise ValueError(f"temperature={temperature!r}: expected > 0")
    if temperature == 1.0:
        return p
    top = p.max(1, keepdims=True)
    q = np.divide(p, top, out=np.zeros_like(p, dtype=np.float32), where=top > 0)
    q **= np.float32(1.0 / temperature)  # entries that underflow were < 1e-38 ** T of the top: nil
    return posterior(q)


def point_rows(scores: np.ndarray, rows: Optional[np.ndarray], n: int):
    """(lo, hi, (hi - lo, C) float16 stored rows) of the N = ``n`` original points in order, CHUNK at a
    time: point i's row is ``scores[rows[i]]`` (``rows`` None: row i) normalised as scores.npy keeps it."""
    for lo in range(0, n, CHUNK):
        hi = min(n, lo + CHUNK)
        yield lo, hi, stored(scores[lo:hi] if rows is None else scores[rows[lo:hi]])


def point_confidence(scores: np.ndarray, rows: Optional[np.ndarray]) -> np.ndarray:
    """(N, 3) float32 top score, margin and entropy (:func:`confidence`) of each original point's
    stored row (:func:`point_rows`): the values labels.ply, the LAS output and run.rrd carry."""
    n = len(scores) if rows is None else len(rows)
    out = np.empty((n, 3), np.float32)
    for lo, hi, p in point_rows(scores, rows, n):
        out[lo:hi] = confidence(p)
    return out


class Calibration:
    """Accumulates a method's calibration over points (or pixels) added in parts.

    ``add(p, gt, rows)`` scores the distributions ``p[rows]`` against ``gt``; :meth:`result`
    gives the figures. ``num_classes`` is C (the uniform distribution of points without one).
    """

    def __init__(self, num_classes: int, bins: int = BINS, stored: bool = False):
        if bins < 1:
            raise ValueError(f"calibration bins={bins!r}: expected >= 1")
        self.num_classes, self.bins = int(num_classes), int(bins)
        self.stored = bool(stored)  # score the rows as scores.npy keeps them (:func:`stored`)
        self.count = np.zeros(self.bins, np.int64)
        self.sum_conf = np.zeros(self.bins)
        self.sum_acc = np.zeros(self.bins)
        self.nll = self.brier = 0.0
        self.n = self.n_uniform = 0

    def add(self, scores: np.ndarray, gt: np.ndarray, rows: Optional[np.ndarray] = None,
            temperature: float = 1.0) -> None:
        """Score the class distributions of ``scores`` against ``gt``.

        Args:
            scores: (M, C) non-negative class scores (Z, pixel mass, or distributions already):
                each row is normalised (:func:`posterior`; made with ``stored``: :func:`stored`) and
                tempered (:func:`with_temperature`). float16 scores are stored rows (scores.npy),
                scored as they are.
            gt: (N,) or any-shape integer ground truth (class ids or IGNORE).
            rows: ``gt``'s shape, int: the row of ``scores`` of each ground-truth point, -1 = no
                distribution (uniform); None = row i for point i (needs M = N).
            temperature: T of :func:`with_temperature` (1 = as given).

        The points are taken CHUNK at a time (their rows gathered, normalised and scored), so
        memory stays at CHUNK x C whatever M and N.
        """
        c = self.num_classes
        if scores.ndim != 2 or scores.shape[1] != c:
            raise ValueError(f"class scores of shape {scores.shape}: expected (points, {c})")
        if not temperature > 0:
            raise ValueError(f"temperature={temperature!r}: expected > 0")
        g = np.asarray(gt).ravel().astype(np.int64)
        r = np.arange(scores.shape[0]) if rows is None else np.asarray(rows).ravel().astype(np.int64)
        if r.shape != g.shape:
            raise ValueError(f"{r.size} distribution rows for {g.size} ground-truth points")
        keep = g != IGNORE
        g, r = g[keep], r[keep]
        if not g.size:
            return
        if g.min() < 0 or g.max() >= c:
            raise ValueError(f"ground-truth class ids must be in [0, {c}) or IGNORE, got {g.min()}..{g.max()}")
        if r.max() >= scores.shape[0]:
            raise ValueError(f"distribution row {r.max()} of {scores.shape[0]}")
        for a in range(0, g.size, CHUNK):
            self._add(scores, g[a:a + CHUNK], r[a:a + CHUNK], temperature)

    def _add(self, scores: np.ndarray, g: np.ndarray, r: np.ndarray, temperature: float) -> None:
        c = self.num_classes
        has = r >= 0
        s = scores[r[has]]
        if s.dtype == STORED or self.stored:  # the rows as saved, taken as they are (sums 1 within float16's step)
            p = with_temperature((s if s.dtype == STORED else stored(s)).astype(np.float32), temperature)
        else:
            p = with_temperature(posterior(s), temperature)  # (n with a row, C)
        pmax = p.max(1)
        with_p = pmax > 0  # a row of zeros (no evidence reached it) is no distribution either
        has[has] = with_p
        p, pmax, gh = p[with_p], pmax[with_p], g[has]
        u = 1.0 / c
        n = g.size
        pg, conf, acc = np.full(n, u), np.full(n, u), np.full(n, u)
        brier = np.full(n, 1.0 - u)
        pg[has] = p[np.arange(p.shape[0]), gh]
        conf[has] = pmax
        acc[has] = (pg[has] == conf[has]) / (p == pmax[:, None]).sum(1)  # ties: expected accuracy
        brier[has] = np.einsum("ij,ij->i", p, p, dtype=np.float64) - 2.0 * pg[has] + 1.0
        # bin m holds ((m-1)/B, m/B]; vote fractions such as 3/5 sit on an edge, where float16 or float32
        # rounding would scatter them over two bins: an edge within EDGE_TOL belongs to the lower one
        b = np.clip(np.ceil((conf - EDGE_TOL) * self.bins).astype(np.int64) - 1, 0, self.bins - 1)
        self.count += np.bincount(b, minlength=self.bins)
        self.sum_conf += np.bincount(b, conf, minlength=self.bins)
        self.sum_acc += np.bincount(b, acc, minlength=self.bins)
        self.nll += float(-np.log(np.maximum(pg, EPS)).sum())
        self.brier += float(brier.sum())
        self.n += int(n)
        self.n_uniform += int((~has).sum())

    def result(self) -> dict:
        """``ece`` (percent), ``nll`` (nats per point), ``brier`` (per point), ``n_points`` scored,
        ``n_uniform`` (of them without a distribution) and the reliability ``bins``: per bin
        ``count``, mean ``confidence`` and ``accuracy`` (percent; None for an empty bin) and its
        upper ``edge``. The figures are None when no point was scored."""
        n = self.n
        nz = self.count > 0
        conf = np.divide(self.sum_conf, self.count, out=np.zeros(self.bins), where=nz)
        acc = np.divide(self.sum_acc, self.count, out=np.zeros(self.bins), where=nz)
        ece = float(100.0 * np.sum(self.count * np.abs(acc - conf)) / n) if n else None
        return {
            "ece": ece, "nll": self.nll / n if n else None, "brier": self.brier / n if n else None,
            "n_points": n, "n_uniform": self.n_uniform,
            "bins": {"edge": [round((m + 1) / self.bins, 6) for m in range(self.bins)],
                     "count": self.count.tolist(),
                     "confidence": [float(100 * v) if k else None for v, k in zip(conf, nz)],
                     "accuracy": [float(100 * v) if k else None for v, k in zip(acc, nz)]},
        }


def calibration(p: np.ndarray, gt: np.ndarray, rows: Optional[np.ndarray] = None, bins: int = BINS,
                temperature: float = 1.0) -> dict:
    """:meth:`Calibration.result` of the (M, C) class scores or distributions ``p`` scored at
    ``gt`` (see :meth:`Calibration.add`)."""
    cal = Calibration(p.shape[1], bins)
    cal.add(p, gt, rows, temperature)
    return cal.result()


def of_methods(scores: dict, gt: np.ndarray, rows: Optional[np.ndarray], num_classes: int,
               temperature: float = 1.0, bins: int = BINS) -> dict:
    """``{method: figures}`` (:meth:`Calibration.result` plus its ``temperature``) of each
    method's (M, C) ``scores`` (Z or pixel mass), normalised as scores.npy keeps them
    (:func:`stored`), tempered (:func:`with_temperature`) and scored at ``gt`` through ``rows``
    (see :meth:`Calibration.add`)."""
    out = {}
    for name, s in scores.items():
        cal = Calibration(num_classes, bins, stored=True)
        cal.add(s, gt, rows, temperature)
        out[name] = {**cal.result(), "temperature": float(temperature)}
    return out
