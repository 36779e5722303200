"""A simulated embedding network (no network weights can be downloaded here) and query files.

An open-vocabulary network (CLIP / LSeg / OpenSeg ...) maps an image to per-patch embeddings in
R^D and class names to text embeddings in the same space; a pixel is labelled by its most similar
text embedding. The simulation:

- :func:`prototypes` stands in for the text encoder: one seeded unit vector per class *name*
  (the same name gives the same vector in any list, as a text encoder does), a shared common
  direction plus a class-specific part, so classes are 0.2-0.5 apart in cosine as CLIP's text
  embeddings are, not orthogonal; :func:`text_encoder` is it with the ``module.fn`` signature
  ``diffuser-lab-query --encoder`` calls.
- :func:`simulate_features` stands in for the image encoder: a frame's predicted labels (or class
  probabilities) -> an embedding map at the patch grid, with distortions that are *not* linear in
  the class probabilities (a patch leans to its majority class, boundary mixing between patches, a
  per-view rotation of a subspace, noise, L2 normalisation).
- :func:`write_queries` / :func:`load_queries`: a query set on disk, ``.npz`` with ``names`` (Q,) str
  and ``embeddings`` (Q, D) (computed elsewhere, e.g. by a real text encoder).
"""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Sequence

import numpy as np

from diffuser_lab import seeding

from .arrays import open_npz
from .scene import IGNORE

__all__ = ["prototypes", "text_encoder", "simulate_features", "write_queries", "load_queries", "check_queries",
           "QUERY_FILE"]

QUERY_FILE = "a .npz query file with 'names' (Q,) str and 'embeddings' (Q, D) float"
"""What :func:`load_queries` expects, as its error lines say it."""

COMMON_SHARE = (0.2, 0.5)
"""Range of a prototype's squared weight on the shared direction: two classes' cosine is about the
product of their weights (0.2-0.5), as between CLIP text embeddings of object names."""


def _name_seed(name: str) -> int:
    """A stable 64-bit integer of a class name (Python's ``hash`` of a str changes per process)."""
    return int.from_bytes(hashlib.blake2b(name.encode("utf-8"), digest_size=8).digest(), "little")


def prototypes(names: Sequence[str], dim: int = 512, seed: int = 0) -> np.ndarray:
    """Seeded class embeddings, the simulated text encoder.

    Row c is ``sqrt(a_c) u + sqrt(1 - a_c) v_c``: ``u`` the unit direction all classes share (from
    ``seed``), ``v_c`` a unit vector orthogonal to it and ``a_c`` in :data:`COMMON_SHARE`, both
    drawn from (``seed``, the name): the same name gives the same row in any list. Two classes'
    cosine is ``sqrt(a_i a_j)`` plus ``v_i . v_j`` (about +-1/sqrt(dim)): 0.2-0.5 at dim 512.

    Args:
        names: (C,) class names (or query texts).
        dim: D, the embedding dimension (>= 2).
        seed: the "network": another seed gives another embedding space.
    Returns:
        (C, D) float32, unit rows.
    """
    if dim < 2:
        raise ValueError(f"prototypes: dim {dim}, expected >= 2")
    u = seeding.keyed("text.common", seed, 0).standard_normal(dim)
    u /= np.linalg.norm(u)
    out = np.empty((len(names), dim), np.float64)
    for c, name in enumerate(names):
        rng = seeding.keyed("text.class", seed, 1, _name_seed(str(name)))
        v = rng.standard_normal(dim)
        v -= (v @ u) * u
        v /= np.linalg.norm(v)
        a = rng.uniform(*COMMON_SHARE)
        out[c] = np.sqrt(a) * u + np.sqrt(1.0 - a) * v
    return out.astype(np.float32)


def text_encoder(names: list[str]) -> np.ndarray:
    """(Q, 512) float32: :func:`prototypes` of ``names`` (seed 0), as an encoder callable
    (``diffuser-lab-query RUN --encoder diffuser_lab.data.embeddings.text_encoder``)."""
    return prototypes(names)


def _box_sum(a: np.ndarray) -> np.ndarray:
    """(h, w, ...) -> the sum over each cell's 3x3 neighbourhood (zero outside the grid)."""
    p = np.pad(a, [(1, 1), (1, 1)] + [(0, 0)] * (a.ndim - 2))
    h, w = a.shape[:2]
    return sum(p[i : i + h, j : j + w] for i in range(3) for j in range(3))


def _normalise(f: np.ndarray) -> np.ndarray:
    """Rows of (..., D) scaled to unit length (zero rows stay zero)."""
    n = np.linalg.norm(f, axis=-1, keepdims=True)
    return f / np.where(n > 0, n, 1.0)


def _cell_shares(labels, probs, num_classes: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Per patch-grid cell, the (h, w, C) float32 share of each class among its labelled pixels and
    the (h, w) bool mask of cells with at least one labelled pixel."""
    if probs is not None:
        p = np.asarray(probs, np.float32)
        if p.ndim != 3 or p.shape[2] != num_classes:
            raise ValueError(f"simulate_features: probabilities of shape {p.shape}, expected (H, W, {num_classes})")
        p = np.where(np.isfinite(p) & (p > 0), p, np.float32(0))
        s = p.sum(-1, keepdims=True)
        p = p / np.where(s > 0, s, 1)  # each labelled pixel counts once
        H, W = p.shape[:2]
        h, w = -(-H // stride), -(-W // stride)
        p = np.pad(p, [(0, h * stride - H), (0, w * stride - W), (0, 0)])
        hist = p.reshape(h, stride, w, stride, num_classes).sum((1, 3))
    else:
        lab = np.asarray(labels)
        if lab.ndim != 2 or lab.dtype.kind not in "iu":
            raise ValueError(f"simulate_features: labels of shape {lab.shape} dtype {lab.dtype}, "
                             f"expected (H, W) integer class ids")
        if lab.size and (lab.min() < IGNORE or lab.max() >= num_classes):
            raise ValueError(f"simulate_features: label ids {int(lab.min())}..{int(lab.max())}, expected "
                             f"{IGNORE}..{num_classes - 1}")
        H, W = lab.shape
        h, w = -(-H // stride), -(-W // stride)
        cell = (np.arange(H)[:, None] // stride) * w + np.arange(W)[None, :] // stride
        ok = lab >= 0
        flat = cell[ok].astype(np.int64) * num_classes + lab[ok]
        hist = np.bincount(flat, minlength=h * w * num_classes).reshape(h, w, num_classes).astype(np.float32)
    count = hist.sum(-1)
    valid = count > 0
    return hist / np.where(valid, count, 1)[..., None], valid


def _subspace_rotation(dim: int, k: int, angle_deg: float, rng: np.random.Generator):
    """A random rotation of a random k-dimensional subspace of R^dim (identity on the rest):
    (Q (dim, k) orthonormal, R (k, k)); the k/2 planes turn by ``angle_deg`` x U(0.5, 1), random sign."""
    k = min(k, dim) // 2 * 2
    q, _ = np.linalg.qr(rng.standard_normal((dim, k)))
    theta = np.deg2rad(angle_deg) * rng.uniform(0.5, 1.0, k // 2) * rng.choice([-1.0, 1.0], k // 2)
    R = np.zeros((k, k))
    c, s = np.cos(theta), np.sin(theta)
    i = np.arange(0, k, 2)
    R[i, i], R[i, i + 1], R[i + 1, i], R[i + 1, i + 1] = c, -s, s, c
    return q, R


def simulate_features(labels: np.ndarray | None, prototypes: np.ndarray, rng: np.random.Generator, *,
                      probs: np.ndarray | None = None, stride: int = 8, dominance: float = 2.0,
                      boundary_mix: float = 0.3, rotation_deg: float = 20.0, rotation_dims: int = 32,
                      noise: float = 0.3, dtype=np.float16) -> np.ndarray:
    """A simulated network's embedding map of one frame, at its patch grid.

    From the frame's predicted labels (H, W) int (``IGNORE`` = no label) or class probabilities
    ``probs`` (H, W, C) (each pixel's row normalised to sum 1; an all-zero or non-finite row = no
    label), per ``stride`` x ``stride`` cell of the patch grid:

    1. the classes' shares among the cell's labelled pixels, raised to ``dominance`` and
       renormalised (a patch leans to its majority class; 1 = proportional);
    2. the prototypes mixed by those weights, L2-normalised;
    3. boundary mixing: ``(1 - boundary_mix) f + boundary_mix * mean(f of the labelled 8-neighbour
       cells)``, L2-normalised (a patch's receptive field reaches its neighbours);
    4. a per-view rotation of a random ``rotation_dims``-dimensional subspace by ``rotation_deg``
       x U(0.5, 1) per plane, drawn from ``rng`` (a different one every call, i.e. every view);
    5. Gaussian noise of expected norm ``noise`` (``noise / sqrt(D)`` per component);
    6. L2 normalisation.

    Not linear in the class probabilities: step 1 (a power of the shares), the normalisations of
    steps 2, 3 and 6 (a mixed cell's feature is a unit vector, not the probability-weighted sum),
    step 4 (linear within a view but another map in every view: no one (C, D) matrix E gives the
    features as Y E over the views) and step 5 (additive, independent of Y). With
    ``dominance=1, boundary_mix=0, rotation_deg=0, noise=0`` a cell of one class is its prototype.

    Args:
        labels: (H, W) integer class ids in IGNORE..C-1, or None with ``probs``.
        prototypes: (C, D) class embeddings (:func:`prototypes`).
        rng: the view's generator (rotation and noise).
        probs: (H, W, C) class probabilities, used instead of ``labels`` when given.
        stride: the patch size in pixels (a ViT's 8, 14 or 16).
        dtype: the output's float dtype.
    Returns:
        (ceil(H / stride), ceil(W / stride), D) ``dtype``: unit rows; NaN rows where a cell has no
        labelled pixel.
    """
    E = np.asarray(prototypes, np.float32)
    if E.ndim != 2:
        raise ValueError(f"simulate_features: prototypes of shape {E.shape}, expected (C, D)")
    if stride < 1:
        raise ValueError(f"simulate_features: stride {stride}, expected >= 1")
    if probs is None and labels is None:
        raise ValueError("simulate_features: give labels (H, W) or probs (H, W, C)")
    C, D = E.shape
    shares, valid = _cell_shares(labels, probs, C, stride)
    w = shares ** np.float32(dominance)
    w /= np.where(valid, w.sum(-1), 1)[..., None]
    f = _normalise(w @ E)  # (h, w, D); zero rows where no pixel is labelled
    if boundary_mix > 0:
        n = _box_sum(valid.astype(np.float32)) - valid
        around = (_box_sum(f) - f) / np.where(n > 0, n, 1)[..., None]
        f = _normalise(np.where((n > 0)[..., None], (1 - boundary_mix) * f + boundary_mix * around, f))
    if rotation_deg and rotation_dims >= 2:
        q, R = _subspace_rotation(D, rotation_dims, rotation_deg, rng)
        q = q.astype(np.float32)
        f = f + ((f @ q) @ (R.T - np.eye(len(R))).astype(np.float32)) @ q.T
    if noise:
        f = f + rng.standard_normal(f.shape, dtype=np.float32) * np.float32(noise / np.sqrt(D))
    f = _normalise(f)
    f[~valid] = np.nan
    return f.astype(dtype, copy=False)


def check_queries(names: Sequence[str], embeddings, where: str, dim: int | None = None) -> tuple[list[str], np.ndarray]:
    """A query set checked: (names list[str], (Q, D) float32 embeddings as given).

    Raises:
        ValueError: one line starting with ``where``: no names, names not unique or empty, embeddings
            not (Q, D) with one row a name, a row not finite or all zero, D not ``dim`` (when given).
    """
    names = [str(n) for n in names]
    e = np.asarray(embeddings)
    if e.dtype.kind not in "fiu":
        raise ValueError(f"{where}: embeddings of dtype {e.dtype}, expected numbers (Q, D)")
    e = e.astype(np.float32, copy=False)
    if not names:
        raise ValueError(f"{where}: no query names, expected at least one")
    if e.ndim != 2 or e.shape[0] != len(names):
        raise ValueError(f"{where}: embeddings of shape {e.shape}, expected ({len(names)}, D): one row per name")
    if e.shape[1] < 1 or (dim is not None and e.shape[1] != dim):
        raise ValueError(f"{where}: embeddings of dimension {e.shape[1]}, expected "
                         f"{dim if dim is not None else '>= 1'}{' (the features)' if dim is not None else ''}")
    blank = [i for i, n in enumerate(names) if not n.strip()]
    if blank:
        raise ValueError(f"{where}: query {blank[0]} has an empty name, expected a text")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"{where}: query names {dup} repeated, expected unique names")
    bad = ~np.isfinite(e).all(1) | ~(np.abs(e) > 0).any(1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{where}: embedding of {names[i]!r} is not finite or all zero, expected a direction")
    return names, e


def write_queries(path: str | Path, names: Sequence[str], embeddings) -> Path:
    """Write a query set: ``.npz`` with ``names`` (Q,) str and ``embeddings`` (Q, D) float32.
    Returns the path written (``.npz`` appended when missing, as numpy does)."""
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    names, e = check_queries(names, embeddings, str(path))
    np.savez(path, names=np.array(names, dtype=str), embeddings=e)
    return path


def load_queries(path: str | Path, dim: int | None = None) -> tuple[list[str], np.ndarray]:
    """Read a query set written by :func:`write_queries` (or by a user's own extractor).

    Args:
        path: the ``.npz`` file.
        dim: when given, the D the embeddings must have (the features').
    Returns:
        (names list[str] of Q, (Q, D) float32 embeddings as stored).
    Raises:
        ValueError: one line naming the file and what was expected (unreadable, a missing key,
        names not strings, a wrong shape, D not ``dim`` ...: :func:`check_queries`).
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: unreadable (FileNotFoundError: no such file), expected {QUERY_FILE}")
    with open_npz(path, QUERY_FILE, "queries") as z:
        missing = [k for k in ("names", "embeddings") if k not in z]
        if missing:
            raise ValueError(f"{path}: no {' or '.join(repr(k) for k in missing)} array (has: "
                             f"{', '.join(z.files) or 'nothing'}), expected {QUERY_FILE}")
        names = z.read("names", ndim=1, kinds="SU", expected="a (Q,) array of strings")
        emb = z.read("embeddings")
    names = [n.decode("utf-8") if isinstance(n, bytes) else str(n) for n in names.tolist()]
    return check_queries(names, emb, str(path), dim)


def query_dim(queries: str | Path | None, encoder: str | None, names: Sequence[str]) -> int | None:
    """D of a run's queries before any frame is read: a query file's embeddings (``predictions.queries``,
    read), else a text encoder's output on ``names`` (``predictions.encoder``: ``module.fn``, called
    once on the names); None without either (the simulated network's prototypes take the frames' D)
    or when the encoder cannot say (the run's queries then report why, with the frames' D)."""
    if queries:
        return int(load_queries(queries)[1].shape[1])
    if not encoder:
        return None
    import importlib

    module, _, name = str(encoder).rpartition(".")
    try:
        out = getattr(importlib.import_module(module), name)([str(n) for n in names])
        if hasattr(out, "detach"):  # a torch tensor
            out = out.detach().float().cpu().numpy()
        shape = np.shape(out)
    except Exception:  # noqa: BLE001 - the queries' own loading names the encoder and its error
        return None
    return int(shape[1]) if len(shape) == 2 else None
