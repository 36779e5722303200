"""A reduced basis for features runs: the labels exact in a handful of columns, the rest in a basis.

The diffusion is linear in its evidence: diffusing ``F P`` gives (the diffusion of ``F``) ``P`` for any
fixed (D, k) matrix ``P``. A features run (:mod:`diffuser_lab.method.features`) therefore need not
diffuse all D columns of its feature sums:

- the query labels, argmax over q of f.q / |q|, need only the projections of ``f`` on the queries:
  with the queries' span in the basis they are exact (up to float rounding);
- what needs more, the threshold test (|f|), the saved features and queries asked later (``f``
  itself), lives in the basis: the queries' span plus the leading principal directions of the
  pixels' features outside it, with its error measured.

:class:`FeatureBasis` is that basis, ``vectors`` (D, k) orthonormal columns (the first ``n_query``
span the queries), fitted once per run on a sample of the frames' feature cells
(:func:`fit_basis`: the queries' span by QR, then Halko's randomized range finder on the cells'
residual). ``probes`` (D, s) are ``s`` more orthonormal columns, random in the residual space (the
orthogonal complement of ``vectors``, of dimension r = D - k): their coordinates estimate the
residual's energy, ``|R f|^2 ~ (r / s) |U^T f|^2`` (unbiased for any ``f`` when ``U`` is a
uniformly random s-frame of that space), so a feature's norm is estimated, not just bounded
below by its projection's. The frames' features are projected on ``[vectors, probes]`` before
their evidence is added (:mod:`diffuser_lab.method.evidence`: each sampled pixel normalised by its
exact norm in R^D), so the evidence sums, their diffusion and the baselines all live in k + s
columns.

:class:`BasisFeatures` holds per-point features in the basis: (M, k) coordinates and (M,) the
estimated residual energy; its norm, its cosines with the queries and its reconstruction in R^D
(unit rows, float16: what ``features.npy`` holds) are methods.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from diffuser_lab import seeding
from diffuser_lab.backends.records import to_float16
from diffuser_lab.backends.threads import blas_one_thread

__all__ = ["FeatureBasis", "BasisFeatures", "fit_basis", "query_span", "range_finder", "unit_rows_float16", "SAMPLE_ROWS"]

SAMPLE_ROWS = 20_000
"""Feature cells the principal directions are fitted on at most (a seeded subsample)."""
POWER_ITERATIONS = 2
OVERSAMPLE = 10


def query_span(embeddings: np.ndarray, rtol: float = 1e-5) -> np.ndarray:
    """(Q, D) query embeddings -> (D, q) float64 orthonormal columns spanning them (q <= Q: the
    numerical rank, singular values under ``rtol`` of the largest dropped: repeated queries)."""
    E = np.asarray(embeddings, np.float64)
    U, s, _ = np.linalg.svd(E.T, full_matrices=False)
    keep = s > rtol * max(float(s[0]) if s.size else 0.0, 1e-300)
    return U[:, keep]


def range_finder(A: np.ndarray, p: int, seed: int, *, oversample: int = OVERSAMPLE,
                 power: int = POWER_ITERATIONS) -> tuple[np.ndarray, np.ndarray]:
    """The ``p`` leading right singular vectors of ``A`` (S, D) by Halko, Martinsson & Tropp's
    randomized range finder (Alg. 4.4: ``power`` subspace iterations, ``oversample`` extra columns)
    and the SVD of the small projected matrix.

    Returns (D, p') float64 orthonormal columns (p' = min(p, S, D)) and their (p',) squared singular
    values (the energy of ``A`` along each). The Gaussian test matrix is a keyed draw
    (:func:`diffuser_lab.seeding.normal`): the same on every CPU."""
    S, D = A.shape
    p = int(min(p, S, D))
    if p <= 0:
        return np.zeros((D, 0)), np.zeros(0)
    ell = min(p + oversample, S, D)
    omega = seeding.normal(seed, "features.basis.range_finder", np.arange(D)[:, None], np.arange(ell)[None, :])
    Y = np.linalg.qr(A @ omega)[0]  # (S, ell)
    for _ in range(power):  # loop over power iterations (2): sharpens a slowly decaying spectrum
        Z = np.linalg.qr(A.T @ Y)[0]  # (D, ell)
        Y = np.linalg.qr(A @ Z)[0]
    _, s, Vt = np.linalg.svd(Y.T @ A, full_matrices=False)  # (ell, D)
    return Vt[:p].T, s[:p] ** 2


@dataclass(frozen=True, eq=False)
class FeatureBasis:
    """A run's reduced feature basis (module docstring).

    Attributes:
        vectors: (D, k) float32 orthonormal columns; the first ``n_query`` span the queries.
        probes: (D, s) float32 orthonormal, orthogonal to ``vectors``: the residual's probes.
        n_query: the queries' span's dimension (their numerical rank).
        queries: (Q, k) float32 the queries' unit embeddings in coordinates (exact: they lie in the span).
        sample_energy: share of the fitting sample's energy (sum of squared unit rows) the vectors keep.
        sample_rows: cells the principal directions were fitted on.
    """

    vectors: np.ndarray
    probes: np.ndarray
    n_query: int
    queries: np.ndarray
    sample_energy: float = float("nan")
    sample_rows: int = 0
    columns: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        cols = np.ascontiguousarray(np.concatenate([self.vectors, self.probes], axis=1), np.float32)
        cols.flags.writeable = False
        object.__setattr__(self, "columns", cols)

    @property
    def dim(self) -> int:
        """D, the features' dimension."""
        return int(self.vectors.shape[0])

    @property
    def k(self) -> int:
        """The basis' dimension (queries' span + principal directions)."""
        return int(self.vectors.shape[1])

    @property
    def s(self) -> int:
        """Probe columns."""
        return int(self.probes.shape[1])

    @property
    def width(self) -> int:
        """k + s: the columns a run accumulates and diffuses."""
        return self.k + self.s

    @property
    def residual_dim(self) -> int:
        """r = D - k, the dimension of the space the probes sample."""
        return self.dim - self.k

    def split(self, X: np.ndarray) -> "BasisFeatures":
        """(M, k + s) coordinates on :attr:`columns` (sums of unit features, diffused or not) ->
        :class:`BasisFeatures` (the k coordinates, the residual energy estimated from the probes)."""
        X = np.asarray(X)
        c = X[:, : self.k]
        if self.s:
            p = X[:, self.k:].astype(np.float32, copy=False)
            res = np.einsum("ij,ij->i", p, p) * np.float32(self.residual_dim / self.s)
        else:
            res = np.zeros(X.shape[0], np.float32)
        return BasisFeatures(c, res.astype(np.float32, copy=False))

    def record(self) -> dict:
        """summary.json's ``features.basis`` fields that describe the basis itself."""
        return {"kind": "auto", "dim": self.k, "of": self.dim, "queries_span": self.n_query,
                "principal": self.k - self.n_query, "probes": self.s, "sample_rows": int(self.sample_rows),
                "sample_energy": round(float(self.sample_energy), 6)}


@dataclass
class BasisFeatures:
    """Per-point features in a :class:`FeatureBasis`: ``coords`` (M, k) float32/float16 and
    ``residual`` (M,) float32 the energy outside the basis, |f|^2 - |coords|^2 (estimated by the
    probes, or exact: a unit feature's 1 - |coords|^2). A zero row with zero residual: no feature."""

    coords: np.ndarray
    residual: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.coords.shape

    def __len__(self) -> int:
        return int(self.coords.shape[0])

    def take(self, rows: np.ndarray) -> "BasisFeatures":
        """The features of ``rows`` (M',) int."""
        return BasisFeatures(self.coords[rows], self.residual[rows])

    def kept2(self) -> np.ndarray:
        """(M,) float32 |coords|^2, the projection's energy."""
        c = self.coords.astype(np.float32, copy=False)
        return np.einsum("ij,ij->i", c, c)

    def norms(self) -> np.ndarray:
        """(M,) float32 the estimated |f| (sqrt of |coords|^2 + residual, the residual clipped at 0)."""
        return np.sqrt(self.kept2() + np.maximum(self.residual, 0))

    def cosines(self, queries: np.ndarray) -> np.ndarray:
        """(M, Q) float32 cosines with the queries' (Q, k) coordinates (:attr:`FeatureBasis.queries`):
        f.q exact, divided by the estimated |f|; NaN rows where the norm is 0 or not finite."""
        c = self.coords.astype(np.float32, copy=False)
        norm = self.norms()
        ok = np.isfinite(norm) & (norm > 0)
        sim = c @ np.ascontiguousarray(queries.T, np.float32)
        sim *= np.divide(1.0, norm, out=np.zeros_like(norm), where=ok)[:, None]
        sim[~ok] = np.nan
        return sim

    def energy_kept(self) -> np.ndarray:
        """(M,) float32 |coords|^2 / |f|^2 (estimated) of the rows with a feature (NaN elsewhere)."""
        k2 = self.kept2()
        tot = k2 + np.maximum(self.residual, 0)
        return np.divide(k2, tot, out=np.full_like(k2, np.nan), where=tot > 0)

    def unit_float16(self, basis: FeatureBasis, rows: Optional[np.ndarray] = None, out: Optional[np.ndarray] = None,
                     chunk: int = 32768) -> np.ndarray:
        """(M', D) float16 unit rows in R^D of the projections, of ``rows`` (default all):
        :func:`unit_rows_float16` of the coordinates on ``basis.vectors``."""
        return unit_rows_float16(self.coords, basis.vectors, rows, out, chunk)


def unit_rows_float16(coords: np.ndarray, vectors: np.ndarray, rows: Optional[np.ndarray] = None,
                      out: Optional[np.ndarray] = None, chunk: int = 32768) -> np.ndarray:
    """(M, k) coordinates on (D, k) orthonormal ``vectors`` -> (M', D) float16 unit rows in R^D
    (coords @ vectors.T, normalised; 0 rows where the coordinates are 0) of ``rows`` (default all), a
    chunk of rows at a time (no (M, D) float32 temporary); into ``out`` (e.g. a memory map's rows)
    when given. Many calls of a few thousand rows (a file written in chunks) run faster inside one
    ``blas_one_thread()``."""
    n = len(coords) if rows is None else len(rows)
    out = np.empty((n, vectors.shape[0]), np.float16) if out is None else out
    V = np.ascontiguousarray(np.asarray(vectors, np.float32).T)  # (k, D)
    for lo in range(0, n, chunk):  # chunks of rows: bounded float32 temporaries
        sel = slice(lo, min(lo + chunk, n)) if rows is None else rows[lo:lo + chunk]
        c = np.asarray(coords[sel], np.float32).copy()
        norm = np.sqrt(np.einsum("ij,ij->i", c, c))
        c *= np.divide(1.0, norm, out=np.zeros_like(norm), where=norm > 0)[:, None]
        to_float16(c @ V, out[lo:lo + len(c)])
    return out


def fit_basis(sample: np.ndarray, embeddings: np.ndarray, principal: int, probes: int, seed: int) -> FeatureBasis:
    """The run's basis from a sample of its feature cells.

    Args:
        sample: (S, D) float32 unit feature rows (e.g. the valid cells of a few frames' maps).
        embeddings: (Q, D) the queries' unit embeddings.
        principal: principal directions of the sample's residual (after the queries' span) to add.
        probes: random orthonormal probe columns of the remaining residual space.
        seed: keys the subsample, the range finder's test matrix and the probes (keyed draws).
    Returns:
        the :class:`FeatureBasis` (k = the queries' rank + min(principal, ...), at most D - probes).
    """
    with blas_one_thread():  # small products: OpenBLAS's spinning workers cost more than they give
        return _fit_basis(sample, embeddings, principal, probes, seed)


def _fit_basis(sample: np.ndarray, embeddings: np.ndarray, principal: int, probes: int, seed: int) -> FeatureBasis:
    E = np.asarray(embeddings, np.float64)
    D = E.shape[1]
    S = query_span(E)  # (D, q)
    X = np.asarray(sample, np.float32)
    if X.shape[0] > SAMPLE_ROWS:
        keep = np.sort(seeding.rng(seed, "features.basis.sample").choice(X.shape[0], SAMPLE_ROWS, replace=False))
        X = X[keep]
    X = X.astype(np.float64)
    total = float(np.einsum("ij,ij->", X, X))
    R = X - (X @ S) @ S.T  # the sample outside the queries' span
    p = int(max(0, min(principal, D - S.shape[1] - probes)))
    V, _ = range_finder(R, p, seed) if p and R.shape[0] else (np.zeros((D, 0)), None)
    B = np.linalg.qr(np.concatenate([S, V - S @ (S.T @ V)], axis=1))[0]  # re-orthonormalised together
    B[:, : S.shape[1]] = S  # the queries' span first, as fitted
    kept = float(np.einsum("ij,ij->", X @ B, X @ B))
    s = int(max(0, min(probes, D - B.shape[1])))
    G = seeding.normal(seed, "features.basis.probes", np.arange(D)[:, None], np.arange(s)[None, :])
    G -= B @ (B.T @ G)
    G -= B @ (B.T @ G)  # twice: orthogonal to the basis to rounding
    U = np.linalg.qr(G)[0] if s else np.zeros((D, 0))
    vectors = B.astype(np.float32)
    q = (np.asarray(embeddings, np.float64) / np.linalg.norm(E, axis=1, keepdims=True)) @ B
    return FeatureBasis(vectors, U.astype(np.float32), int(S.shape[1]), q.astype(np.float32),
                        kept / total if total > 0 else float("nan"), int(X.shape[0]))
