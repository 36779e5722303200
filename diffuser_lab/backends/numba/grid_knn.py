"""Compiled (numba) exact K nearest neighbours of a cloud in Morton order (``morton.py``) on a
uniform grid processed cell by cell: the kNN of :func:`diffuser_lab.method.graph.build_graph` (its
Eq. 4 weights are in ``weights.py``).

The points (in Morton order) are binned into cubic cells of ``L`` lattice steps, a little
more than the K-th neighbour distance estimated on a sample, by a stable counting sort; cells
are numbered x-major, so the 3 cells of a z-column of a 3x3x3 block are contiguous. Each occupied
cell copies the candidates of its block once into small float64 arrays (9 contiguous runs) shared
by all its points. Per point, one vectorised loop computes the squared distances to all of them;
a threshold keeping exactly K is then found by counting (a vectorised compare per try, starting
from the previous point's threshold and interpolating the counts), and those K are compacted with
64-bit masks, so no step branches per candidate, and ranked into the row by (squared distance,
index) (:func:`~.cell_search.push`, an insertion sort: at an exact tie the smaller index comes first
and wins the K-th place). The result is exact when the K-th distance is below the point's guaranteed radius (one
cell plus its distance to its own cell's faces); the few other points are searched again in
their 5x5x5 block, then (very rarely) with rings of cells growing until no closer point can
remain (:func:`~.cell_search.ring_knn`, the search the growing map's grid uses too). The rows follow
the rule of :mod:`diffuser_lab.backends.knn` (squared distances ``((dx*dx + dy*dy) + dz*dz)`` in
float64 from the float32 coordinates, no fastmath so no FMA; rows by (d2, index)), so they are the
KD-tree path's rows element for element.
"""
from __future__ import annotations

import numpy as np

from . import NB, n_threads
from . import parts as _parts
from .morton import morton_order

CELL_FACTOR = 1.1
"""Cell side in units of the estimated K-th neighbour distance."""
SAMPLE = 1024
"""Contiguous Morton-sorted points used to estimate the K-th neighbour distance."""

if NB is not None:
    from numba import njit, prange

    from .cell_search import push, ring_knn
    from .morton import lattice

    try:
        from numba.cpython.unsafe.numbers import trailing_zeros  # LLVM's cttz
    except ImportError:  # not public API: a portable count

        @njit(cache=True, inline="always")
        def trailing_zeros(x):
            c = 0
            while x & np.uint64(1) == 0:
                x >>= np.uint64(1)
                c += 1
            return c

    @njit(cache=True, parallel=True, boundscheck=False)
    def _prep_par(points, normals, use_n, order, q, step, L, dims, P4, N4, cellof, b2, cnt, counting):
        """Per sorted point i (in cnt.shape[0] chunks): its coordinates (and normal) in Morton
        order as float64 rows of 4, its cell (linear, x-major) and the squared radius its cell's
        3x3x3 block is sure to cover; cnt[t, c]: points of chunk t in cell c (if ``counting``)."""
        n = order.shape[0]
        nparts = cnt.shape[0]
        h = L * step
        fl = np.float64(L)
        for t in prange(nparts):
            for i in range(t * n // nparts, (t + 1) * n // nparts):
                o = order[i]
                f = L
                lin = 0
                for a in range(3):
                    P4[i, a] = points[o, a]
                    if use_n:
                        N4[i, a] = normals[o, a]
                    qa = np.int64(q[o, a])
                    ca = np.int64(np.floor(qa / fl))  # exact: qa, L < 2^21
                    c0 = ca * L
                    f = min(f, min(qa - c0, c0 + L - qa))
                    lin = lin * dims[a] + ca
                P4[i, 3] = 0.0
                if use_n:
                    N4[i, 3] = 0.0
                cellof[i] = lin
                if counting:
                    cnt[t, lin] += 1
                # one cell plus the distance to the own cell's nearest face, one lattice step of
                # slack for the quantisation; strict (nextafter): a candidate at exactly the
                # bound may have a twin outside the block
                r = h + (f - 1) * step
                b2[i] = np.nextafter(r * r, -np.inf) if r > 0 else -1.0

    @njit(cache=True, boundscheck=False)
    def _offsets(cnt, start):
        """start (ncell + 1,): first position of every cell in cell order; cnt[t, c] becomes the
        first position of chunk t's points of cell c (a stable counting sort)."""
        nparts, ncell = cnt.shape
        pos = 0
        for c in range(ncell):
            start[c] = pos
            for t in range(nparts):
                m = cnt[t, c]
                cnt[t, c] = pos
                pos += m
        start[ncell] = pos

    @njit(cache=True, parallel=True, boundscheck=False)
    def _scatter_par(P4, cellof, b2, fill, X, Y, Z, J, B2):
        """Cell-ordered copies (SoA) of the sorted points, chunk t from fill[t] (:func:`_offsets`)."""
        n = cellof.shape[0]
        nparts = fill.shape[0]
        for t in prange(nparts):
            for i in range(t * n // nparts, (t + 1) * n // nparts):
                c = cellof[i]
                pos = fill[t, c]
                fill[t, c] = pos + 1
                X[pos] = P4[i, 0]
                Y[pos] = P4[i, 1]
                Z[pos] = P4[i, 2]
                J[pos] = i
                B2[pos] = b2[i]

    @njit(cache=True, boundscheck=False, inline="always")
    def _count_le(D, nc, t):
        c = 0
        for a in range(nc):
            if D[a] <= t:
                c += 1
        return c

    @njit(cache=True, boundscheck=False, inline="always")
    def _compact(D, ncp, t, sd, sel):
        """sd/sel[:m] = D and positions of D[:ncp] <= t, in order; returns m. Bit masks of 64
        (a vectorised compare) and a loop over their set bits: no branch per candidate."""
        m = 0
        for b in range(0, ncp, 64):
            msk = np.uint64(0)
            for l in range(64):
                msk |= np.uint64(D[b + l] <= t) << np.uint64(l)
            while msk != 0:
                l = trailing_zeros(msk)
                sd[m] = D[b + l]
                sel[m] = b + l
                m += 1
                msk &= msk - np.uint64(1)
        return m

    @njit(cache=True, boundscheck=False)
    def _narrow(D, nc, k, kmax, tgt, t, t_lo, c_lo, t_hi, c_hi):
        """Shrink the threshold t_hi (count(D[:nc] <= t_hi) = c_hi >= k) until the count is at most
        kmax: interpolate the counts towards tgt (a surface: count ~ d2), bisect when that stalls;
        stops early on exact ties. Returns (t_hi, c_hi)."""
        it = 0
        while c_hi > kmax and it < 16:
            if not (t > t_lo and t < t_hi):
                t = 0.5 * (max(t_lo, 0.0) + t_hi)
                if not (t > t_lo and t < t_hi):
                    break
            c = _count_le(D, nc, t)
            if c >= k:
                t_hi = t
                c_hi = c
            else:
                t_lo = t
                c_lo = c
            if t_lo < 0:
                t = t_hi * tgt / c_hi
            else:
                t = t_lo + (t_hi - t_lo) * (tgt - c_lo) / (c_hi - c_lo)
            it += 1
        return t_hi, c_hi

    @njit(cache=True, boundscheck=False)
    def _threshold(D, nc, k, t, b2):
        """A threshold keeping exactly k of D[:nc] (or, on exact ties, the fewest above k), found
        by counting from the guess t and interpolating the counts (a surface: count ~ d2); never
        above b2. Returns (threshold, count); count < k when fewer than k lie within b2."""
        t = min(t, b2)
        c = _count_le(D, nc, t)
        t_lo = -1.0
        c_lo = 0
        while c < k:  # up to a threshold holding k
            if t >= b2:
                return t, c
            t_lo = t
            c_lo = c
            t = min(t * (k + 0.5) / max(c, 1), b2) if t > 0 else b2
            c = _count_le(D, nc, t)
        return _narrow(D, nc, k, k, k + 0.5, t_lo + (t - t_lo) * (k + 0.5 - c_lo) / (c - c_lo) if t_lo >= 0
                       else t * (k + 0.5) / c, t_lo, c_lo, t, c)

    @njit(cache=True, boundscheck=False)
    def _kth_sample(s, k, stride):
        """Squared distance to the k-th neighbour (self excluded) of every stride-th point of the
        (M, 3) float64 sample, among the sample (about; an estimate for the cell size)."""
        m = s.shape[0]
        kk = min(k, m - 1)
        out = np.empty((m + stride - 1) // stride)
        d = np.empty(m)
        for t in range(out.shape[0]):
            i = t * stride
            dmax = 0.0
            for j in range(m):
                ex = s[j, 0] - s[i, 0]
                ey = s[j, 1] - s[i, 1]
                ez = s[j, 2] - s[i, 2]
                d[j] = ex * ex + ey * ey + ez * ez
                dmax = max(dmax, d[j])
            d[i] = np.inf
            th, c = _narrow(d, m, kk, kk, kk + 0.5, dmax * kk / (m - 1), -1.0, 0, dmax, m - 1)
            dk = 0.0
            for j in range(m):
                if d[j] <= th:
                    dk = max(dk, d[j])
            out[t] = dk
        return out

    @njit(cache=True, boundscheck=False)
    def _gather(X, Y, Z, J, start, dims, cx, cy, cz, R, buf):
        """Copy the points of the cells within R of cell (cx, cy, cz) into the candidate buffers
        (a tuple CX, CY, CZ, CJ, D, sd, sj, sel; grown as needed), padded to a multiple of 64 with
        infinitely far points. Returns (buffers, count, padded count, position of the first point
        of the cell itself)."""
        dx_, dy_, dz_ = dims[0], dims[1], dims[2]
        z0 = max(cz - R, 0)
        z1 = min(cz + R, dz_ - 1) + 1
        x0, x1 = max(cx - R, 0), min(cx + R, dx_ - 1) + 1
        y0, y1 = max(cy - R, 0), min(cy + R, dy_ - 1) + 1
        total = 0
        for ix in range(x0, x1):
            for iy in range(y0, y1):
                base = (ix * dy_ + iy) * dz_
                total += start[base + z1] - start[base + z0]
        ncp = (total + 63) & ~63  # whole blocks of 64 for the bit masks
        CX, CY, CZ, CJ, D, sd, sj, sel = buf
        if ncp > CX.shape[0]:
            cap = 2 * ncp
            CX, CY, CZ, D, sd = np.empty(cap), np.empty(cap), np.empty(cap), np.empty(cap), np.empty(cap)
            CJ, sj, sel = np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap, np.int64)
        # the columns of the block, each a contiguous run of cells along z (x-major cell order)
        nc = 0
        own = 0
        for ix in range(x0, x1):
            for iy in range(y0, y1):
                base = (ix * dy_ + iy) * dz_
                a0 = start[base + z0]
                a1 = start[base + z1]
                if ix == cx and iy == cy:
                    own = nc + start[base + cz] - a0
                for a in range(a0, a1):
                    CX[nc + a - a0] = X[a]
                    CY[nc + a - a0] = Y[a]
                    CZ[nc + a - a0] = Z[a]
                    CJ[nc + a - a0] = J[a]
                nc += a1 - a0
        for a in range(nc, ncp):
            CX[a] = np.inf
            CY[a] = np.inf
            CZ[a] = np.inf
        return (CX, CY, CZ, CJ, D, sd, sj, sel), nc, ncp, own

    @njit(cache=True, boundscheck=False, inline="always")
    def _select(buf, ncp, k, t_hi, out_i, i, bd, bj):
        """Row i = the k nearest candidates (k or more have D <= t_hi), ascending by (d2, index),
        so on exact ties the smallest indices come first and win the k-th place. Returns the
        smallest positive d2 kept (inf if none)."""
        CX, CY, CZ, CJ, D, sd, sj, sel = buf
        m = _compact(D, ncp, t_hi, sd, sel)
        for a in range(m):
            sj[a] = CJ[sel[a]]
        tot = -1
        if m <= 4 * k:
            # each one's rank by d2: counts without branches (vectorised), no sort; the ranks are
            # 0..m-1 (sum m(m-1)/2) unless d2 ties exactly (measured 0.1 us a row of 24)
            tot = 0
            for a in range(m):
                da = sd[a]
                r = 0
                for b in range(m):
                    r += sd[b] < da
                tot += r
                if r < k:
                    bd[r] = da
                    bj[r] = sj[a]
        if tot != m * (m - 1) // 2:  # exact ties (or very many candidates): by (d2, index) in a K-buffer
            cnt = 0
            for a in range(m):
                cnt = push(bd, bj, cnt, k, sd[a], sj[a])
        dmin = np.inf
        for s in range(k):
            out_i[i, s] = bj[s]
            if bd[s] > 0 and dmin == np.inf:
                dmin = bd[s]
        return dmin

    @njit(cache=True, boundscheck=False)
    def _new_buf(cap):
        """Candidate buffers of a block (see :func:`_gather`) for cap candidates."""
        return (np.empty(cap), np.empty(cap), np.empty(cap), np.empty(cap, np.int64), np.empty(cap), np.empty(cap),
                np.empty(cap, np.int64), np.empty(cap, np.int64))

    @njit(cache=True, boundscheck=False)
    def _knn_cells(X, Y, Z, J, B2, start, occ, dims, origin, step, L, k, t_est, c_lo, c_hi, out_i, d0):
        """Rows of the points of cells occ[c_lo:c_hi] from their 3x3x3 blocks; a point whose
        k-th neighbour may lie outside that block is searched in its 5x5x5 block, then in rings
        of cells (:func:`_far_point`)."""
        dy_, dz_ = dims[1], dims[2]
        buf = _new_buf(256)
        far = _new_buf(1024)
        bd = np.empty(k)
        bj = np.empty(k, np.int64)
        for oc in range(c_lo, c_hi):
            lin = occ[oc]
            buf, nc, ncp, own = _gather(X, Y, Z, J, start, dims, lin // (dy_ * dz_), (lin // dz_) % dy_, lin % dz_,
                                        1, buf)
            CX, CY, CZ, CJ, D, sd, sj, sel = buf
            s0 = start[lin]
            guess = t_est
            for p in range(s0, start[lin + 1]):
                i = J[p]
                px, py, pz = X[p], Y[p], Z[p]
                for a in range(ncp):
                    ex = CX[a] - px
                    ey = CY[a] - py
                    ez = CZ[a] - pz
                    D[a] = ex * ex + ey * ey + ez * ez
                D[own + p - s0] = np.inf  # the point itself
                # the threshold keeping exactly k, from the previous point's (the sample's
                # estimate for the first of a cell), within the block's guaranteed radius
                t, c = _threshold(D, ncp, k, guess, B2[p])
                if c < k:  # the k-th neighbour may lie outside the block
                    far = _far_point(i, px, py, pz, X, Y, Z, J, start, dims, origin, step, L, k, t_est, far, bd, bj,
                                     out_i, d0)
                    continue
                d0[i] = _select(buf, ncp, k, t, out_i, i, bd, bj)
                guess = t

    @njit(cache=True, parallel=True, boundscheck=False)
    def _knn_cells_par(X, Y, Z, J, B2, start, occ, dims, origin, step, L, k, t_est, out_i, d0, bounds):
        for t in prange(bounds.shape[0] - 1):
            _knn_cells(X, Y, Z, J, B2, start, occ, dims, origin, step, L, k, t_est, bounds[t], bounds[t + 1], out_i,
                       d0)

    @njit(cache=True, boundscheck=False)
    def _far_point(i, px, py, pz, X, Y, Z, J, start, dims, origin, step, L, k, t_est, buf, bd, bj, out_i, d0):
        """Row i (at px, py, pz) from the 5x5x5 cells around its own, or, where the k-th neighbour
        may lie outside those too, from rings of cells (:func:`~.cell_search.ring_knn`; bd/bj: its
        (k,) buffers). Returns the buffers."""
        qx = lattice(px, origin[0], step)
        qy = lattice(py, origin[1], step)
        qz = lattice(pz, origin[2], step)
        f = L
        for qa in (qx, qy, qz):
            c0 = (qa // L) * L
            f = min(f, min(qa - c0, c0 + L - qa))
        bound = 2 * L * step + (f - 1) * step
        b2 = np.nextafter(bound * bound, -np.inf) if bound > 0 else -1.0
        buf, nc, ncp, own = _gather(X, Y, Z, J, start, dims, qx // L, qy // L, qz // L, 2, buf)
        CX, CY, CZ, CJ, D, sd, sj, sel = buf
        for a in range(ncp):
            ex = CX[a] - px
            ey = CY[a] - py
            ez = CZ[a] - pz
            D[a] = ex * ex + ey * ey + ez * ez
        for a in range(nc):  # the point itself
            if CJ[a] == i:
                D[a] = np.inf
        t, c = _threshold(D, ncp, k, t_est, b2)
        if c >= k:
            d0[i] = _select(buf, ncp, k, t, out_i, i, bd, bj)
            return buf
        # the point's distances to its cell's faces, one lattice step less (its position within
        # its lattice step is unknown)
        cx, cy, cz = qx // L, qy // L, qz // L
        flo = ((qx - cx * L - 1) * step, (qy - cy * L - 1) * step, (qz - cz * L - 1) * step)
        fhi = ((cx * L + L - qx - 1) * step, (cy * L + L - qy - 1) * step, (cz * L + L - qz - 1) * step)
        no_table = np.empty(0, np.int64)
        ring_knn(i, px, py, pz, (cx, cy, cz), flo, fhi, L * step, np.zeros(3, np.int64), dims - 1, dims, no_table,
                 no_table, 0, start, start[1:], X, Y, Z, J, k, bd, bj)
        dmin = np.inf
        for e in range(k):
            out_i[i, e] = bj[e]
            if bd[e] > 0 and bd[e] < dmin:
                dmin = bd[e]
        d0[i] = dmin
        return buf


def sorted_knn(points: np.ndarray, normals: np.ndarray | None, k: int):
    """Morton order and exact K nearest neighbours (self excluded, rows by (d2, index)).

    Args:
        points: (N, 3) float32 world points, metres; normals: (N, 3) float32 or None.
    Returns:
        order (N,) int64 (as :func:`morton_order`); P4 (N, 4) float64 ``points[order]`` padded
        with a zero column, metres; N4 likewise the normals (None without normals); and either
        (idx (N, K) int32 neighbours as sorted indices, each row ascending by (d2, index) (the
        rule of :mod:`diffuser_lab.backends.knn`), d0 (N,) float64 the smallest positive squared distance per row in m^2, inf if none) or
        None when the cloud is too sparse for a dense grid (the caller then uses a KD-tree).
    """
    points = np.ascontiguousarray(points, np.float32)
    n = points.shape[0]
    order, origin, step, qmax, q = morton_order(points)
    use_n = normals is not None
    nrm = np.ascontiguousarray(normals, np.float32) if use_n else np.zeros((1, 3), np.float32)
    # cell side from the K-th neighbour distance of a contiguous, so spatially compact, run
    m = min(n, SAMPLE)
    lo = (n - m) // 2
    sample = points[order[lo : lo + m]].astype(np.float64)
    r_k = float(np.sqrt(np.median(_kth_sample(sample, k, max(1, m // 32)))))
    L = int(max(1, np.ceil(CELL_FACTOR * r_k / step))) if r_k > 0 else 0
    dims = np.asarray(qmax, np.int64) // max(L, 1) + 1
    dense = L > 0 and float(np.prod(dims.astype(np.float64))) <= max(8.0 * n, 2.0**22)
    ncell = int(np.prod(dims)) if dense else 1
    P4 = np.empty((n, 4))
    N4 = np.empty((n, 4)) if use_n else np.empty((1, 4))
    cellof = np.empty(n, np.int64)
    b2 = np.empty(n)
    # one chunk per thread for the counting sort into cells (a count table each)
    nt = max(1, min(n_threads(), n // 4096 + 1))
    cnt = np.zeros((nt, ncell) if dense else (nt, 1), np.int64)
    _prep_par(points, nrm, use_n, order, q, step, max(L, 1), dims if dense else np.ones(3, np.int64),
              P4, N4, cellof, b2, cnt, dense)
    N4 = N4 if use_n else None
    if not dense:
        return order, P4, N4, None
    start = np.empty(ncell + 1, np.int64)
    _offsets(cnt, start)
    X, Y, Z, B2 = (np.empty(n) for _ in range(4))
    J = np.empty(n, np.int64)
    _scatter_par(P4, cellof, b2, cnt, X, Y, Z, J, B2)
    occ = np.flatnonzero(start[1:] != start[:-1])
    parts = _parts(n)
    out_i = np.empty((n, k), np.int32)
    d0 = np.empty(n)
    bounds = np.searchsorted(start[occ], np.linspace(0, n, parts + 1)).astype(np.int64)
    bounds[-1] = len(occ)
    _knn_cells_par(X, Y, Z, J, B2, start, occ, dims, origin, step, L, k, r_k * r_k, out_i, d0, bounds)
    return order, P4, N4, (out_i, d0)
