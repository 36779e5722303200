"""Edge weights that also carry the points' own similarity (``graph.affinity``): LUDVIG's graph.

LUDVIG (Marrie et al., ICCV 2025, arXiv 2410.14462, Sec. 4, graph diffusion) refines uplifted 3D
features by diffusion over a kNN graph of the 3D Gaussians whose edge weights combine the
geometry with the similarity of the elements' own (DINOv2) features. In this project's terms that is
a third factor of Eq. 4:

    w_ij = exp(-|x_i - x_j|^2 / (2 sigma_d^2) - |n_i - n_j|^2 / (2 sigma_s^2)) * exp(-|c_i - c_j|^2 / (2 sigma_c^2))

with c the points' colour (``graph.affinity=colour``: RGB in [0, 1], the cloud's colours) or their
averaged evidence (``features``: a features run's averaged unit features, a labels run's averaged
class distribution, i.e. the Bayesian evidence normalised). An edge to or from a point without an
attribute (no evidence) keeps its Eq. 4 weight. Everything else (Eqs. 14-16, the solvers) is
unchanged: the graph variant is an ablation of Diffuser itself (default ``none``: Eq. 4 as written).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from diffuser_lab.config import GraphAffinity

from .graph import KnnGraph, SortedKnnGraph

__all__ = ["attributes", "apply_affinity"]

CHUNK_ELEMENTS = 1 << 23
"""Rows x K x attribute columns compared at once (bounds the float32 temporaries to ~32 MB)."""


def attributes(affinity: GraphAffinity | str, *, colors: Optional[np.ndarray] = None,
               mass: Optional[np.ndarray] = None, links: Optional[np.ndarray] = None,
               average: Optional[np.ndarray] = None) -> tuple[Optional[np.ndarray], Optional[np.ndarray]]:
    """The (N, A) attributes c of ``affinity`` and (N,) bool which points have one (None, None for
    ``none``). ``colors``: (N, 3) uint8 or [0, 1] float; ``mass``, ``links``: the evidence (a labels
    run: the class distribution mass / links); ``average``: a features run's (N, D) unit averages."""
    affinity = GraphAffinity(affinity)
    if affinity == GraphAffinity.none:
        return None, None
    if affinity == GraphAffinity.colour:
        if colors is None:
            raise ValueError("graph.affinity=colour: the scene's cloud has no colours (the real sources' clouds "
                             "have them: scene=scannet0470, scannet_frames, rgbd_folder); use graph.affinity="
                             "features or none")
        c = np.asarray(colors, np.float32)
        if c.size and c.max() > 1.0:
            c = c / np.float32(255.0)
        return c, np.ones(c.shape[0], bool)
    known = np.asarray(links) > 0
    if average is not None:
        return average, known
    m = np.asarray(mass, np.float32)
    c = np.divide(m, np.asarray(links, np.float32)[:, None], out=np.zeros_like(m), where=known[:, None])
    return c, known


def apply_affinity(graph: KnnGraph, attrs: np.ndarray, known: np.ndarray, sigma_c: float) -> KnnGraph:
    """Multiply ``graph``'s edge weights in place by exp(-|c_i - c_j|^2 / (2 sigma_c^2)) where both
    ends have an attribute (module docstring), and refresh its row sums. ``attrs`` (N, A), ``known``
    (N,) in the caller's point order. Returns the graph."""
    s2 = np.float32(2.0 * float(sigma_c) ** 2)
    if isinstance(graph, SortedKnnGraph):
        nbr, w, order = graph.sorted_neighbors, graph.sorted_weights, graph.order
    else:
        nbr, w, order = graph.neighbors, graph.weights, None
    n, k = nbr.shape
    step = max(1, CHUNK_ELEMENTS // max(1, k * attrs.shape[1]))
    for lo in range(0, n, step):  # row chunks: no (N, K, A) temporary
        rows = np.arange(lo, min(n, lo + step))
        pts = rows if order is None else order[rows]
        nb = nbr[rows] if order is None else order[nbr[rows]]
        a = np.asarray(attrs[pts], np.float32)[:, None, :]
        b = np.asarray(attrs[nb.ravel()], np.float32).reshape(rows.size, k, -1)
        d2 = np.einsum("rkc,rkc->rk", a - b, a - b)
        f = np.exp(-d2 / s2).astype(np.float32)
        f[~(known[pts][:, None] & known[nb])] = 1.0
        w[rows] *= f
    if isinstance(graph, SortedKnnGraph):
        graph.sorted_row_sums = graph.sorted_weights.sum(1, dtype=np.float64)
        graph._public = None  # the caller-order view is rebuilt from the new weights
    return graph
