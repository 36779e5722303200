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

Both backends follow the rule of :mod:`diffuser_lab.backends.knn` (float64 ``((dx*dx + dy*dy) +
dz*dz)``, rows by (d2, index), the index being the insertion index) and report the same changed
rows (:func:`~diffuser_lab.backends.knn.closer_rows`: a new point strictly closer than the K-th),
so their rows are equal element for element.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from . import numba as nb
from .knn import TIE_MARGIN, closer_rows, kdtree_rows, numpy_weights
from .numba.growing import GridRows


class TreeRows:
    """The rows from scipy's cKDTree over all points (rebuilt per add) by the rule
    (:func:`~diffuser_lab.backends.knn.kdtree_rows`), as the compiled path's."""

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
        aff = np.flatnonzero(np.square(dn) < kth[:n_old] * (1 + TIE_MARGIN)).astype(np.int64)
        aff = aff[closer_rows(P, kth, aff, n_old, n)]
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
        idx, d2 = kdtree_rows(tree, P, rows, self.k)
        nbr[rows] = idx
        d2_out[rows] = d2
        d0[rows] = np.where(d2 > 0, d2, np.inf).min(1)
        kth[rows] = d2[:, -1]


def rows_backend(k: int) -> GridRows | TreeRows:
    """The rows backend of a new graph with K = ``k``: compiled when the kernels are used
    (:func:`diffuser_lab.backends.numba.available`), else scipy."""
    return GridRows(k) if nb.available() else TreeRows(k)
