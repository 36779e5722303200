"""Z states encoded for run.mcap: a compiled transpose (class-major storage) and a float32 ->
float16 conversion bit for bit as numpy's (whose own conversion of values that become float16
subnormals takes a slow path)."""
from __future__ import annotations

import numpy as np

from . import NB, available

if NB is not None:
    from numba import njit

    @njit(cache=True, nogil=True, boundscheck=False)
    def _transpose_f32(a, out):
        """out[c, i] = a[i, c]: reads row by row, C sequential write streams."""
        m, c = a.shape
        for i in range(m):
            for j in range(c):
                out[j, i] = a[i, j]

    @njit(cache=True, nogil=True, boundscheck=False)
    def _f32_to_f16_bits(a, out):
        """IEEE float32 bits -> float16 bits, rounding to nearest, ties to even (as numpy)."""
        for i in range(a.shape[0]):
            x = np.uint32(a[i])
            sign = (x >> np.uint32(16)) & np.uint32(0x8000)
            exp = np.int64((x >> np.uint32(23)) & np.uint32(0xFF))
            man = x & np.uint32(0x7FFFFF)
            e = exp - 112  # float16 biased exponent
            if exp == 255:  # inf, nan
                r = np.uint32(0x7C00) | (np.uint32(0x200) if man else np.uint32(0))
            elif e >= 31:  # overflow
                r = np.uint32(0x7C00)
            elif e <= 0:  # float16 subnormal (or zero): the nearest multiple of 2^-24
                if e < -10:
                    r = np.uint32(0)
                else:
                    m = man | np.uint32(0x800000)
                    shift = np.uint32(14 - e)
                    half = np.uint32(1) << (shift - np.uint32(1))
                    r = m >> shift
                    rem = m & ((np.uint32(1) << shift) - np.uint32(1))
                    if rem > half or (rem == half and (r & np.uint32(1))):
                        r += np.uint32(1)
            else:
                r = (np.uint32(e) << np.uint32(10)) | (man >> np.uint32(13))
                rem = man & np.uint32(0x1FFF)
                if rem > np.uint32(0x1000) or (rem == np.uint32(0x1000) and (r & np.uint32(1))):
                    r += np.uint32(1)  # a carry into the exponent is right (up to inf)
            out[i] = np.uint16(sign | r)


def transpose_into(a: np.ndarray, out: np.ndarray) -> None:
    """out[...] = a.T for a 2-D ``a`` (M, C) and a C-contiguous ``out`` (C, M) of the same dtype:
    compiled for float32 (4x numpy's strided copy at 51k x 20), numpy otherwise."""
    if available() and a.dtype == np.float32 and out.dtype == np.float32 and a.flags.c_contiguous:
        _transpose_f32(a, out)
    else:
        np.copyto(out, a.T)


def to_float16(a: np.ndarray) -> np.ndarray | None:
    """``a.astype("<f2")`` for C-contiguous float32 ``a``, bit for bit, compiled (numpy takes a
    slow path for values that become float16 subnormals: ~50 ms on a 1M-value Z state); None
    without numba."""
    if not available() or a.dtype != np.float32 or not a.flags.c_contiguous:
        return None
    out = np.empty(a.shape, "<f2")
    _f32_to_f16_bits(a.reshape(-1).view(np.uint32), out.reshape(-1).view(np.uint16))
    return out


if NB is not None:
    @njit(cache=True, nogil=True, boundscheck=False)
    def _shares_into(a, levels, out, sums, tmp):
        """sums[i] = float32(sum_c a[i, c]); out[c, i] = round(a[i, c] / sums[i] * levels).
        Rows go through ``tmp`` (B, C) in blocks, then out block-transposed: writing the
        class-major output directly, a byte at a time into C streams, is 5x slower. Float32
        arithmetic: its rounding (~1e-7 of the row sum) is far below a step."""
        m, c = a.shape
        nb = tmp.shape[0]
        lv = np.float32(levels)
        for i0 in range(0, m, nb):
            i1 = min(i0 + nb, m)
            for i in range(i0, i1):
                acc = 0.0
                for j in range(c):
                    acc += a[i, j]
                s = np.float32(acc)
                sums[i] = s
                inv = lv / s if s > 0 else np.float32(0.0)
                for j in range(c):
                    # a <= s, so v <= levels + 0.5 (float32 rounding stays below levels + 1); v >= 0
                    # (or 0.5): the cast's truncation rounds
                    tmp[i - i0, j] = a[i, j] * inv + np.float32(0.5)
            for j in range(c):
                for i in range(i0, i1):
                    out[j, i] = tmp[i - i0, j]


def shares(a: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray]:
    """(M, C) float32 Z >= 0 -> (row sums (M,) float32, shares (C, M) uint8 or uint16): share
    q[c, i] = round(Z[i, c] / sum_c Z[i, c] * (2^bits - 1)), class-major. Compiled where numba is
    (one pass, ~1 ms on the 51k x 20 demo, ~11 ms at 566k), numpy otherwise; the two agree up to float rounding."""
    levels = (1 << bits) - 1
    dt = np.uint8 if bits <= 8 else np.uint16
    m, c = a.shape
    out = np.empty((c, m), dt)
    sums = np.empty(m, np.float32)
    if available() and a.dtype == np.float32 and a.flags.c_contiguous:
        _shares_into(a, levels, out, sums, np.empty((256, c), dt))
        return sums, out
    sums[:] = a.sum(1, dtype=np.float64)
    inv = np.divide(float(levels), sums.astype(np.float64), out=np.zeros(m), where=sums > 0)
    np.clip(np.floor(a.T * inv + 0.5), 0, levels, out=out, casting="unsafe")
    return sums, out
