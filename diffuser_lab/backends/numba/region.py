"""Compiled :func:`diffuser_lab.backends.region.reach`: a breadth-first walk of the rows' neighbour
lists, one hop at a time (the same rows as its numpy twin)."""
from __future__ import annotations

import numpy as np

from . import NB

if NB is not None:
    from numba import njit

    @njit(cache=True, boundscheck=False)
    def reach_mask(nbr, rows, hops, mask):
        """mask[i] = True for the rows within ``hops`` hops of ``rows`` (mask all False on entry)."""
        edge = np.empty(nbr.shape[0], np.int64)
        m = 0
        for r in rows:
            if not mask[r]:
                mask[r] = True
                edge[m] = r
                m += 1
        lo, hi = 0, m
        for _ in range(hops):
            for e in range(lo, hi):
                i = edge[e]
                for kk in range(nbr.shape[1]):
                    j = nbr[i, kk]
                    if not mask[j]:
                        mask[j] = True
                        edge[m] = j
                        m += 1
            if m == hi:
                break
            lo, hi = hi, m
