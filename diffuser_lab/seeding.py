"""Random draws keyed by what they are for.

A seed must give the same figures on every CPU and whatever geometry or floating point decided
before a draw. So a draw never comes from the running state of a generator that earlier draws,
in a number something else decided, have advanced: every draw is named by its purpose (a
string: ``"demo.layout"``, ``"surface.noise"``, ...) and the ids of what it is for (a triangle,
a sample, a camera candidate, a frame, a region). A point that one CPU keeps and another drops
changes that point's draws, not the rest of the run.

Three forms:

- :func:`rng`: numpy's ``default_rng([seed..., purpose, ids...])`` (its SeedSequence keys) for
  one thing whose draws are fixed by what it is (a room's layout, one camera candidate, one
  frame's blobs): a Generator to draw from as usual.
- :func:`uniform`, :func:`normal`, :func:`integers`: one counter-based draw per key, vectorised
  over arrays of ids (each sample of each triangle, each region of a frame): a splitmix64 hash of
  (seed, purpose, ids) -> 53 random bits. Integer arithmetic and ``scipy.special.ndtri`` (plain C,
  no run-time SIMD dispatch), so the bits are the same on every machine.
- :func:`keyed`: ``default_rng([key...])`` of an explicit integer key, no purpose id mixed in: the
  streams that predate purposes (:data:`KEYED`: the demo room's layout, a city block, the depth
  sensor's frames, the simulated text encoder, two samples), kept bit for bit because the reported
  figures were measured with them. A new draw takes :func:`rng` or the counter-based form.

Nothing else in the package or ``analysis/`` makes a generator or draws from ``np.random`` /
``random`` (``tests/test_seeding.py`` scans the code for it and pins every purpose's first draws).

A seed is an int or a sequence of ints (a key prefix, e.g. ``(seed, bx, by)`` for a city
block); negative ints are taken modulo 2**64.
"""
from __future__ import annotations

import zlib
from typing import Sequence, Union

import numpy as np

__all__ = ["Seed", "purpose_id", "rng", "keyed", "KEYED", "hash64", "uniform", "normal", "integers"]

Seed = Union[int, np.integer, Sequence[int]]

_MASK = (1 << 64) - 1
_M1, _M2, _GOLD = np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB), np.uint64(0x9E3779B97F4A7C15)


def purpose_id(purpose: str) -> int:
    """The stable 32-bit id of a purpose name (CRC-32 of its UTF-8 bytes): the same in every
    process, Python version and machine (``hash()`` of a str is salted per process)."""
    return zlib.crc32(purpose.encode("utf-8"))


def _words(seed: Seed) -> list[int]:
    if isinstance(seed, (int, np.integer)):
        return [int(seed) & _MASK]
    try:
        return [int(s) & _MASK for s in seed]
    except TypeError:
        raise TypeError(f"seed {seed!r}: expected an int or a sequence of ints (a draw's key), "
                        "not a generator") from None


def rng(seed: Seed, purpose: str, *ids: int) -> np.random.Generator:
    """The numpy Generator of one purpose and one thing: ``default_rng([*seed, purpose_id(purpose),
    *ids])``. Its draws depend on nothing else (no shared generator's running state).

    Args:
        seed: the run's seed (int) or a key prefix (sequence of ints).
        purpose: what the draws are for (a fixed string per call site).
        ids: ints naming the thing (a frame index, a candidate index, ...). SeedSequence pads a key
            with zeros, so trailing zero ids are no ids (``rng(s, p, 0)`` is ``rng(s, p)``): a purpose
            is drawn with the same number of ids at every call site.
    """
    return np.random.default_rng([*_words(seed), purpose_id(purpose), *(int(i) & _MASK for i in ids)])


KEYED = {
    "demo.layout": "(seed,): the demo room's layout, the room every figure so far shows",
    "city.block": "(seed, bx, by, 0): city block (bx, by)'s mesh",
    "city.views": "(seed, bx, by, 2): city block (bx, by)'s camera poses",
    "sensor.frame": "(seed, index, 0x5E45) mod 2**32: the depth sensor's draws of frame index",
    "text.common": "(seed, 0): the simulated text encoder's direction every class shares",
    "text.class": "(seed, 1, blake2b-64 of the name): a class's own direction and share",
    "geometry.spacing": "(seed,): the points the spacing rho is measured on (scene.voxel_size=auto)",
    "sparse.sample": "(seed,): the points sparse_classes=auto counts neighbourhood classes on",
}
"""The streams :func:`keyed` serves, by the name their call sites give, with their keys. They predate
purposes: their keys hold no purpose id, so two of them with the same ints are the same stream (the
layout's, the spacing's and the sparse sample's at seed 0: unrelated uses, never drawn together as
one; SeedSequence pads a key with zeros, so ``(seed, 0)`` is ``(seed,)`` too). Moving one to
:func:`rng` changes the figures measured with it."""


def keyed(purpose: str, *key: int) -> np.random.Generator:
    """The numpy Generator of an explicit integer key, ``default_rng([*key])`` (ints modulo 2**64): a
    stream that predates purposes (:data:`KEYED`), bit for bit what its call site drew before.

    Args:
        purpose: the stream's name in :data:`KEYED` (checked; not part of the key).
        key: the ints that are the key, as :data:`KEYED` gives them.
    Raises:
        KeyError: ``purpose`` is not one of :data:`KEYED` (a new draw takes :func:`rng`).
    """
    if purpose not in KEYED:
        raise KeyError(f"seeding.keyed({purpose!r}): not a stream that predates purposes ({', '.join(KEYED)}); "
                       "a new draw takes seeding.rng(seed, purpose, ...)")
    if not key:
        raise TypeError(f"seeding.keyed({purpose!r}): expected the key's ints, got none")
    return np.random.default_rng([int(k) & _MASK for k in key])


def _mix64(x: np.ndarray) -> np.ndarray:
    """splitmix64's finaliser on uint64 arrays: a fixed, well-mixed bijection (wraps mod 2**64)."""
    x = np.asarray(x, np.uint64)
    with np.errstate(over="ignore"):
        x = (x ^ (x >> np.uint64(30))) * _M1
        x = (x ^ (x >> np.uint64(27))) * _M2
    return x ^ (x >> np.uint64(31))


def hash64(*parts) -> np.ndarray:
    """uint64 hash of a tuple of integer arrays or ints (broadcast against each other), order-sensitive.
    Negative ints wrap modulo 2**64."""
    h = np.uint64(0)
    with np.errstate(over="ignore"):
        for p in parts:
            a = np.asarray(p)
            a = a if a.dtype == np.uint64 else a.astype(np.int64).astype(np.uint64)
            h = _mix64(np.asarray(h, np.uint64) * _GOLD + a)
    return h


def _bits(seed: Seed, purpose: str, ids) -> np.ndarray:
    return hash64(*_words(seed), purpose_id(purpose), *ids)


def uniform(seed: Seed, purpose: str, *ids) -> np.ndarray:
    """Uniform draws in the open interval (0, 1), float64 on a grid of 2**-52, one per element of the
    broadcast integer arrays ``ids`` (the same key gives the same number, whatever else is drawn)."""
    return ((_bits(seed, purpose, ids) >> np.uint64(12)).astype(np.float64) + 0.5) * 2.0**-52


def normal(seed: Seed, purpose: str, *ids) -> np.ndarray:
    """Standard normal draws, float64, one per key (the inverse CDF of :func:`uniform`'s draw)."""
    from scipy.special import ndtri

    return ndtri(uniform(seed, purpose, *ids))


def integers(seed: Seed, purpose: str, n, *ids) -> np.ndarray:
    """Integers uniform in [0, n) (n: int or array broadcast with the keys, 1 <= n < 2**53), int64,
    one per key."""
    u = uniform(seed, purpose, *ids)
    n = np.asarray(n, np.int64)
    return np.minimum((u * n).astype(np.int64), n - 1)
