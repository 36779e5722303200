"""The rows an online frame's steps take (a region of the system): the rows the frame changed and
the rows within a few hops of them along the rows' neighbours (:func:`reach`): compiled where numba
runs (:mod:`diffuser_lab.backends.numba.region`), numpy otherwise (the same rows)."""
from __future__ import annotations

import numpy as np

from . import numba as nb


GAP = 64
"""Region rows closer than this are joined, the rows between included: the region is stepped in runs
of consecutive rows (their data stays in cache; stepping a row more only moves it on)."""


def reach(neighbors: np.ndarray, rows: np.ndarray, hops: int, extra: tuple[int, int] = (0, 0),
          gap: int = GAP) -> np.ndarray:
    """Rows within ``hops`` hops of ``rows`` along the neighbour lists, and the range ``extra``, with
    the rows between two of them fewer than ``gap`` apart.

    Args:
        neighbors: (N, K) int32 each row's neighbours (row j is read by row i when j is in
            neighbors[i]: a hop goes from i to its neighbours).
        rows: (R,) int64 the starting rows (any order, each once or more).
        hops: how many hops (0: the rows alone). extra: ``[lo, hi)`` rows added as they are.
    Returns:
        (M,) int64 sorted rows.
    """
    n = neighbors.shape[0]
    mask = np.zeros(n, np.bool_)
    rows = np.asarray(rows, np.int64)
    if nb.available():
        from .numba.region import reach_mask

        reach_mask(neighbors, rows, int(hops), mask)
    else:
        mask[rows] = True
        edge = rows
        for _ in range(int(hops)):
            reached = neighbors[edge].ravel()
            edge = np.unique(reached[~mask[reached]])
            if edge.size == 0:
                break
            mask[edge] = True
    mask[extra[0] : extra[1]] = True
    out = np.flatnonzero(mask)
    d = np.diff(out)
    holes = np.flatnonzero((d > 1) & (d < gap))
    if holes.size == 0:
        return out
    lens = d[holes] - 1
    first = np.repeat(out[holes] + 1 - np.cumsum(np.r_[0, lens[:-1]]), lens)
    mask[first + np.arange(lens.sum())] = True
    return np.flatnonzero(mask)
