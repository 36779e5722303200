"""Features through the one diffusion core (Eqs. 10-16 with D-dimensional evidence).

A feature pixel (a network's per-pixel embedding, L2-normalised) takes the place of a pixel's class
probabilities in Eqs. 11-13: the mass and the depth check are unchanged, and since the system is linear
in the evidence, the graph diffuses features as it diffuses class scores. The core, however, is built for
class masses (non-negative columns whose row sum is the point's pixel count: Eq. 13's rows sum to 1)
and must not learn which it carries. So a unit feature ``f`` in R^D enters it as the D + 1
non-negative numbers

    g_d = (1 + f_d) / (2D)   (d < D),        g_D = 1/2 - Sum_d f_d / (2D),

which sum to 1 like a probability vector (|f_d| <= 1 and Sum_d f_d <= sqrt(D) <= D keep every g >= 0).
The map is affine, so a point's mass (the sum over its linked pixels) is encoded from its feature sum
``F`` (N, D) and pixel count ``n`` (N,) alone (:func:`encode`), and after the diffusion (linear)

    Z_f = 2D Z_g[:, :D] - Sum_d' Z_g[:, d']      (:func:`decode`),

the row sum being the diffused pixel count. Z_f is then exactly the diffusion of the feature sums
(float32: ~1e-6 of a row's scale, measured in tests/method/test_features.py). The early stop measures
the encoded scores' relative change, as for class probabilities.

Why L2-normalised pixels: the embeddings of CLIP-like networks are compared by cosine, so their
direction is the information and their norm is not (it varies with the network and the image); a
unit vector gives every linked pixel the same weight lambda, as a probability vector does (Eq. 13),
and it is what keeps the encoding non-negative.
"""
from __future__ import annotations

import numpy as np

__all__ = ["encode", "decode", "normalised", "class_scores", "CLIP_TEMPERATURE"]


def normalised(f: np.ndarray, axis: int = -1) -> tuple[np.ndarray, np.ndarray]:
    """(..., D) features -> (unit float32 features, (...) bool whether the feature is usable: finite
    and of non-zero norm); unusable rows are 0."""
    f = np.asarray(f, np.float32)
    norm = np.sqrt(np.einsum("...d,...d->...", f, f))
    ok = np.isfinite(norm) & (norm > 0)
    out = np.where(ok[..., None], f / np.where(ok, norm, 1)[..., None], 0).astype(np.float32)
    return out, ok


def encode(F: np.ndarray, n: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """(N, D) sums of unit pixel features and (N,) their counts -> (N, D + 1) float32 non-negative
    pixel mass for the diffusion core (module docstring); ``out`` (N, D + 1) float32 may be given."""
    F = np.asarray(F, np.float32)
    N, D = F.shape
    n = np.asarray(n, np.float32).reshape(N, 1)
    out = np.empty((N, D + 1), np.float32) if out is None else out
    s = np.float32(1.0 / (2 * D))
    np.add(F, n, out=out[:, :D])
    out[:, :D] *= s
    out[:, D] = 0.5 * n[:, 0] - F.sum(1, dtype=np.float64).astype(np.float32) * s
    np.maximum(out, 0, out=out)  # float rounding only: exact values are >= 0
    return out


def decode(Z: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """(N, D + 1) diffused encoded mass -> (N, D) float32 diffused feature sums (module docstring)."""
    Z = np.asarray(Z, np.float32)
    D = Z.shape[1] - 1
    total = Z.sum(1, dtype=np.float64).astype(np.float32)
    out = np.empty((Z.shape[0], D), np.float32) if out is None else out
    np.multiply(Z[:, :D], np.float32(2 * D), out=out)
    out -= total[:, None]
    return out


CLIP_TEMPERATURE = 0.07
"""The temperature that turns cosines into class probabilities (CLIP's learned logit scale, 1/100
to 1/14 in practice; 0.07 is its initial value)."""


def class_scores(cos: np.ndarray, to_class: np.ndarray, num_classes: int,
                 temperature: float = CLIP_TEMPERATURE) -> np.ndarray:
    """(N, Q) cosines of points to queries -> (N, C) float32 non-negative class scores:
    ``exp((cos - 1) / temperature)`` of each class's best query (0 for a class no query names, and
    for rows of NaN: nothing reached the point). Normalised per row it is the softmax over classes
    that calibration and the recorders read as a class distribution (argmax = the query label)."""
    s = np.exp((np.nan_to_num(cos, nan=-np.inf) - 1) / np.float32(temperature)).astype(np.float32)
    out = np.zeros((cos.shape[0], num_classes), np.float32)
    for q, c in enumerate(np.asarray(to_class)):
        if 0 <= c < num_classes:
            np.maximum(out[:, c], s[:, q], out=out[:, c])
    return out
