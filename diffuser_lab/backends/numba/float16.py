"""The recorders' compiled kernels (called through :mod:`diffuser_lab.backends.records`, which
holds their numpy twins and picks one): Z states encoded for run.mcap (a transpose to class-major
storage, a float32 -> float16 conversion bit for bit as numpy's, whose own conversion of values
that become float16 subnormals takes a slow path, and the q8/q16 shares) and the statistics of a
recorded diffusion step (labels, confidence, changes, confusion counts in one pass)."""
from __future__ import annotations

import numpy as np

from . import NB

if NB is not None:
    from numba import njit

    @njit(cache=True, nogil=True, boundscheck=False)
    def transpose_f32(a, out):
        """out[c, i] = a[i, c]: reads row by row, C sequential write streams."""
        m, c = a.shape
        for i in range(m):
            for j in range(c):
                out[j, i] = a[i, j]

    @njit(cache=True, nogil=True, boundscheck=False)
    def f32_to_f16_bits(a, out):
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

    @njit(cache=True, nogil=True, boundscheck=False)
    def shares_into(a, levels, out, sums, tmp):
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

    @njit(cache=True, nogil=True, boundscheck=False)
    def step_stats(Z, ignore, prev, labels, conf, gt, to_work, wrong, counts):
        """One recorded step in one pass over Z and one over the original points: labels (first
        maximum, ``ignore`` where the row's maximum is not > 0), confidence, labels changed since
        ``prev``, and with ground truth ``gt`` (empty: none) the confusion counts and the wrong
        points. Returns (changed, labelled, sum of the labelled rows' confidence)."""
        m, c = Z.shape
        changed = 0
        n_lab = 0
        conf_sum = 0.0
        for i in range(m):
            best = Z[i, 0]
            arg = 0
            tot = np.float32(0.0)
            for j in range(c):
                v = Z[i, j]
                tot += v
                if v > best:  # first maximum, as np.argmax
                    best = v
                    arg = j
            if best > 0:
                labels[i] = arg
                conf[i] = best / tot if tot > 0 else np.float32(0.0)
                n_lab += 1
                conf_sum += conf[i]
            else:
                labels[i] = ignore
                conf[i] = 0.0
            if labels[i] != prev[i]:
                changed += 1
        for i in range(gt.shape[0]):  # (N,) original points; empty without ground truth
            lab = labels[to_work[i]] if to_work.shape[0] else labels[i]
            g = gt[i]
            if g < 0 or g >= c:  # IGNORE (or no class of Z: never indexes out of range)
                wrong[i] = False
                continue
            wrong[i] = lab != g
            counts[g, c if lab == ignore else lab] += 1
        return changed, n_lab, conf_sum
