"""The field's training-free lifting rules (2024-2026) on the project's evidence: streaming, per point.

Each rule turns the links the one frame loop makes (a point, the pixel it projects to past the depth
check, that pixel's class distribution / one-hot label or unit feature: :data:`~diffuser_lab.method.
evidence.LinkHook`) into a per-point value, and holds only running state per point, never a point's
observations (memory independent of the number of frames):

=========  ==========================================================  ========================
name       rule (paper, equation)                                      state per point
=========  ==========================================================  ========================
weighted   Occam's LGS (arXiv 2412.01807) / Dr. Splat (CVPR 2025): the  sum of w x, sum of w
           weighted average f_i = sum_v w_iv x_v / sum_v w_iv, w the
           view's contribution to the element (:func:`link_weights`)
median     VALA (arXiv 2509.05515): visibility gate, then the streaming  estimate m, sum of
           weighted geometric median in cosine space (Weiszfeld steps)   w x / d, sum of w / d
topk       The Bare Necessities (arXiv 2412.01539): the k most           k values, k scores
           confident views averaged (k = 1: the best view)
vote       LabelMaker (Weder et al., 3DV 2024): hard votes of the views  C counts
           past the depth check, argmax
=========  ==========================================================  ========================

For labels a rule reads each link's class distribution (the Bayesian evidence's vector, Eq. 13:
rows summing to 1) or one-hot label; for features the unit feature (:mod:`diffuser_lab.method.features`).
:meth:`Rule.values` is (N, C) class scores for labels and (N, D) features for features (unit rows;
0: no link), or class votes (:attr:`Rule.classes`: ``vote``, whose features run votes the views'
zero-shot labels). Rows without a link are 0 (no label).

Where the papers weigh a Gaussian's share of a pixel's ray (alpha-blending weight, the marginal
contribution), a point's link has none; its weight is the point analogue (:func:`link_weights`): the
pixels its surface element covers in the view (cos(incidence) / z^2) times the depth check's margin,
computed from the frame's depth at evidence time.

The two other rules of the bench are not rules of this module: Splat Feature Solver's Tikhonov-guided
closed form is ``solver=exact solver.tikhonov=t`` (:func:`diffuser_lab.method.exact.tikhonov_scale`),
LUDVIG's feature-aware graph is ``graph.affinity`` (:mod:`diffuser_lab.method.affinity`).
"""
from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from diffuser_lab.data.geometry import normals_from_depth
from diffuser_lab.data.scene import IGNORE

from .features import normalised

__all__ = ["Rule", "Weighted", "Median", "TopK", "Vote", "link_weights"]

WEISZFELD_EPS = 1e-3
"""Weiszfeld's distance floor (the unit of the vectors: unit features, class distributions): a link
at the estimate weighs w / eps, not infinity."""


def link_weights(frame, points: np.ndarray, idx: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                 depth_tol: float) -> np.ndarray:
    """(M,) float32 per-link weights of the points ``idx`` of ``points`` at pixels ``rows``, ``cols`` of
    ``frame``: how much the pixel's ray belongs to the point, the point analogue of a Gaussian's
    alpha-blending weight alpha_i T_i (Occam's LGS Sec. 3, Dr. Splat Sec. 3, VALA's marginal
    contribution w_i(r) = alpha_i(r) T_i(r)):

        w = |cos theta| * (1 m / z)^2 * exp(-2 (dz / depth_tol)^2)

    theta the angle between the pixel's ray and the surface normal of the frame's depth image at
    that pixel (central differences, :func:`~diffuser_lab.data.geometry.normals_from_depth`; 1 where
    the depth has no normal), z the point's depth in the view (cos theta / z^2: the share of the view's
    pixels its surface element covers) and dz = z - depth(pixel) the depth check's margin (a Gaussian
    of sigma = depth_tol / 2: 1 at the surface, 0.14 at the check's limit)."""
    if idx.size == 0:
        return np.zeros(0, np.float32)
    T = np.asarray(frame.T_cw, np.float64)
    pc = np.asarray(points[idx], np.float64) @ T[:3, :3].T + T[:3, 3]
    z = pc[:, 2]
    dz = z - np.asarray(frame.depth, np.float64)[rows, cols]
    n = normals_from_depth(frame.depth, frame.K, np.stack([rows, cols], axis=1))
    ray = pc / np.maximum(np.linalg.norm(pc, axis=1, keepdims=True), 1e-12)
    cos = np.abs(np.einsum("ij,ij->i", n, ray))
    cos = np.where(np.einsum("ij,ij->i", n, n) > 0, cos, 1.0)
    w = cos / np.maximum(z, 1e-6) ** 2 * np.exp(-2.0 * (dz / depth_tol) ** 2)
    return w.astype(np.float32)


class Rule:
    """A streaming lifting rule: a :data:`~diffuser_lab.method.evidence.LinkHook` (call it with each
    link set) with per-point running state, and the per-point result (:meth:`values`).

    Args:
        n: points; dim: C (labels) or D (features); features: the vectors are unit features.
    Attributes:
        classes: :meth:`values` are class scores even in a features run (``vote``).
        weighted: the rule weighs links by :func:`link_weights` (needs ``depth_tol``).
    """

    name = ""
    classes = False
    weighted = False

    def __init__(self, n: int, dim: int, *, features: bool = False, depth_tol: float = 0.05):
        self.n, self.dim, self.features, self.depth_tol = int(n), int(dim), bool(features), float(depth_tol)

    @classmethod
    def of(cls, n: int, *, dim: int, features: bool, depth_tol: float, **run) -> "Rule":
        """The rule for ``n`` points of ``dim`` columns (C; D in a features run) as a run sets it
        (:meth:`diffuser_lab.method.fusion.FusionMethod.lifting_rule`); ``run`` holds what some rules
        take besides: ``top_k``, ``num_classes``, a features run's ``confidence`` and ``classify``
        (:meth:`diffuser_lab.method.space.Features.rule_inputs`)."""
        return cls(n, dim, features=features, depth_tol=depth_tol)

    def __call__(self, frame, points, idx, rows, cols, vec) -> None:
        if idx.size == 0:
            return
        w = link_weights(frame, points, idx, rows, cols, self.depth_tol) if self.weighted else None
        self.add(idx, np.asarray(vec, np.float32), w)

    def add(self, idx: np.ndarray, x: np.ndarray, w: Optional[np.ndarray]) -> None:
        """Points ``idx`` (M,) (each once) observed as ``x`` (M, dim) with link weights ``w`` (M,)."""
        raise NotImplementedError

    def values(self) -> np.ndarray:
        """(n, dim) float32 the per-point result (class scores / unit features; 0 rows: no link)."""
        raise NotImplementedError

    def _out(self, v: np.ndarray) -> np.ndarray:
        return normalised(v)[0] if self.features else np.asarray(v, np.float32)


class Weighted(Rule):
    """Occam's LGS (Cheng et al., arXiv 2412.01807, Sec. 3, the maximum-likelihood uplift) and Dr. Splat
    (Jun-Seong et al., CVPR 2025, Sec. 3.2, the weighted feature registration): the weighted average of
    a point's observations,

        f_i = sum_(v,p) w_i(v, p) x_(v,p) / sum_(v,p) w_i(v, p),

    with w the link's contribution (:func:`link_weights`). Features: unit rows (the cosine of the
    average). State: sum of w x (dim) and sum of w per point."""

    name = "weighted"
    weighted = True

    def __init__(self, n: int, dim: int, **kw):
        super().__init__(n, dim, **kw)
        self.sum = np.zeros((self.n, self.dim), np.float32)
        self.weight = np.zeros(self.n, np.float32)

    def add(self, idx, x, w):
        self.sum[idx] += w[:, None] * x
        self.weight[idx] += w

    def values(self):
        v = np.divide(self.sum, self.weight[:, None], out=np.zeros_like(self.sum), where=self.weight[:, None] > 0)
        return self._out(v)


class Median(Rule):
    """VALA (Wang et al., arXiv 2509.05515, Sec. 3: the visibility-aware gate, then the streaming
    weighted geometric median in cosine space). The geometric median m* = argmin_m sum_t w_t |x_t - m|
    by Weiszfeld's fixed point m <- sum_t (w_t / d_t) x_t / sum_t (w_t / d_t), d_t = |x_t - m|, taken
    as the views stream in (one Weiszfeld step per observation, as VALA's per-view update):

        d_t = max(|x_t - m_(t-1)|, eps),  S_t = S_(t-1) + w_t x_t / d_t,  T_t = T_(t-1) + w_t / d_t,
        m_t = S_t / T_t   (features: m_t / |m_t|, the estimate on the unit sphere: cosine space)

    m_0 = 0, so the first observation is the estimate. The gate: the depth check (a point is linked only
    where it is the surface the pixel sees; a point has no background share of a ray) and the link
    weights w_t of :func:`link_weights`. Labels: the median of the class distributions (a convex
    combination: a distribution). State: m, S (dim each) and T per point; eps :data:`WEISZFELD_EPS`."""

    name = "median"
    weighted = True

    def __init__(self, n: int, dim: int, **kw):
        super().__init__(n, dim, **kw)
        self.m = np.zeros((self.n, self.dim), np.float32)
        self.s = np.zeros((self.n, self.dim), np.float32)
        self.t = np.zeros(self.n, np.float32)

    def add(self, idx, x, w):
        d = np.sqrt(np.einsum("ij,ij->i", x - self.m[idx], x - self.m[idx]))
        c = w / np.maximum(d, WEISZFELD_EPS)
        s = self.s[idx] + c[:, None] * x
        t = self.t[idx] + c
        self.s[idx], self.t[idx] = s, t
        m = np.divide(s, t[:, None], out=np.zeros_like(s), where=t[:, None] > 0)
        self.m[idx] = normalised(m)[0] if self.features else m

    def values(self):
        return self._out(self.m)


class TopK(Rule):
    """The Bare Necessities (Maggio et al., arXiv 2412.01539, Sec. 3: view selection instead of the average
    of an object's CLIP features across all views): a point keeps its ``k`` most confident views'
    vectors and averages them,

        f_i = (1 / |V_k(i)|) sum_(v in V_k(i)) x_(i,v),   V_k(i) = the k views of highest confidence c(x),

    c the top class's probability (labels: the pixel's distribution's maximum; features: the
    softmax over the queries' best cosines, as the best-view baseline: k = 1 is that baseline).
    State: k vectors (float16) and k scores per point; a view replaces the least confident kept one."""

    name = "topk"

    def __init__(self, n: int, dim: int, *, k: int = 3, confidence: Optional[Callable] = None, **kw):
        super().__init__(n, dim, **kw)
        self.k = int(k)
        self.confidence = confidence
        self.kept = np.zeros((self.n, self.k, self.dim), np.float16)
        self.score = np.full((self.n, self.k), -np.inf, np.float32)

    @classmethod
    def of(cls, n, *, dim, features, depth_tol, top_k: int = 3, confidence: Optional[Callable] = None, **run):
        """``k = top_k`` (``method.top_k``); a features run's ``confidence`` (labels: the vectors' maximum)."""
        return cls(n, dim, k=top_k, confidence=confidence, features=features, depth_tol=depth_tol)

    def add(self, idx, x, w):
        c = self.confidence(x) if self.confidence is not None else x.max(1)
        slot = np.argmin(self.score[idx], axis=1)
        better = c > self.score[idx, slot]
        i, j = idx[better], slot[better]
        self.score[i, j] = c[better]
        self.kept[i, j] = x[better]

    def values(self):
        out = np.zeros((self.n, self.dim), np.float32)
        for j in range(self.k):  # k slots: no (n, k, dim) float32 temporary
            out += self.kept[:, j].astype(np.float32)
        count = np.isfinite(self.score).sum(1).astype(np.float32)
        out = np.divide(out, count[:, None], out=out, where=count[:, None] > 0)
        return self._out(out)


class Vote(Rule):
    """LabelMaker (Weder et al., 3DV 2024, Sec. 3.3, the 3D lifting: every view's label of the point,
    past the depth check, votes; the majority wins): l_i = argmax_c sum_v [argmax x_(i,v) = c].
    Features: each view's label is the query label of its feature (``classify``: the run's
    :meth:`~diffuser_lab.method.space.Features.labels`), so the values are class votes
    (:attr:`classes`), not features. State: C counts per point."""

    name = "vote"
    classes = True

    def __init__(self, n: int, dim: int, *, num_classes: Optional[int] = None, classify: Optional[Callable] = None,
                 **kw):
        super().__init__(n, dim, **kw)
        self.classify = classify
        self.counts = np.zeros((self.n, int(num_classes if num_classes is not None else dim)), np.float32)

    @classmethod
    def of(cls, n, *, dim, features, depth_tol, num_classes: Optional[int] = None, classify: Optional[Callable] = None,
           **run):
        """Votes of ``num_classes`` classes; a features run's per-view labels ``classify``."""
        return cls(n, dim, num_classes=num_classes, classify=classify, features=features, depth_tol=depth_tol)

    def add(self, idx, x, w):
        if self.features:
            lab = np.asarray(self.classify(x), np.int64)
        else:
            lab = np.argmax(x, axis=1)
            lab[x.max(1) <= 0] = IGNORE
        ok = lab != IGNORE
        np.add.at(self.counts, (idx[ok], lab[ok]), 1.0)

    def values(self):
        return self.counts
