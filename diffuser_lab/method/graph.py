"""Point-to-point edges (paper Eqs. 3-4) and the normalised system of Eqs. 14-15.

Each point is linked to its K nearest neighbours (Euclidean, KD-tree) with weight
    w_ij = exp(-|x_i - x_j|^2 / (2 sigma_d^2) - |n_i - n_j|^2 / (2 sigma_s^2)),
sigma_d = 2 rho by default, rho = mean distance of a point to its nearest neighbour.
The graph is directed as in Eq. 3 (j in KNN(i)); rows have exactly K entries.

Speed: :func:`build_graph` sorts the points along a Morton (Z-order) curve first and works in
that order throughout (kNN, weights, and later the normalised system and the diffusion), so that
a point's neighbours are near it in memory. With numba (the ``fast`` extra) the Morton order, an
exact kNN on a uniform grid (cells about the K-th neighbour distance, processed cell by cell) and
the weights are compiled, else scipy's cKDTree is queried in that order (both in
:mod:`diffuser_lab.backends.knn`). The graph it returns exposes ``neighbors``/``weights`` in the
caller's point order (built on first access); results never depend on the input order except
through exact distance ties.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from diffuser_lab import progress
from diffuser_lab.backends import knn as knn_backend
from diffuser_lab.backends.knn import normal_distance2
from diffuser_lab.config import GraphConfig, NormalSign
from diffuser_lab.data.geometry import estimate_normals

__all__ = ["KnnGraph", "SortedKnnGraph", "build_graph", "graph_stage", "knn", "make_graph", "mean_spacing", "nearest_distinct",
           "normal_distance2"]


@dataclass
class KnnGraph:
    """K-nearest-neighbour graph with fixed row length.

    Attributes:
        neighbors: (N, K) int32 indices of each point's neighbours (self excluded).
        weights: (N, K) float32 edge weights w_ij of Eq. 4.
        rho: mean nearest-neighbour distance of the cloud, metres.
        sigma_d: distance bandwidth used, metres.
    """

    neighbors: np.ndarray
    weights: np.ndarray
    rho: float
    sigma_d: float

    @property
    def n(self) -> int:
        return int(self.neighbors.shape[0])

    def matrix(self, row_scale: np.ndarray | None = None) -> sp.csr_matrix:
        """(N, N) CSR adjacency G^{X->X}; rows multiplied by ``row_scale`` (N,) if given."""
        n, k = self.neighbors.shape
        data = self.weights if row_scale is None else self.weights * row_scale[:, None].astype(np.float32)
        indptr = np.arange(0, n * k + 1, k, dtype=np.int64)
        # copies: the matrix may be edited in place (eliminate_zeros) and must not alias the graph
        return sp.csr_matrix((data.ravel().copy(), self.neighbors.ravel().copy(), indptr), shape=(n, n))


class SortedKnnGraph(KnnGraph):
    """A :class:`KnnGraph` kept in Morton order internally (see module doc).

    Attributes:
        order: (N,) int64, ``order[s]`` = caller's index of sorted point s.
        sorted_neighbors: (N, K) int32 neighbours of sorted point s, as sorted indices.
        sorted_weights: (N, K) float32 their weights; sorted_row_sums: (N,) float64 row sums.
    ``neighbors``/``weights`` (caller's order) are computed on first access and cached.
    """

    def __init__(self, order: np.ndarray, sorted_neighbors: np.ndarray, sorted_weights: np.ndarray,
                 sorted_row_sums: np.ndarray, rho: float, sigma_d: float):
        self.order = order
        self.sorted_neighbors = sorted_neighbors
        self.sorted_weights = sorted_weights
        self.sorted_row_sums = sorted_row_sums
        self.rho = rho
        self.sigma_d = sigma_d
        self._public: tuple[np.ndarray, np.ndarray] | None = None

    def _caller_order(self) -> tuple[np.ndarray, np.ndarray]:
        if self._public is None:
            nb = np.empty_like(self.sorted_neighbors)
            w = np.empty_like(self.sorted_weights)
            nb[self.order] = self.order[self.sorted_neighbors]
            w[self.order] = self.sorted_weights
            self._public = (nb, w)
        return self._public

    @property
    def neighbors(self) -> np.ndarray:  # type: ignore[override]
        return self._caller_order()[0]

    @property
    def weights(self) -> np.ndarray:  # type: ignore[override]
        return self._caller_order()[1]

    @property
    def n(self) -> int:
        return int(self.order.shape[0])

    @property
    def k(self) -> int:
        return int(self.sorted_neighbors.shape[1])

    def __repr__(self) -> str:
        return f"SortedKnnGraph(n={self.n}, k={self.k}, rho={self.rho:.4g}, sigma_d={self.sigma_d:.4g})"


def knn(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """K nearest neighbours of every point, itself excluded (duplicates of it are kept).

    Returns:
        dist: (N, K) float32 distances in metres, ascending; idx: (N, K) int32.
    """
    n = points.shape[0]
    if k >= n:
        raise ValueError(f"graph.k={k} must be smaller than the number of points ({n})")
    dist, idx = knn_backend.kdtree_knn(points, k)
    return dist.astype(np.float32), idx.astype(np.int32)


def mean_spacing(dist: np.ndarray) -> float:
    """rho: mean distance to the nearest distinct neighbour (zero distances of duplicates skipped)."""
    d = dist[:, 0]
    pos = d[d > 0]
    if pos.size == 0:
        raise ValueError("all points coincide: the mean point spacing rho is 0")
    return float(pos.mean())


def _rho(d0: np.ndarray) -> float:
    """rho from :func:`~diffuser_lab.backends.knn.sorted_knn`'s d0: per point the squared distance to
    its nearest *distinct* neighbour among its K (duplicates at distance 0 skipped; inf: none)."""
    d = np.sqrt(d0)
    pos = d[np.isfinite(d)]
    if pos.size == 0:
        raise ValueError("all points coincide: the mean point spacing rho is 0")
    return float(pos.mean())


def nearest_distinct(points: np.ndarray, k: int = 24, backend: str = "auto") -> np.ndarray:
    """Per point of the (N, 3) ``points`` the distance to its nearest distinct neighbour among its ``k``
    nearest (metres, float64; inf: none, duplicates at distance 0 skipped): the terms of
    :func:`build_graph`'s rho, for a cloud taken part by part (a tiled run's survey)."""
    points = np.ascontiguousarray(points, np.float32)
    d = np.full(points.shape[0], np.inf)
    if points.shape[0] < 2:
        return d
    nb = knn_backend.sorted_knn(points, None, min(k, points.shape[0] - 1), backend)
    d[nb.order] = np.sqrt(nb.d0)
    return d


def build_graph(points: np.ndarray, k: int = 24, normals: np.ndarray | None = None, *,
                sigma_s: float = 0.2, sigma_d: float | None = None, sigma_d_factor: float = 2.0,
                invariant_normals: bool = False, backend: str = "auto") -> KnnGraph:
    """Eqs. 3-4 for (N, 3) world ``points``.

    Args:
        normals: (N, 3) unit normals; None drops the normal term (LDLS-like graph).
        sigma_d: distance bandwidth in metres; None = ``sigma_d_factor`` * rho.
        invariant_normals: normal difference independent of the normals' sign.
        backend: ``auto`` (compiled grid kNN when numba is available), ``numba``, or
            ``scipy`` (cKDTree + numpy).
    Returns:
        a :class:`SortedKnnGraph` (see module doc).
    """
    points = np.ascontiguousarray(points, np.float32)
    n = points.shape[0]
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {points.shape}")
    if normals is not None and np.shape(normals) != (n, 3):
        raise ValueError(f"normals must be (N, 3) like the points, got {np.shape(normals)}")
    if k >= n:
        raise ValueError(f"graph.k={k} must be smaller than the number of points ({n})")
    nbrs = knn_backend.sorted_knn(points, normals, k, backend)
    rho = _rho(nbrs.d0)
    sd = float(sigma_d) if sigma_d is not None else sigma_d_factor * rho
    w, wsum = knn_backend.edge_weights(nbrs, invariant_normals, sd, sigma_s)
    return SortedKnnGraph(order=nbrs.order, sorted_neighbors=nbrs.idx, sorted_weights=w, sorted_row_sums=wsum,
                          rho=rho, sigma_d=sd)


def graph_stage(n_points: int, g: GraphConfig, estimating_normals: bool):
    """The progress stage of :func:`make_graph` (+ :func:`~diffuser_lab.method.diffusion.normalise`) on
    ``n_points`` points, noting a first run's kernel compilation."""
    name = f"kNN graph (k={g.k}, {n_points:,} points{', estimating normals' if estimating_normals else ''})"
    if progress.enabled() and knn_backend.compiles():
        name += progress.COMPILING
    return progress.stage(name)


def make_graph(points: np.ndarray, normals: np.ndarray | None, g: GraphConfig) -> tuple[np.ndarray | None, KnnGraph]:
    """Eqs. 3-4 as configured. Normals: the given ones (sign trusted unless
    ``normal_sign=invariant``), else estimated by open3d (sign arbitrary, so compared
    sign-invariantly unless ``normal_sign=signed``). Returns (normals used or None, graph)."""
    invariant = g.normal_sign == NormalSign.invariant
    if g.use_normals and normals is None:
        normals = estimate_normals(points, g.normal_knn)
        invariant = g.normal_sign != NormalSign.signed
    graph = build_graph(points, g.k, normals if g.use_normals else None, sigma_s=g.sigma_s, sigma_d=g.sigma_d,
                        sigma_d_factor=g.sigma_d_factor, invariant_normals=invariant)
    return normals, graph
