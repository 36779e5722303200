"""Eqs. 14-15 for a set of rows: the one numpy path and the dispatch to the compiled one
(:mod:`diffuser_lab.backends.numba.normalise`, bit for bit the same float32 results).

With G the kNN weights (Eq. 4) of row s and E the pixel mass of its point o (Eq. 12, before lambda):
    d_s  = Sum_j G_sj + lambda * Sum_c E_oc          (denominator of Eqs. 14-15)
    P_sj = gamma * G_sj / d_s  (0 where G_sj / d_s < edge_floor)      (Eq. 14)
    B_sc = lambda * E_oc / d_s                                        (Z^{I->X}, Eq. 15)
gamma = 1 is the paper's system; an online run's discount gamma < 1 is folded into P.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from . import numba as nb
from .numba import normalise as compiled


def normalise_rows(rows: Optional[np.ndarray], order: Optional[np.ndarray], weights: np.ndarray,
                   row_sums: np.ndarray, mass: np.ndarray, pixel_weight: float, gamma: float, edge_floor: float,
                   P: np.ndarray, B: np.ndarray) -> None:
    """Eqs. 14-15 of ``rows`` (sorted int64 row indices; None: every row) into ``P`` and ``B`` in place.

    Args:
        order: (N,) int64 the point (row of ``mass``) of row s, or None when row s is point s.
        weights: (N, K) float32 G; row_sums: (N,) float64 Sum_j G_sj; mass: (M, C) pixel mass.
        P: (N, K) float32 and B: (N, C) float32, rows in the rows' order.
    """
    if nb.available() and compiled.takes(mass):
        compiled.normalise_rows(rows, order, weights, row_sums, mass, pixel_weight, gamma, edge_floor, P, B)
    else:
        normalise_rows_numpy(rows, order, weights, row_sums, mass, pixel_weight, gamma, edge_floor, P, B)


def normalise_rows_numpy(rows, order, weights, row_sums, mass, pixel_weight, gamma, edge_floor, P, B) -> None:
    """The numpy path of :func:`normalise_rows` (float32 throughout)."""
    sel = slice(None) if rows is None else rows
    if order is None:
        pts = sel
    else:
        pts = order if rows is None else order[rows]
    pix = np.asarray(mass)[pts].astype(np.float32) * np.float32(pixel_weight)
    denom = row_sums[sel].astype(np.float32) + pix.sum(1)
    # a point whose edges all underflowed and that has no pixel mass is isolated: zero row
    inv = np.divide(1.0, denom, out=np.zeros_like(denom), where=denom > 1e-30).astype(np.float32)
    p = weights[sel] * inv[:, None]
    p[p < edge_floor] = 0.0
    if gamma != 1.0:
        p *= np.float32(gamma)
    P[sel] = p
    B[sel] = pix * inv[:, None]
