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

import dataclasses

import numpy as np

from diffuser_lab.backends import features as compiled_features
from diffuser_lab.backends.records import to_float16

from .diffusion import normalise
from .solvers import solve

__all__ = ["encode", "decode", "normalised", "unit_float16", "diffuse_features", "class_scores", "top_probability",
           "CLIP_TEMPERATURE"]


def normalised(f: np.ndarray, axis: int = -1) -> tuple[np.ndarray, np.ndarray]:
    """(..., D) features -> (unit float32 features, (...) bool whether the feature is usable: finite
    and of non-zero norm); unusable rows are 0."""
    f = np.asarray(f, np.float32)
    norm = np.sqrt(np.einsum("...d,...d->...", f, f))
    ok = np.isfinite(norm) & (norm > 0)
    out = np.where(ok[..., None], f / np.where(ok, norm, 1)[..., None], 0).astype(np.float32)
    return out, ok


def unit_float16(F: np.ndarray, chunk: int = 32768) -> np.ndarray:
    """(N, D) features -> (N, D) float16 unit rows (0 rows where unusable), normalised a chunk of
    rows at a time: no (N, D) float32 temporaries (what runs keep and write of 300k x 512 features)."""
    out = np.empty(F.shape, np.float16)
    for lo in range(0, F.shape[0], chunk):
        to_float16(normalised(F[lo:lo + chunk])[0], out[lo:lo + chunk])  # numpy's cast of subnormals is slow
    return out


def encode(F: np.ndarray, n: np.ndarray, out: np.ndarray | None = None, dim: int | None = None) -> np.ndarray:
    """(N, B) sums of unit pixel features and (N,) their counts -> (N, B + 1) float32 non-negative
    pixel mass for the diffusion core (module docstring), whose rows sum to the counts.

    ``dim``: the features' D when ``F`` holds B of its columns (a block, :func:`diffuse_features`):
    the B columns are scaled by 1 / 2D and the last column is the balance ``n - sum``, so a block's
    rows still sum to the counts and it diffuses through the same system. ``out`` (N, B + 1) float32
    may be given."""
    F = np.asarray(F, np.float32)
    N, B = F.shape
    D = B if dim is None else int(dim)
    n = np.asarray(n, np.float32).reshape(N, 1)
    out = np.empty((N, B + 1), np.float32) if out is None else out
    s = np.float32(1.0 / (2 * D))
    np.add(F, n, out=out[:, :B])
    out[:, :B] *= s
    out[:, B] = n[:, 0] - out[:, :B].sum(1, dtype=np.float64).astype(np.float32)
    np.maximum(out, 0, out=out)  # float rounding only: exact values are >= 0
    return out


def decode(Z: np.ndarray, out: np.ndarray | None = None, dim: int | None = None) -> np.ndarray:
    """(N, B + 1) diffused encoded mass -> (N, B) float32 diffused feature sums (module docstring;
    ``dim``: D when the columns are a block of it, as :func:`encode`'s)."""
    Z = np.asarray(Z, np.float32)
    B = Z.shape[1] - 1
    D = B if dim is None else int(dim)
    total = Z.sum(1, dtype=np.float64).astype(np.float32)
    out = np.empty((Z.shape[0], B), np.float32) if out is None else out
    np.multiply(Z[:, :B], np.float32(2 * D), out=out)
    out -= total[:, None]
    return out


STATE_BYTES = 1 << 30
"""A features diffusion runs all D columns at once while its state (B, Z and Z's next step:
3 x N x (D + 1) float32) fits this; beyond it, in blocks of :data:`BLOCK` columns."""
BLOCK = 128


def diffuse_features(graph, F: np.ndarray, n: np.ndarray, pixel_weight: float, solver, observer=None,
                     block: int | None = None):
    """Diffuse (N, D) feature sums ``F`` (pixel counts ``n`` (N,)) over ``graph`` with the solver
    config ``solver`` (:func:`diffuser_lab.method.solvers.solve`), through the unchanged core.

    All columns at once when the state fits :data:`STATE_BYTES` and no ``block`` is given
    (``observer`` sees every recorded iteration, encoded); otherwise in blocks of ``block`` (default
    :data:`BLOCK`) columns, each with its balance column (:func:`encode` ``dim``): the same system,
    so a column diffuses as it would at once; the first block runs the early stop and the others
    the same number of iterations (``observer`` is not called: the intermediate state never exists
    whole), and ``F`` is overwritten block by block with the result (the peak memory: ~F plus one block).

    Returns (N, D) float32 the diffused feature sums and the (first) DiffusionResult (its ``Z``:
    the encoded scores of all columns at once, or None in blocks)."""
    N, D = F.shape
    if block is None and 3 * 4 * N * (D + 1) <= STATE_BYTES:
        res = solve(normalise(graph, encode(F, n), pixel_weight), solver, observer=observer)
        return decode(res.Z), res
    block = int(block or BLOCK)
    F = np.ascontiguousarray(F, np.float32)
    first = None
    for lo in range(0, D, block):
        hi = min(D, lo + block)
        cfg = solver if first is None else dataclasses.replace(solver, max_iter=max(first.iterations, 1), tol=0.0)
        res = solve(normalise(graph, encode(F[:, lo:hi], n, dim=D), pixel_weight), cfg)
        F[:, lo:hi] = decode(res.Z, dim=D)
        first = first or res
    first = dataclasses.replace(first, Z=None, info={**first.info, "feature_blocks": -(-D // block), "block": block})
    return F, first

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


def top_probability(cos: np.ndarray, to_class: np.ndarray, num_classes: int,
                    temperature: float = CLIP_TEMPERATURE) -> np.ndarray:
    """(N, Q) cosines -> (N,) float32 the top class's probability: max over classes of
    :func:`class_scores` over their sum (0 where the sum is 0), bit for bit.

    What picks a point's most confident view, once per linked pixel: the scores are made class-major
    ((C, N): whole rows per class and query, no strided columns) and the row sum adds the classes in
    the order NumPy's reduction over a row of C <= 128 numbers uses (eight accumulators, then the
    rest), so the result equals ``s.max(1) / s.sum(1)`` of :func:`class_scores`' ``s`` exactly (the
    test compares them). With numba the rows are one compiled pass after the exponentials
    (:func:`diffuser_lab.backends.features.top_probability_rows`, the same operations in the same order). Other
    inputs (not float32, C > 128) take the plain path."""
    cos = np.asarray(cos)
    to_class = np.asarray(to_class)
    if cos.dtype != np.float32 or cos.ndim != 2 or not 0 < num_classes <= 128:
        return _top_of_scores(class_scores(cos, to_class, num_classes, temperature))
    n = cos.shape[0]
    if compiled_features.available() and n:
        e = np.subtract(cos, np.float32(1), order="C")  # class_scores' exp values (NaN kept: the kernel's 0)
        e /= np.float32(temperature)
        np.exp(e, out=e)
        out = compiled_features.top_probability_rows(e, to_class, num_classes)
        if out is not None:
            return out
    t = np.array(cos.T, order="C")  # (Q, N) a copy (never a view: worked in place)
    np.nan_to_num(t, copy=False, nan=-np.inf)
    t -= 1
    t /= np.float32(temperature)
    np.exp(t, out=t)
    s = np.zeros((num_classes, n), np.float32)
    for q, c in enumerate(to_class):
        if 0 <= c < num_classes:
            np.maximum(s[c], t[q], out=s[c])
    total = _row_sum_order(s)
    return np.divide(s.max(0) if n else np.zeros(0, np.float32), total, out=np.zeros_like(total),
                     where=total > 0)


def _row_sum_order(s: np.ndarray) -> np.ndarray:
    """(C, N) -> (N,) the sums over C in the order of NumPy's pairwise sum of a contiguous row of
    C <= 128 (its ``pairwise_sum``: C < 8 in turn; else eight running sums of every eighth number,
    combined ((0+1)+(2+3))+((4+5)+(6+7)), then the remainder in turn)."""
    c = s.shape[0]
    if c < 8:
        total = s[0].copy()
        for j in range(1, c):
            total += s[j]
        return total
    r = s[:8].copy()
    i = 8
    while i < c - c % 8:
        r += s[i:i + 8]
        i += 8
    total = (r[0] + r[1]) + (r[2] + r[3])
    total += (r[4] + r[5]) + (r[6] + r[7])
    for j in range(i, c):
        total += s[j]
    return total


def _top_of_scores(s: np.ndarray) -> np.ndarray:
    total = s.sum(1)
    return np.divide(s.max(1), total, out=np.zeros_like(total), where=total > 0)
