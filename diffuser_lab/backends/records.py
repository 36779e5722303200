"""The recorders' hot loops, one function each: the compiled kernel
(:mod:`diffuser_lab.backends.numba.float16`) while the compiled kernels are on
(:func:`diffuser_lab.backends.numba.available`), else its numpy twin here. The twins give the
same bits, except where a docstring says otherwise (float32 summation order).

Z states encoded for run.mcap (:func:`transpose_into`, :func:`to_float16`, :func:`shares`),
the statistics of a recorded diffusion step (:func:`step_stats`) and an (N, D) float16 ``.npy``
written a chunk of rows at a time (:func:`write_rows`)."""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple, Optional

import numpy as np

from . import numba as nb
from .base import NONE as IGNORE  # the data layer's IGNORE: a point nothing reached
from .numba import float16


def _kernels():
    """:mod:`diffuser_lab.backends.numba.float16` while the compiled kernels are on, else None."""
    return float16 if nb.available() else None


def compiled() -> bool:
    """Whether the functions here run their compiled kernels now."""
    return _kernels() is not None


def transpose_into(a: np.ndarray, out: np.ndarray) -> None:
    """out[...] = a.T for a 2-D ``a`` (M, C) and a C-contiguous ``out`` (C, M) of the same dtype:
    compiled for float32 (4x numpy's strided copy at 51k x 20), numpy otherwise."""
    k = _kernels()
    if k is not None and a.dtype == np.float32 and out.dtype == np.float32 and a.flags.c_contiguous:
        k.transpose_f32(a, out)
    else:
        np.copyto(out, a.T)


_F16_MIN_NORMAL = np.float32(2.0**-14)


def to_float16(a: np.ndarray, out: Optional[np.ndarray] = None) -> np.ndarray:
    """``a.astype("<f2")`` for finite float32 ``a``, bit for bit, fast: numpy converts values
    that become float16 subnormals (magnitude below 2^-14; Z has many, so do unit features of
    hundreds of dimensions) in a slow path (~50 ms on a 1M-value Z state). Compiled for
    C-contiguous float32 (inf and nan too); otherwise those values are rounded here as the
    multiple of 2^-24 nearest (ties to even), with their sign: their float16 bit pattern.
    ``out``: a C-contiguous float16 array of ``a``'s shape to write into (e.g. a memory map's rows)."""
    k = _kernels()
    dst = out if out is not None and out.flags.c_contiguous else np.empty(a.shape, "<f2")
    if k is not None and a.dtype == np.float32 and a.flags.c_contiguous:
        k.f32_to_f16_bits(a.reshape(-1).view(np.uint32), dst.reshape(-1).view(np.uint16))
    else:
        mag = np.abs(a)
        sub = mag < _F16_MIN_NORMAL
        with np.errstate(over="ignore"):  # beyond 65504: inf, as numpy
            dst[...] = np.where(sub, np.float32(0.0), a).astype("<f2")
        bits = dst.view(np.uint16)
        bits[sub] = (np.rint(mag[sub] * np.float32(2.0**24)).astype(np.uint16)
                     | (np.signbit(a[sub]).astype(np.uint16) << np.uint16(15)))
    if out is not None and dst is not out:
        out[...] = dst
    return dst if out is None else out


def shares(a: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray]:
    """(M, C) float32 Z >= 0 -> (row sums (M,) float32, shares (C, M) uint8 or uint16): share
    q[c, i] = round(Z[i, c] / sum_c Z[i, c] * (2^bits - 1)), class-major. Compiled where numba is
    (one pass, ~1 ms on the 51k x 20 demo, ~11 ms at 566k), numpy otherwise; the two agree up to float rounding."""
    levels = (1 << bits) - 1
    dt = np.uint8 if bits <= 8 else np.uint16
    m, c = a.shape
    out = np.empty((c, m), dt)
    sums = np.empty(m, np.float32)
    k = _kernels()
    if k is not None and a.dtype == np.float32 and a.flags.c_contiguous:
        k.shares_into(a, levels, out, sums, np.empty((256, c), dt))
        return sums, out
    sums[:] = a.sum(1, dtype=np.float64)
    inv = np.divide(float(levels), sums.astype(np.float64), out=np.zeros(m), where=sums > 0)
    np.clip(np.floor(a.T * inv + 0.5), 0, levels, out=out, casting="unsafe")
    return sums, out


class StepStats(NamedTuple):
    """What :func:`step_stats` gives. M: rows of Z; N: original points.

    Attributes:
        labels: (M,) int16 argmax of Z (Eq. 16), IGNORE where the row's maximum is not > 0 (or
            the labels given).
        confidence: (M,) float32 max_c Z / sum_c Z, 0 where unlabeled.
        n_changed: labels that differ from the previous ones.
        n_labelled: labelled rows. mean_confidence: their mean confidence (0.0 without any).
        wrong: (N,) bool, annotated points whose label (through ``to_work``) is wrong, or None
            without ground truth.
        counts: (C, C + 1) int64 confusion counts (rows: true class, last column: unlabeled), or
            None without ground truth.
    """

    labels: np.ndarray
    confidence: np.ndarray
    n_changed: int
    n_labelled: int
    mean_confidence: float
    wrong: Optional[np.ndarray]
    counts: Optional[np.ndarray]


def confidence(Z: np.ndarray) -> np.ndarray:
    """(M, C) scores -> (M,) float32 max_c Z / sum_c Z, 0 where the row sums to 0."""
    top = Z.max(1)
    tot = Z.sum(1, dtype=np.float32)
    out = np.zeros(Z.shape[0], np.float32)
    np.divide(top, tot, out=out, where=tot > 0)
    return out


def step_stats(Z: np.ndarray, prev: np.ndarray, gt: Optional[np.ndarray] = None,
               to_work: Optional[np.ndarray] = None, labels: Optional[np.ndarray] = None) -> StepStats:
    """The statistics of one recorded step: Z (M, C) float32 scores, ``prev`` (M,) the previous
    labels, ``gt`` (N,) int ground truth of the original points or None, ``to_work`` (N,) each
    original point's row of Z or None (the rows are the points), ``labels`` (M,) the labels of
    the exact Z when Z is a stored approximation (they replace Z's argmax; confidence still
    comes from Z; numpy). Compiled: one pass over Z and one over the points (~0.5 ms on the
    51k x 20 demo, numpy's ~1.7 ms); the confidence there sums in row order (float32 rounding
    apart, numpy's)."""
    k = _kernels() if labels is None and Z.dtype == np.float32 and Z.ndim == 2 and Z.shape[1] > 0 else None
    if k is not None:
        m, c = Z.shape
        labels = np.empty(m, np.int16)
        conf = np.empty(m, np.float32)
        g = gt if gt is not None else np.zeros(0, np.int16)
        rows = to_work if to_work is not None else np.zeros(0, np.int64)
        wrong = np.empty(len(g), np.bool_)
        counts = np.zeros((c, c + 1), np.int64)
        n_changed, n_lab, conf_sum = k.step_stats(Z, IGNORE, prev, labels, conf, g, rows, wrong, counts)
        mean_conf = float(conf_sum / n_lab) if n_lab else 0.0
        if gt is None:
            wrong = counts = None
        return StepStats(labels, conf, int(n_changed), int(n_lab), mean_conf, wrong, counts)
    given = labels is not None
    if given:
        labels = np.asarray(labels, np.int16)
    else:  # Eq. 16, as method.diffusion.labels_from_scores (backends sit below method/)
        labels = np.argmax(Z, axis=1).astype(np.int16)
        labels[Z.max(1) <= 0] = IGNORE
    conf = confidence(Z)
    labelled = labels != IGNORE
    if given:
        conf[~labelled] = 0.0
    n_changed = int(np.count_nonzero(labels != prev))
    wrong = counts = None
    if gt is not None:
        lab = labels if to_work is None else labels[to_work]
        wrong = (lab != gt) & (gt != IGNORE)
        # as method.metrics.confusion_matrix over Z's C classes
        c = Z.shape[1]
        lab, g = lab.ravel().astype(np.int64), np.asarray(gt).ravel().astype(np.int64)
        valid = g != IGNORE
        p = np.where(lab[valid] == IGNORE, c, lab[valid])
        counts = np.bincount(g[valid] * (c + 1) + p, minlength=c * (c + 1)).reshape(c, c + 1)
    n_lab = int(labelled.sum())
    mean_conf = float(conf[labelled].mean()) if n_lab else 0.0
    return StepStats(labels, conf, n_changed, n_lab, mean_conf, wrong, counts)


WRITE_ROWS = 4096
"""Rows made and written at once (4 MB of float16 at D = 512: the float32 products stay in cache)."""


def write_rows(path: Path, shape: tuple, chunks) -> None:
    """An (N, D) float16 ``.npy`` at ``path`` from ``chunks`` of consecutive rows, appended as they come:
    no (N, D) array, no memory map's page faults."""
    with open(path, "wb") as fh:
        np.lib.format.write_array_header_2_0(fh, {"descr": np.lib.format.dtype_to_descr(np.dtype(np.float16)),
                                                  "fortran_order": False, "shape": tuple(shape)})
        for chunk in chunks:
            fh.write(memoryview(np.ascontiguousarray(chunk, np.float16)))


__all__ = ["transpose_into", "to_float16", "shares", "step_stats", "StepStats", "confidence", "compiled",
           "write_rows", "WRITE_ROWS"]
