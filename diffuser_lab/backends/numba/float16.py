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
