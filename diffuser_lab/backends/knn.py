"""The kNN graph's computations (paper Eqs. 3-4) behind one function per operation, on the compiled
kernels (:mod:`diffuser_lab.backends.numba`: Morton order, grid kNN, Eq. 4 weights) or their
numpy/scipy twins (Morton order of :mod:`diffuser_lab.backends.morton`, scipy's cKDTree, numpy's
exp): :func:`sorted_knn` then :func:`edge_weights`. Both paths give the same rows, element for
element; the weights agree to a float32 ulp (the compiled exp is a polynomial).

The one rule of every kNN row (batch and growing graph, compiled and numpy/scipy, any CPU):
    * squared distance in float64 from the float32 coordinates, ``((dx*dx + dy*dy) + dz*dz)``
      with dx = float64(x_j) - float64(x_i) (:func:`sq_dist`; the compiled kernels compute it
      without fastmath, so no FMA contracts it);
    * the point itself excluded, duplicates of it (d2 = 0) kept;
    * a row is its K smallest by (d2, index), in that order: at an exact tie the smaller index
      comes first, and wins the K-th place. The index is the graph's: the Morton-sorted index
      (:func:`~diffuser_lab.backends.morton.spatial_order`, a stable sort) in the batch graph,
      the insertion index in the growing one.
A KD-tree orders exact ties its own way and rounds its distances differently, so
:func:`kdtree_rows` queries more than K+1, ranks them by the rule, and queries again with more
the rows where a point it did not return could still tie the K-th.
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
    """Points in Morton order and their K nearest neighbours by the rule (module doc).

    Attributes:
        order: (N,) int64, ``order[s]`` = caller's index of sorted point s.
        idx: (N, K) int32 neighbours of each sorted point, as sorted indices, ascending by (d2, index).
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


TIE_MARGIN = 1e-9
"""Relative margin between a KD-tree's own distances and the rule's (they differ by rounding, ~1e-16):
a candidate the tree did not return may tie the K-th unless the last it returned is this much farther."""
EXTRA = 1
"""Candidates a KD-tree query returns beyond the K+1 (self included): the one that tells that the
K-th is not tied with a point left out (rows where it may be are queried again with twice as many)."""
CHUNK = 1 << 16
"""Rows per KD-tree query (bounds the (rows, candidates) temporaries)."""


def _summed(dx: np.ndarray, dy: np.ndarray, dz: np.ndarray) -> np.ndarray:
    """The rule's sum of float64 coordinate differences: ``(dx*dx + dy*dy) + dz*dz`` (separate
    ufuncs: never fused into an FMA)."""
    return (dx * dx + dy * dy) + dz * dz


def sq_dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared distances by the rule of every kNN path (module doc): float64
    ``((dx*dx + dy*dy) + dz*dz)`` of (..., 3) float32 (or float64) points a and b (broadcast), m^2."""
    return _summed(*(np.subtract(a[..., c], b[..., c], dtype=np.float64) for c in range(3)))


def kdtree_rows(tree: cKDTree, points: np.ndarray, rows: np.ndarray, k: int,
                workers: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Rows by the rule (module doc) of the points ``rows`` (M,) among the tree's: ``tree`` is a
    cKDTree of ``points[:tree.n]`` ((n, 3) float32 or float64, n > k).

    The tree is asked for K+1+:data:`EXTRA` candidates (self among them), ranked by (:func:`sq_dist`,
    index); a row is final when the last candidate lies beyond its K-th by more than
    :data:`TIE_MARGIN` (or all n were returned), else it is asked again with twice as many.

    Returns:
        idx: (M, K) int64 neighbours, ascending by (d2, index); d2: (M, K) float64 their squared
        distances, m^2.
    """
    n, m_rows = tree.n, rows.shape[0]
    cols = [np.ascontiguousarray(points[:n, c], np.float64) for c in range(3)]  # gathers per axis: fast
    idx = np.empty((m_rows, k), np.int64)
    d2 = np.empty((m_rows, k))
    for lo in range(0, m_rows, CHUNK):
        todo = np.arange(lo, min(lo + CHUNK, m_rows))
        m = min(k + 1 + EXTRA, n)
        while todo.size:
            own = rows[todo]
            dist, cand = tree.query(points[own], k=m, workers=workers)
            dd = _summed(*(x[cand] - x[own][:, None] for x in cols))  # sq_dist, axis by axis
            is_self = cand == own[:, None]
            dd[is_self] = -1.0
            # most rows come as the rule has them: self first, then strictly increasing d2
            ci, cd = cand[:, 1:k + 1], dd[:, 1:k + 1]
            tied = np.flatnonzero(np.any(dd[:, 1:] <= dd[:, :-1], axis=1))
            if tied.size:  # by index, then a stable sort by d2: by (d2, index), self last
                c = np.sort(cand[tied], 1)
                e = _summed(*(x[c] - x[own[tied]][:, None] for x in cols))
                e[c == own[tied][:, None]] = np.inf
                o = np.argsort(e, axis=1, kind="stable")[:, :k]
                ci[tied], cd[tied] = np.take_along_axis(c, o, 1), np.take_along_axis(e, o, 1)
            # a point not returned is at least as far as the last returned, by the tree's distance
            done = np.square(dist[:, -1]) * (1 - TIE_MARGIN) > cd[:, -1] if m < n else np.ones(todo.size, bool)
            if done.all() and todo[-1] - todo[0] == todo.size - 1:  # the usual case: one block of rows
                idx[todo[0]:todo[-1] + 1], d2[todo[0]:todo[-1] + 1] = ci, cd
            else:
                idx[todo[done]], d2[todo[done]] = ci[done], cd[done]
            todo = todo[~done]
            m = min(2 * m, n)
    return idx, d2


def closer_rows(points: np.ndarray, kth: np.ndarray, rows: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """(r,) bool: which of ``rows`` have a point of ``points[lo:hi]`` strictly closer than their
    K-th neighbour, by the rule's squared distance (:func:`sq_dist`) against ``kth[rows]`` (m^2):
    the rows a growing graph's add changes (an equal distance loses to the older, smaller index)."""
    if rows.size == 0:
        return np.zeros(0, bool)
    kth2 = kth[rows]
    lists = cKDTree(points[lo:hi]).query_ball_point(points[rows], np.sqrt(kth2) * (1 + TIE_MARGIN))
    lens = np.fromiter((len(x) for x in lists), np.int64, rows.size)
    cand = np.concatenate([np.asarray(x, np.int64) for x in lists]) + lo if lens.sum() else np.zeros(0, np.int64)
    owner = np.repeat(np.arange(rows.size), lens)
    ok = np.zeros(rows.size, bool)
    ok[owner[sq_dist(points[cand], points[rows[owner]]) < kth2[owner]]] = True
    return ok


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
    """Every point's K nearest among the (N, 3) ``points`` by the rule (module doc; index = row of
    ``points``) from scipy's cKDTree (:func:`kdtree_rows`, all threads): dist (N, K) float64
    (the square roots of the rule's d2), ascending, and idx (N, K) int64."""
    idx, d2 = kdtree_rows(cKDTree(points), points, np.arange(points.shape[0]), k, workers=-1)
    return np.sqrt(d2), idx


def _kdtree_rows(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every point's K nearest by a KD-tree (:func:`kdtree_rows`): idx (N, K) int32, d2 (N, K)
    float64 and d0 (N,), the smallest positive d2 (inf if none)."""
    idx, d2 = kdtree_rows(cKDTree(points), points, np.arange(points.shape[0]), k, workers=-1)
    return idx.astype(np.int32), d2, np.where(d2 > 0, d2, np.inf).min(1)


def sorted_knn(points: np.ndarray, normals: np.ndarray | None, k: int, backend: str = "auto") -> SortedKnn:
    """Morton order of the (N, 3) float32 ``points`` (C-contiguous) and every point's K nearest
    neighbours (Eq. 3) by the rule (module doc), on the compiled grid kNN (:func:`use_compiled`; a
    KD-tree where the cloud is too sparse for a dense grid) or scipy's cKDTree: the same rows on both.

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
