"""Point-to-point edges (paper Eqs. 3-4) and the normalised system of Eqs. 14-15.

Each point is linked to its K nearest neighbours (Euclidean, KD-tree) with weight
    w_ij = exp(-|x_i - x_j|^2 / (2 sigma_d^2) - |n_i - n_j|^2 / (2 sigma_s^2)),
sigma_d = 2 rho by default, rho = mean distance of a point to its nearest neighbour.
The graph is directed as in Eq. 3 (j in KNN(i)); rows have exactly K entries.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree


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


def knn(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """K nearest neighbours of every point, itself excluded (duplicates of it are kept).

    Returns:
        dist: (N, K) float32 distances in metres, ascending; idx: (N, K) int32.
    """
    n = points.shape[0]
    if k >= n:
        raise ValueError(f"graph.k={k} must be smaller than the number of points ({n})")
    dist, idx = cKDTree(points).query(points, k=k + 1, workers=-1)
    # Drop the point itself; with exact duplicates it need not come first, and if it is not
    # among the k+1 at all (more than k duplicates) drop the farthest instead.
    is_self = idx == np.arange(n)[:, None]
    is_self[~is_self.any(1), -1] = True
    first = is_self.cumsum(1) == 1
    keep = ~(is_self & first)
    return dist[keep].reshape(n, k).astype(np.float32), idx[keep].reshape(n, k).astype(np.int32)


def mean_spacing(dist: np.ndarray) -> float:
    """rho: mean distance to the nearest distinct neighbour (zero distances of duplicates skipped)."""
    d = dist[:, 0]
    pos = d[d > 0]
    if pos.size == 0:
        raise ValueError("all points coincide: the mean point spacing rho is 0")
    return float(pos.mean())


def normal_distance2(ni: np.ndarray, nj: np.ndarray, invariant: bool) -> np.ndarray:
    """|n_i - n_j|^2 for unit normals; ``invariant`` takes min over the sign of n_j (= 2 - 2|n_i.n_j|)."""
    dot = np.einsum("...d,...d->...", ni, nj)
    if invariant:
        dot = np.abs(dot)
    return np.maximum(2.0 - 2.0 * dot, 0.0)


def build_graph(points: np.ndarray, k: int = 24, normals: np.ndarray | None = None, *,
                sigma_s: float = 0.2, sigma_d: float | None = None, sigma_d_factor: float = 2.0,
                invariant_normals: bool = False) -> KnnGraph:
    """Eqs. 3-4 for (N, 3) world ``points``.

    Args:
        normals: (N, 3) unit normals; None drops the normal term (LDLS-like graph).
        sigma_d: distance bandwidth in metres; None = ``sigma_d_factor`` * rho.
        invariant_normals: normal difference independent of the normals' sign.
    """
    points = np.asarray(points, np.float32)
    dist, idx = knn(points, k)
    rho = mean_spacing(dist)
    sd = float(sigma_d) if sigma_d is not None else sigma_d_factor * rho
    expo = dist * dist * np.float32(-0.5 / sd**2)
    if normals is not None:
        nrm = np.asarray(normals, np.float32)
        expo -= normal_distance2(nrm[:, None, :], nrm[idx], invariant_normals) * np.float32(0.5 / sigma_s**2)
    return KnnGraph(neighbors=idx, weights=np.exp(expo).astype(np.float32), rho=rho, sigma_d=sd)
