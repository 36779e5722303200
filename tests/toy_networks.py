"""Toy 2D networks (grey levels of the RGB image) for predictions=model: importable by a test and, as
``tests.toy_networks.<name>``, by the command line run from the repository root (the README's
example of a network in the loop). Nothing here imports the tests' helpers."""
from __future__ import annotations

import numpy as np

# The models' own 4-class label space (dark, mid, light, bright grey) and where its classes go.
GREY_TO_SCANNET20 = "source_id,source_name,target\n0,dark,chair\n1,mid,wall\n2,light,floor\n3,bright,ignore\n"
CALLS = {"n": 0}


def grey_levels(rgb, cuts=(60, 120, 180)):
    """Label ids (H, W) uint8: the grey level's bin among ``cuts`` (4 classes)."""
    CALLS["n"] += 1
    return np.digitize(rgb.astype(np.float32).mean(axis=2), cuts).astype(np.uint8)


def soft_grey(rgb, centres=(40.0, 100.0, 160.0, 220.0), temperature=25.0):
    """Class probabilities (H/2, W/2, 4) float32: softmax of minus the distance to each grey centre,
    at half the input's resolution (the pipeline resizes it bilinearly)."""
    CALLS["n"] += 1
    g = rgb[::2, ::2].astype(np.float32).mean(axis=2)
    s = -np.abs(g[..., None] - np.asarray(centres, np.float32)) / temperature
    e = np.exp(s - s.max(axis=2, keepdims=True))
    return e / e.sum(axis=2, keepdims=True)


class GreyWithDepth:
    """A class target: built once with its kwargs, called per frame as model(rgb, depth)."""

    def __init__(self, near=1.0):
        self.near, self.depths = near, []

    def __call__(self, rgb, depth):
        CALLS["n"] += 1
        self.depths.append(depth)
        ids = grey_levels(rgb)
        return np.where((depth > 0) & (depth < self.near), 3, ids).astype(np.int32)


def make_grey(cuts=(60, 120, 180)):
    """A factory target: needs no frame, returns the per-frame callable."""
    return lambda rgb: grey_levels(rgb, cuts)


def grey_embeddings(rgb, dim=16, stride=4):
    """Embeddings (dim, H/stride, W/stride) float32, channel first like a CNN's: the soft grey
    classes of :func:`soft_grey` times fixed random unit prototypes (a toy feature network)."""
    CALLS["n"] += 1
    p = soft_grey(rgb[::stride // 2, ::stride // 2])  # (H/stride, W/stride, 4)
    E = np.random.default_rng(7).normal(size=(4, dim)).astype(np.float32)
    E /= np.linalg.norm(E, axis=1, keepdims=True)
    return np.moveaxis(p @ E, 2, 0)


def grey_embedding_queries(names):
    """The prototypes of :func:`grey_embeddings` for the first four names (a toy text encoder)."""
    E = np.random.default_rng(7).normal(size=(4, 16)).astype(np.float32)
    return (E / np.linalg.norm(E, axis=1, keepdims=True))[: len(names)]
