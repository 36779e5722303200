"""The most confident view's score of feature pixels (:func:`diffuser_lab.method.features.top_probability`)
in one compiled pass per row: each class's best query, the row sum in NumPy's order and the top
class's share, bit for bit as the numpy twin (float32 maxima, sums and one division: no
reassociation, no fastmath). Compiled on first use (cached on disk; not part of the warm run)."""
from __future__ import annotations

import numpy as np

from . import NB

if NB is not None:
    from numba import njit

    @njit(cache=True, boundscheck=False)
    def _top_probability(e, to_class, num_classes, out):
        m, q = e.shape
        s = np.empty(num_classes, np.float32)
        r = np.empty(8, np.float32)
        for i in range(m):
            for c in range(num_classes):
                s[c] = np.float32(0)
            for j in range(q):
                c = to_class[j]
                if c >= 0 and c < num_classes:
                    v = e[i, j]
                    if v > s[c]:  # NaN (a NaN cosine: no feature) counts as 0, as nan_to_num's -inf does
                        s[c] = v
            # NumPy's pairwise_sum of a row of num_classes <= 128 numbers
            if num_classes < 8:
                total = s[0]
                for c in range(1, num_classes):
                    total = np.float32(total + s[c])
            else:
                for k in range(8):
                    r[k] = s[k]
                k = 8
                while k < num_classes - num_classes % 8:
                    for j in range(8):
                        r[j] = np.float32(r[j] + s[k + j])
                    k += 8
                a = np.float32(np.float32(r[0] + r[1]) + np.float32(r[2] + r[3]))
                b = np.float32(np.float32(r[4] + r[5]) + np.float32(r[6] + r[7]))
                total = np.float32(a + b)
                while k < num_classes:
                    total = np.float32(total + s[k])
                    k += 1
            top = s[0]
            for c in range(1, num_classes):
                if s[c] > top:
                    top = s[c]
            out[i] = np.float32(top / total) if total > 0 else np.float32(0)


def top_probability(e: np.ndarray, to_class: np.ndarray, num_classes: int) -> np.ndarray:
    """(M, Q) float32 C-contiguous ``exp((cos - 1) / T)`` (NaN where a cosine is NaN: taken as 0)
    -> (M,) float32, the numpy twin's result."""
    out = np.empty(e.shape[0], np.float32)
    _top_probability(e, np.ascontiguousarray(to_class, np.int64), int(num_classes), out)
    return out


if NB is not None:

    @njit(cache=True, boundscheck=False)
    def _sample_add(coords, gram, valid, h, w, sy, sx, rows, cols, idx, mass, links, f, ok):
        m = rows.shape[0]
        width = coords.shape[1]
        one, two, zero = np.float32(1), np.float32(2), np.float32(0)
        for n in range(m):
            y = min(max((rows[n] + 0.5) * sy - 0.5, 0.0), h - 1.0)
            x = min(max((cols[n] + 0.5) * sx - 0.5, 0.0), w - 1.0)
            y0, x0 = int(np.floor(y)), int(np.floor(x))
            y1, x1 = min(y0 + 1, h - 1), min(x0 + 1, w - 1)
            wy, wx = np.float32(y - y0), np.float32(x - x0)
            c00, c01, c10, c11 = y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1
            a = np.float32((one - wy) * (one - wx)) if valid[c00] else zero
            b = np.float32((one - wy) * wx) if valid[c01] else zero
            c = np.float32(wy * (one - wx)) if valid[c10] else zero
            d = np.float32(wy * wx) if valid[c11] else zero
            n2 = np.float32(a * a) * gram[0, c00]
            n2 = np.float32(n2 + np.float32(np.float32(b * b) * gram[0, c01]))
            n2 = np.float32(n2 + np.float32(np.float32(c * c) * gram[0, c10]))
            n2 = np.float32(n2 + np.float32(np.float32(d * d) * gram[0, c11]))
            inner = np.float32(np.float32(a * b) * gram[1, c00])
            inner = np.float32(inner + np.float32(np.float32(c * d) * gram[1, c10]))
            inner = np.float32(inner + np.float32(np.float32(a * c) * gram[2, c00]))
            inner = np.float32(inner + np.float32(np.float32(b * d) * gram[2, c01]))
            inner = np.float32(inner + np.float32(np.float32(a * d) * gram[3, c00]))
            inner = np.float32(inner + np.float32(np.float32(b * c) * gram[4, c00]))
            n2 = np.float32(n2 + np.float32(two * inner))
            good = np.float32(np.float32(np.float32(a + b) + c) + d) > zero and n2 > zero and np.isfinite(n2)
            inv = zero
            if good:
                inv = np.float32(1.0 / np.float64(np.float32(np.sqrt(np.float64(n2)))))
            ok[n] = good
            p = idx[n]
            for j in range(width):
                v = np.float32(coords[c00, j] * a)
                v = np.float32(v + np.float32(coords[c01, j] * b))
                v = np.float32(v + np.float32(coords[c10, j] * c))
                v = np.float32(v + np.float32(coords[c11, j] * d))
                v = np.float32(v * inv)
                f[n, j] = v
                if good:
                    mass[p, j] = np.float32(mass[p, j] + v)
            if good:
                links[p] += 1


def sample_add(coords, gram, valid, fshape, shape, rows, cols, idx, mass, links):
    """:func:`diffuser_lab.method.evidence.sample_basis` of (M,) pixels and the adds of the usable
    ones to ``mass`` (N, k + s) float32 and ``links`` (N,) rows ``idx`` (each once), in one pass:
    the same float32 operations in the same order (bit for bit). Returns (M, k + s) float32 the
    unit samples' coordinates and (M,) bool usable."""
    h, w = fshape
    H, W = shape
    m = rows.shape[0]
    f = np.empty((m, coords.shape[1]), np.float32)
    ok = np.empty(m, np.bool_)
    _sample_add(coords, gram, valid.reshape(-1), int(h), int(w), h / H, w / W, np.ascontiguousarray(rows, np.int64),
                np.ascontiguousarray(cols, np.int64), np.ascontiguousarray(idx, np.int64), mass, links, f, ok)
    return f, ok
