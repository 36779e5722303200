"""The growing map's graph computations (:class:`~diffuser_lab.method.growing.IncrementalKnnGraph`):
its kNN rows and their Eq. 4 weights, on the compiled hash grid
(:class:`diffuser_lab.backends.numba.growing.GridRows`) or the scipy twin :class:`TreeRows`
(KD-trees rebuilt per add; slower, same rows). :func:`rows_backend` picks one when a graph is made.

A rows backend has ``build(arrays, n)`` (every row of the first n > K points), ``extend(arrays,
n_old, n)`` (the rows of points n_old..n-1; returns the old rows a new point is closer to than
their K-th neighbour), ``update(arrays, rows)`` (recomputes those) and ``weights(...)``
(Eq. 4 for given rows). ``arrays`` is the graph's (points, nbr, d2, d0, kth) over its capacity:
(cap, 3) float32 points; (cap, K) int32 neighbours and float64 squared distances, each row
ascending by (d2, index); (cap,) float64 the smallest positive d2 (inf if none) and the K-th d2.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from . import numba as nb
from .knn import kdtree_query, numpy_weights
from .numba.growing import GridRows


class TreeRows:
    """The rows from scipy's cKDTree over all points (rebuilt per add), as
    :func:`~diffuser_lab.method.graph.build_graph`'s scipy path; squared distances recomputed in
    float64 from the float32 coordinates and exact ties ordered by index, as the compiled path."""

    compiled = False

    def __init__(self, k: int):
        self.k = k
        self._tree: cKDTree | None = None

    def build(self, arrays: tuple, n: int) -> None:
        self._rows(arrays, np.arange(n, dtype=np.int64), cKDTree(arrays[0][:n]))

    def extend(self, arrays: tuple, n_old: int, n: int) -> np.ndarray:
        P, _, _, _, kth = arrays
        self._tree = cKDTree(P[:n])
        # old rows a new point is strictly closer to than their K-th neighbour
        dn, _ = cKDTree(P[n_old:n]).query(P[:n_old], k=1)
        aff = np.flatnonzero(dn.astype(np.float64) ** 2 < kth[:n_old] * (1 + 1e-12) + 1e-300).astype(np.int64)
        aff = aff[self._closer(P, kth, aff, n_old, n)]
        self._rows(arrays, np.arange(n_old, n, dtype=np.int64), self._tree)
        return aff

    def update(self, arrays: tuple, rows: np.ndarray) -> None:
        self._rows(arrays, rows, self._tree)

    def weights(self, rows: np.ndarray, nbr: np.ndarray, d2: np.ndarray, normals: np.ndarray | None, invariant: bool,
                sigma_d: float, sigma_s: float, w: np.ndarray, wsum: np.ndarray) -> None:
        """Eq. 4 for ``rows``, in place (:func:`~diffuser_lab.backends.knn.numpy_weights`)."""
        ni = None if normals is None else normals[rows]
        nj = None if normals is None else normals[nbr[rows]]
        w[rows], wsum[rows] = numpy_weights(d2[rows], ni, nj, invariant, sigma_d, sigma_s)

    def _rows(self, arrays: tuple, rows: np.ndarray, tree: cKDTree) -> None:
        """``rows`` recomputed from a KD-tree of all points, sorted by (d2, index)."""
        if rows.size == 0:
            return
        P, nbr, d2_out, d0, kth = arrays
        _, idx = kdtree_query(tree, P[rows], rows, self.k)
        d2 = ((P[idx].astype(np.float64) - P[rows][:, None, :].astype(np.float64)) ** 2).sum(-1)
        o = np.lexsort((idx, d2), axis=-1)
        idx, d2 = np.take_along_axis(idx, o, 1), np.take_along_axis(d2, o, 1)
        nbr[rows] = idx
        d2_out[rows] = d2
        d0[rows] = np.where(d2 > 0, d2, np.inf).min(1)
        kth[rows] = d2[:, -1]

    @staticmethod
    def _closer(P: np.ndarray, kth: np.ndarray, rows: np.ndarray, n_old: int, n: int) -> np.ndarray:
        """Mask of ``rows`` (old rows near a new point by the KD-tree's float distance) whose exact
        float64 squared distance to some new point is below their K-th (decides ties as the compiled path)."""
        if rows.size == 0:
            return np.zeros(0, bool)
        kth2 = kth[rows]
        lists = cKDTree(P[n_old:n]).query_ball_point(P[rows], np.sqrt(kth2) * (1 + 1e-9))
        lens = np.fromiter((len(x) for x in lists), np.int64, rows.size)
        cand = np.concatenate([np.asarray(x, np.int64) for x in lists]) + n_old if lens.sum() else np.zeros(0, np.int64)
        owner = np.repeat(np.arange(rows.size), lens)
        d2 = ((P[cand].astype(np.float64) - P[rows[owner]].astype(np.float64)) ** 2).sum(-1)
        ok = np.zeros(rows.size, bool)
        ok[owner[d2 < kth2[owner]]] = True
        return ok


def rows_backend(k: int) -> GridRows | TreeRows:
    """The rows backend of a new graph with K = ``k``: compiled when the kernels are used
    (:func:`diffuser_lab.backends.numba.available`), else scipy."""
    return GridRows(k) if nb.available() else TreeRows(k)
