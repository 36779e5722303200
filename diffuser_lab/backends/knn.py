"""The kNN graph's computations (paper Eqs. 3-4) behind one function per operation, on the compiled
kernels (:mod:`diffuser_lab.backends.numba`: Morton order, grid kNN, Eq. 4 weights) or their
numpy/scipy twins (Morton order of :mod:`diffuser_lab.data.geometry`, scipy's cKDTree, numpy's
exp): :func:`sorted_knn` then :func:`edge_weights`. Both paths give the same neighbour sets;
the weights agree to a float32 ulp (the compiled exp is a polynomial).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .morton import spatial_order

from . import numba as nb
from .numba import grid_knn, morton
from .numba import weights as nb_weights


@dataclass
class SortedKnn:
    """Points in Morton order and their K nearest neighbours (self excluded, ties by index).

    Attributes:
        order: (N,) int64, ``order[s]`` = caller's index of sorted point s.
        idx: (N, K) int32 neighbours of each sorted point, as sorted indices.
        d0: (N,) float64 per row the smallest positive squared distance, m^2 (inf if none).
        points, normals: what :func:`edge_weights` reads: the compiled path's (N, 4) float64 sorted
            points and normals (x, y, z, 0) (normals None without normals), or the numpy path's
            (N, 3) float32 sorted normals (points None).
        d2: numpy path: (N, K) float64 squared distances of the neighbours, m^2; else None.
    """

    order: np.ndarray
    idx: np.ndarray
    d0: np.ndarray
    points: np.ndarray | None
    normals: np.ndarray | None
    d2: np.ndarray | None


def use_compiled(backend: str) -> bool:
    """Whether ``backend`` (``auto``, ``numba`` or ``scipy``) runs the compiled kernels; ``numba``
    without them is an error."""
    if backend == "numba" and not nb.available():
        raise RuntimeError("graph backend numba: numba is not importable (it is a dependency: pip install numba) or DIFFUSER_LAB_NUMBA=0 is set")
    return backend != "scipy" and nb.available()


def compiles() -> bool:
    """Whether a graph built now would first compile the kernels (a hint for progress lines)."""
    return nb.first_compile(morton, grid_knn, nb_weights)


def kdtree_query(tree: cKDTree, queries: np.ndarray, own: np.ndarray, k: int,
                 workers: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The K nearest points of ``tree`` to each of the (M, 3) ``queries``, the query's own index
    ``own`` (M,) dropped (with exact duplicates it need not come first; if it is not among the K+1
    at all, more than K duplicates, the farthest is dropped instead).

    Returns:
        dist: (M, K) float64 distances, ascending; idx: (M, K) int64.
    """
    dist, idx = tree.query(queries, k=k + 1, workers=workers)
    is_self = idx == own[:, None]
    is_self[~is_self.any(1), -1] = True
    keep = ~(is_self & (is_self.cumsum(1) == 1))
    m = own.shape[0]
    return dist[keep].reshape(m, k), idx[keep].reshape(m, k)


def normal_distance2(ni: np.ndarray, nj: np.ndarray, invariant: bool) -> np.ndarray:
    """|n_i - n_j|^2 for unit normals; ``invariant`` takes min over the sign of n_j (= 2 - 2|n_i.n_j|)."""
    dot = np.einsum("...d,...d->...", ni, nj)
    if invariant:
        dot = np.abs(dot)
    return np.maximum(2.0 - 2.0 * dot, 0.0)


def numpy_weights(d2: np.ndarray, ni: np.ndarray | None, nj: np.ndarray | None, invariant: bool, sigma_d: float,
                  sigma_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 4 in numpy for (r, K) squared distances d2 (m^2), the rows' (r, 3) unit normals ni and
    their neighbours' (r, K, 3) nj (float32; None: no normal term): (r, K) float32 weights and
    their (r,) float64 sums."""
    expo = d2 * (-0.5 / sigma_d**2)
    if ni is not None:
        expo -= normal_distance2(ni[:, None, :].astype(np.float64), nj.astype(np.float64), invariant) * (0.5 / sigma_s**2)
    w = np.exp(expo).astype(np.float32)
    return w, w.sum(1, dtype=np.float64)


def kdtree_knn(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Every point's K nearest among the (N, 3) ``points`` by scipy's cKDTree (:func:`kdtree_query`,
    all threads): dist (N, K) float64, ascending, and idx (N, K) int64."""
    return kdtree_query(cKDTree(points), points, np.arange(points.shape[0]), k, workers=-1)


def _kdtree_rows(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every point's K nearest by a KD-tree: idx (N, K) int32, d2 (N, K) float64 and d0 (N,)."""
    dist, idx = kdtree_knn(points, k)
    d2 = np.square(dist)
    return idx.astype(np.int32), d2, np.where(d2 > 0, d2, np.inf).min(1)


def sorted_knn(points: np.ndarray, normals: np.ndarray | None, k: int, backend: str = "auto") -> SortedKnn:
    """Morton order of the (N, 3) float32 ``points`` (C-contiguous) and every point's K nearest
    neighbours (Eq. 3), on the compiled grid kNN (:func:`use_compiled`; a KD-tree where the cloud
    is too sparse for a dense grid) or scipy's cKDTree.

    Args:
        normals: (N, 3) unit normals or None; k < N.
    """
    if use_compiled(backend):
        # P4/N4: sorted points and normals as float64 rows of 4 (what the weights read)
        order, P4, N4, res = grid_knn.sorted_knn(points, normals, k)
        if res is not None:
            idx, d0 = res
        else:  # too sparse for a dense grid
            idx, _, d0 = _kdtree_rows(P4[:, :3], k)
        return SortedKnn(order=order, idx=idx, d0=d0, points=P4, normals=N4, d2=None)
    order = spatial_order(points)
    nrm = None if normals is None else np.asarray(normals, np.float32)[order]
    idx, d2, d0 = _kdtree_rows(points[order], k)
    return SortedKnn(order=order, idx=idx, d0=d0, points=None, normals=nrm, d2=d2)


def edge_weights(nbrs: SortedKnn, invariant: bool, sigma_d: float, sigma_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 4 weights (N, K) float32 of :func:`sorted_knn`'s rows and their sums (N,) float64.

    Args:
        invariant: the normal term independent of the normals' sign; sigma_d: metres; sigma_s.
    """
    if nbrs.points is not None:
        return nb_weights.edge_weights(nbrs.points, nbrs.idx, nbrs.normals, invariant, sigma_d, sigma_s)
    nrm = nbrs.normals
    return numpy_weights(nbrs.d2, nrm, None if nrm is None else nrm[nbrs.idx], invariant, sigma_d, sigma_s)
