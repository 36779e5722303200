"""What the records keep of a features run's (M, D) per-point features: not the features (at
D = 512 that is 2 KB a point in float32 per recorded iteration) but two views of them that stay
under a few bytes a point.

- **PCA to RGB**: a 3-component PCA of the features, fitted once per run (:func:`fit_view`: on
  the unit rows of the evidence's feature sums, i.e. the normalised average features of the seen
  points, a seeded subsample of at most :data:`PCA_ROWS` rows), with the colour scaling (each
  component's 1st to 99th percentile on those rows -> 0 to 255) fixed for the whole run; every
  recorded iteration is then projected with it (:func:`project`) to (M, 3) uint8 RGB, rows
  without a feature grey (:data:`GREY`).
- **A query's similarity**: the cosine of each point's feature to one query
  (``record.query``, default the run's first), in 255 steps over the range its seen rows span at
  the fit (1st to 99th percentile), as (M,) uint8; :data:`NO_FEATURE` where a row is zero.

Both are computed on the run's side from the features (one (M, D) x (D, 4) product and the
rows' norms: no (M, D) copy), so only (M, 4) bytes per recorded iteration travel to the recorders.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from diffuser_lab import seeding

PCA_ROWS = 20_000
"""The PCA is fitted on at most this many seen rows (a seeded subsample)."""
PCA_SEED = 0
GREY = 128
"""The RGB of a point without a feature (unseen, not reached yet)."""
NO_FEATURE = 255
"""The similarity byte of a point without a feature; 0..254 are the cosines."""
SIM_STEPS = 254


@dataclass(frozen=True)
class FeatureView:
    """The fitted projection of one run (fixed for the whole run).

    Attributes:
        basis: (3, D) float32 the principal axes (unit rows; sign: largest component positive).
        mean: (D,) float32 the mean of the fitted unit rows.
        lo, hi: (3,) float32 each component's value that maps to 0 and to 255.
        query: the query whose similarity is recorded; embedding: its (D,) float32 unit embedding.
        sim_lo, sim_hi: the cosines that map to 0 and to :data:`SIM_STEPS`.
        n_fit: rows the PCA was fitted on.
    """

    basis: np.ndarray
    mean: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    query: str
    embedding: np.ndarray
    sim_lo: float
    sim_hi: float
    n_fit: int = 0

    @property
    def dim(self) -> int:
        return int(self.basis.shape[1])


def pick_query(names: Sequence[str], query: Optional[str]) -> int:
    """The index of ``query`` in ``names`` (None: the first); ValueError naming the queries if absent."""
    names = list(names)
    if query is None:
        return 0
    if query not in names:
        shown = ", ".join(names[:12]) + (", ..." if len(names) > 12 else "")
        raise ValueError(f"record.query={query!r}: no such query in this run; its queries: {shown}")
    return names.index(query)


def fit_view(mass: np.ndarray, names: Sequence[str], embeddings: np.ndarray, query: Optional[str] = None,
             *, max_rows: int = PCA_ROWS, seed: int = PCA_SEED) -> FeatureView:
    """Fit the run's projection on the evidence's (M, D) feature sums ``mass`` (their nonzero rows,
    normalised) and pick the query (see the module doc)."""
    qi = pick_query(names, query)
    mass = np.asarray(mass)
    norms = np.sqrt(np.einsum("ij,ij->i", mass, mass, dtype=np.float64))
    rows = np.flatnonzero(norms > 0)
    if len(rows) > max_rows:
        rows = np.sort(seeding.rng(seed, "records.feature_pca").choice(rows, max_rows, replace=False))
    D = mass.shape[1]
    emb = np.ascontiguousarray(embeddings[qi], np.float32)
    emb = emb / max(float(np.linalg.norm(emb)), 1e-30)
    if len(rows) < 2:  # nothing seen: an arbitrary basis, grey everywhere anyway
        basis = np.eye(3, D, dtype=np.float32)
        return FeatureView(basis, np.zeros(D, np.float32), np.zeros(3, np.float32), np.ones(3, np.float32),
                           str(names[qi]), emb, -1.0, 1.0, len(rows))
    X = mass[rows].astype(np.float64) / norms[rows, None]
    mean = X.mean(0)
    X -= mean
    w, v = np.linalg.eigh(X.T @ X)
    basis = v[:, np.argsort(-w, kind="stable")[:3]].T  # (3, D); stable: the same order at ties on any CPU
    flip = np.sign(basis[np.arange(3), np.argmax(np.abs(basis), axis=1)])
    basis *= flip[:, None]
    P = X @ basis.T
    lo, hi = np.percentile(P, 1, axis=0), np.percentile(P, 99, axis=0)
    hi = np.where(hi > lo, hi, lo + 1e-6)
    cos = (X + mean) @ emb.astype(np.float64)
    s_lo, s_hi = float(np.percentile(cos, 1)), float(np.percentile(cos, 99))
    if not s_hi > s_lo:
        s_lo, s_hi = -1.0, 1.0
    return FeatureView(basis.astype(np.float32), mean.astype(np.float32), lo.astype(np.float32),
                       hi.astype(np.float32), str(names[qi]), emb, s_lo, s_hi, len(rows))


def project(view: FeatureView, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, D) features (any scale: sums or unit rows) -> (M, 3) uint8 RGB and (M,) uint8 query
    similarity (see the module doc)."""
    F = np.asarray(F)
    A = np.concatenate([view.basis, view.embedding[None, :]]).T  # (D, 4)
    P = F @ A.astype(F.dtype, copy=False)  # (M, 4)
    norm = np.sqrt(np.einsum("ij,ij->i", F, F, dtype=np.float32))
    has = norm > 0
    P = P.astype(np.float32, copy=False)
    np.divide(P, norm[:, None], out=P, where=has[:, None])
    rgb = P[:, :3] - (view.mean @ view.basis.T)
    rgb = (rgb - view.lo) * (255.0 / (view.hi - view.lo))
    rgb = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
    rgb[~has] = GREY
    sim = (P[:, 3] - view.sim_lo) * (SIM_STEPS / (view.sim_hi - view.sim_lo))
    sim = np.clip(np.rint(sim), 0, SIM_STEPS).astype(np.uint8)
    sim[~has] = NO_FEATURE
    return rgb, sim


def lifted(view: FeatureView, basis: Optional[np.ndarray]) -> FeatureView:
    """A view fitted on coordinates in a reduced basis ((D, k) orthonormal columns; features runs with
    ``predictions.basis=auto``) as the same projection of R^D (what run.mcap keeps: 3 x D); ``view``
    itself when ``basis`` is None."""
    if basis is None:
        return view
    B = np.asarray(basis, np.float32)
    return dataclasses.replace(view, basis=np.ascontiguousarray(view.basis @ B.T), mean=view.mean @ B.T,
                               embedding=np.ascontiguousarray(view.embedding @ B.T))


def feature_view_of(msg) -> FeatureView:
    """The :class:`FeatureView` of run.mcap's ``diffuser_lab.FeatureView`` message."""
    def f32(b: bytes) -> np.ndarray:
        return np.frombuffer(b, "<f4").astype(np.float32)

    return FeatureView(f32(msg.basis).reshape(3, -1), f32(msg.mean), f32(msg.lo), f32(msg.hi), msg.query,
                       f32(msg.embedding), float(msg.sim_lo), float(msg.sim_hi), int(msg.n_fit))


def similarity_values(view: FeatureView, sim: np.ndarray) -> np.ndarray:
    """The (M,) uint8 similarity bytes back to cosines (float32; NaN where no feature)."""
    sim = np.asarray(sim)
    out = view.sim_lo + sim.astype(np.float32) * np.float32((view.sim_hi - view.sim_lo) / SIM_STEPS)
    out[sim == NO_FEATURE] = np.nan
    return out.astype(np.float32)


__all__ = ["FeatureView", "feature_view_of", "fit_view", "lifted", "project", "pick_query", "similarity_values", "PCA_ROWS", "GREY",
           "NO_FEATURE", "SIM_STEPS"]
