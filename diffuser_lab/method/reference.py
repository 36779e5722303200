"""A straightforward scipy float64 implementation of Eqs. 1-15, for benchmarks and cross-checks.

This is what a direct transcription of the paper looks like with numpy/scipy (as in the authors'
public CPU path): a KD-tree kNN, float64 edge weights, a CSR matrix, the row normalisation of
Eqs. 14-15 with sparse diagonal products, the plain iteration ``Z <- P Z + B`` (Eq. 10) over all
classes, and evidence accumulated through a dense one-hot matrix per frame. It has none of the
package's optimisations (spatial order, float32, compiled kernels, numerical floors) and is the
yardstick the benchmark rows are measured against.
"""
from __future__ import annotations

from typing import Iterable

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree


def reference_graph(points: np.ndarray, k: int, normals: np.ndarray | None = None, *, sigma_s: float = 0.2,
                    sigma_d_factor: float = 2.0) -> sp.csr_matrix:
    """Eqs. 3-4: (N, N) float64 CSR of kNN weights (self excluded, sigma_d = factor * rho)."""
    p = np.asarray(points, np.float64)
    n = len(p)
    dist, idx = cKDTree(p).query(p, k=k + 1, workers=-1)
    dist, idx = dist[:, 1:], idx[:, 1:]
    rho = dist[:, 0].mean()
    sd = sigma_d_factor * rho
    expo = -dist**2 / (2 * sd**2)
    if normals is not None:
        nr = np.asarray(normals, np.float64)
        expo -= ((nr[:, None, :] - nr[idx]) ** 2).sum(-1) / (2 * sigma_s**2)
    w = np.exp(expo)
    return sp.csr_matrix((w.ravel(), idx.ravel(), np.arange(0, n * k + 1, k)), shape=(n, n))


def reference_system(G: sp.csr_matrix, mass: np.ndarray, pixel_weight: float) -> tuple[sp.csr_matrix, np.ndarray]:
    """Eqs. 14-15: P = D^-1 G, B = D^-1 lambda E with D = diag(G 1 + lambda E 1)."""
    pix = pixel_weight * np.asarray(mass, np.float64)
    d = np.asarray(G.sum(1)).ravel() + pix.sum(1)
    inv = 1.0 / d
    return (sp.diags(inv) @ G).tocsr(), pix * inv[:, None]


def reference_diffuse(P: sp.csr_matrix, B: np.ndarray, iterations: int) -> np.ndarray:
    """Eq. 10 from Z = 0, ``iterations`` times: (N, C) float64."""
    Z = np.zeros_like(B)
    for _ in range(iterations):
        Z = P @ Z + B
    return Z


def reference_labels(points, normals, mass, *, k: int = 24, pixel_weight: float = 1e-4, iterations: int = 100,
                     sigma_s: float = 0.2, sigma_d_factor: float = 2.0) -> np.ndarray:
    """Graph + normalisation + ``iterations`` of Eq. 10 + argmax (-1 where Z stays 0)."""
    G = reference_graph(points, k, normals, sigma_s=sigma_s, sigma_d_factor=sigma_d_factor)
    P, B = reference_system(G, mass, pixel_weight)
    Z = reference_diffuse(P, B, iterations)
    lab = Z.argmax(1)
    lab[Z.max(1) <= 0] = -1
    return lab


def reference_evidence(points: np.ndarray, frames: Iterable, num_classes: int, depth_tol: float = 0.05) -> np.ndarray:
    """Eqs. 1-2, 11-12 with a dense (H*W, C) one-hot matrix per frame: (N, C) float64 mass."""
    p = np.asarray(points, np.float64)
    mass = np.zeros((len(p), num_classes))
    for f in frames:
        h, w = f.depth.shape
        lab = f.labels.ravel()
        onehot = np.zeros((h * w, num_classes))
        ok = lab >= 0
        onehot[np.flatnonzero(ok), lab[ok]] = 1.0
        pc = p @ f.T_cw[:3, :3].T + f.T_cw[:3, 3]
        z = pc[:, 2]
        front = z > 1e-6
        uv = pc[front] @ np.asarray(f.K, np.float64).T
        u, v = np.rint(uv[:, 0] / uv[:, 2]), np.rint(uv[:, 1] / uv[:, 2])
        ins = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        i = np.flatnonzero(front)[ins]
        pix = v[ins].astype(np.int64) * w + u[ins].astype(np.int64)
        d = f.depth.ravel()[pix]
        vis = (d > 0) & (np.abs(z[i] - d) <= depth_tol)
        mass[i[vis]] += onehot[pix[vis]]
    return mass
