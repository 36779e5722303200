"""Compiled (numba) pieces of :mod:`diffuser_lab.method.growing`: the voxel map's hash insert and
the incremental kNN graph's hash grid and queries.

Hash tables: open addressing with linear probing on non-negative int64 keys (-1 = empty slot),
Fibonacci hashing, at most half full (the caller grows them first, :func:`rehash`).

Graph grid: cubic cells of ``h`` metres (a high quantile of the rows' K-th neighbour distance),
numbered once in a hash table of their packed coordinates and linked to their 26 neighbours
(``cell_nb``), so a query reads no table. Each cell's points are one run of a pool (float64
coordinates and indices, in index order, so an add's points are each run's tail) with room to
grow; a full run moves to the pool's end with twice the room (amortised O(new points) per add).
A query scans its cell's 3x3x3 block keeping the K best by (squared distance, index) under a
threshold guessed from the previous row, and is exact when the K-th distance is within the
block's guaranteed radius (``h`` + the point's distance to its cell's faces); the other points are
searched again ring by ring (:func:`query_rings`) until no closer point can remain. Squared
distances are float64 from the float32 coordinates, as in :func:`~diffuser_lab.method.graph.build_graph`.
"""
from __future__ import annotations

import numpy as np

from . import NB

OFF = 1 << 20
"""Offset of signed cell / voxel coordinates into 21 unsigned bits."""

if NB is not None:
    from numba import njit, prange

    from diffuser_lab.data.geometry import _spread_bits
    from .knn import exp_split  # Eq. 4 weights bit for bit as the batch graph

    _spread = njit(cache=True, boundscheck=False, inline="always")(_spread_bits)

    @njit(cache=True, boundscheck=False, inline="always")
    def _slot(key, bits):
        return np.int64((np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(64 - bits))

    @njit(cache=True, boundscheck=False, inline="always")
    def _find(hk, bits, key):
        """Slot of ``key`` or of the empty slot where it would go."""
        mask = (np.int64(1) << bits) - 1
        s = _slot(key, bits)
        while hk[s] != key and hk[s] != -1:
            s = (s + 1) & mask
        return s

    @njit(cache=True, boundscheck=False)
    def rehash(hk, hv, nk, nv, bits):
        """Copy the entries of table (hk, hv) into the empty table (nk, nv) of 2**bits slots."""
        for s in range(hk.shape[0]):
            if hk[s] != -1:
                t = _find(nk, bits, hk[s])
                nk[t] = hk[s]
                nv[t] = hv[s]

    @njit(cache=True, boundscheck=False, inline="always")
    def _coord(v, size):
        a = np.floor(np.float64(v) / size)
        a = min(max(a, -float(OFF)), float(OFF - 1))  # NaN -> -OFF (np.clip's NaN stays; never here)
        return np.int64(a) + OFF

    @njit(cache=True, boundscheck=False)
    def voxel_insert(points, normals, use_n, size, hk, hv, bits, n_map, keys, slots, sums, nsums, counts, first):
        """One frame into the voxel map: points in occupied voxels (value < n_map) are dropped;
        the others are summed per new voxel, numbered n_map + t in order of first appearance.

        Returns t, the number of new voxels: keys[:t] their Morton keys, slots[:t] their table
        slots, sums/nsums[:t] (float64) sums of points / normals, counts[:t], first[:t] the
        index of their first point."""
        t = 0
        last = np.int64(-1)
        s = 0
        for i in range(points.shape[0]):
            x = _coord(points[i, 0], size)
            y = _coord(points[i, 1], size)
            z = _coord(points[i, 2], size)
            key = np.int64(_spread(np.uint64(x)) | (_spread(np.uint64(y)) << np.uint64(1))
                           | (_spread(np.uint64(z)) << np.uint64(2)))
            if key != last:  # neighbouring pixels mostly share a voxel: no probe
                s = _find(hk, bits, key)
                last = key
            if hk[s] == -1:
                hk[s] = key
                hv[s] = n_map + t
                keys[t] = key
                slots[t] = s
                first[t] = i
                counts[t] = 0
                for a in range(3):
                    sums[t, a] = 0.0
                    nsums[t, a] = 0.0
                t += 1
            v = hv[s] - n_map
            if v < 0:
                continue
            counts[v] += 1
            for a in range(3):
                sums[v, a] += np.float64(points[i, a])
            if use_n:
                for a in range(3):
                    nsums[v, a] += np.float64(normals[i, a])
        return t

    @njit(cache=True, boundscheck=False)
    def voxel_occupied(points, size, hk, bits, out):
        """out[i]: point i's voxel is in the table (a map point holds it)."""
        last = np.int64(-1)
        hit = False
        for i in range(points.shape[0]):
            x = _coord(points[i, 0], size)
            y = _coord(points[i, 1], size)
            z = _coord(points[i, 2], size)
            key = np.int64(_spread(np.uint64(x)) | (_spread(np.uint64(y)) << np.uint64(1))
                           | (_spread(np.uint64(z)) << np.uint64(2)))
            if key != last:
                hit = hk[_find(hk, bits, key)] == key
                last = key
            out[i] = hit

    # --- graph grid ---

    @njit(cache=True, boundscheck=False, inline="always")
    def _ckey(cx, cy, cz):
        return (cx << 42) | (cy << 21) | cz

    @njit(cache=True, boundscheck=False)
    def grid_assign(P, lo, hi, h, hk, hv, bits, cell_c, cell_nb, ncells, cell_of):
        """Cells of points lo..hi-1 (new cells numbered from ncells on, linked both ways with their
        existing neighbours in cell_nb (ncells, 27): the id of the cell at offset
        (ax, ay, az) in -1..1 at column (ax+1)*9 + (ay+1)*3 + az+1, -1 if none); returns the new ncells."""
        last = np.int64(-1)
        cid = 0
        for i in range(lo, hi):
            cx = _coord(P[i, 0], h)
            cy = _coord(P[i, 1], h)
            cz = _coord(P[i, 2], h)
            key = _ckey(cx, cy, cz)
            if key != last:
                last = key
                s = _find(hk, bits, key)
                if hk[s] == -1:
                    hk[s] = key
                    hv[s] = ncells
                    cell_c[ncells, 0] = cx
                    cell_c[ncells, 1] = cy
                    cell_c[ncells, 2] = cz
                    for o in range(27):
                        ax, ay, az = o // 9 - 1, (o // 3) % 3 - 1, o % 3 - 1
                        t = _find(hk, bits, _ckey(cx + ax, cy + ay, cz + az))
                        d = hv[t] if hk[t] != -1 else -1
                        cell_nb[ncells, o] = d
                        if d >= 0:
                            cell_nb[d, 26 - o] = ncells
                    ncells += 1
                cid = hv[s]
            cell_of[i] = cid
        return ncells

    @njit(cache=True, boundscheck=False)
    def grid_append(lo, hi, P, cell_of, cstart, cend, climit, fresh, X, Y, Z, J, pend):
        """Append points lo..hi-1 to their cells' runs in the pool X/Y/Z (float64 coordinates), J
        (indices): cell c holds cstart[c]..cend[c]-1 with room up to climit[c]; a full run moves to
        the pool's end with twice the room (fresh[c], the start of this add's points in the run,
        moves with it). Returns (the first point not appended: the pool is full, pend)."""
        for i in range(lo, hi):
            c = cell_of[i]
            if cend[c] == climit[c]:
                ln = cend[c] - cstart[c]
                cap = max(4, 2 * ln)
                if pend + cap > X.shape[0]:
                    return i, pend
                for e in range(ln):
                    X[pend + e] = X[cstart[c] + e]
                    Y[pend + e] = Y[cstart[c] + e]
                    Z[pend + e] = Z[cstart[c] + e]
                    J[pend + e] = J[cstart[c] + e]
                fresh[c] = pend + fresh[c] - cstart[c]
                cstart[c] = pend
                cend[c] = pend + ln
                climit[c] = pend + cap
                pend += cap
            p = cend[c]
            X[p] = np.float64(P[i, 0])
            Y[p] = np.float64(P[i, 1])
            Z[p] = np.float64(P[i, 2])
            J[p] = i
            cend[c] = p + 1
        return hi, pend

    @njit(cache=True, boundscheck=False)
    def pool_compact(ncells, cstart, cend, climit, fresh, X, Y, Z, J, nX, nY, nZ, nJ):
        """Copy every run into the new pool nX/nY/nZ/nJ with room for twice its length; returns pend."""
        pend = 0
        for c in range(ncells):
            ln = cend[c] - cstart[c]
            for e in range(ln):
                nX[pend + e] = X[cstart[c] + e]
                nY[pend + e] = Y[cstart[c] + e]
                nZ[pend + e] = Z[cstart[c] + e]
                nJ[pend + e] = J[cstart[c] + e]
            fresh[c] = pend + fresh[c] - cstart[c]
            cstart[c] = pend
            cend[c] = pend + ln
            climit[c] = pend + max(4, 2 * ln)
            pend = climit[c]
        return pend

    @njit(cache=True, boundscheck=False, inline="always")
    def _store_row(i, bd, bj, k, nbr, d2, d0, kth2):
        """Row i of the graph from the ascending K-buffer bd/bj: neighbours, squared distances, the
        nearest distinct one (d0, inf if none) and the K-th (kth2)."""
        dz0 = np.inf
        for e in range(k):
            nbr[i, e] = bj[e]
            d2[i, e] = bd[e]
            if bd[e] > 0.0 and dz0 == np.inf:
                dz0 = bd[e]
        d0[i] = dz0
        kth2[i] = bd[k - 1]

    @njit(cache=True, boundscheck=False, inline="always")
    def _push(bd, bj, cnt, k, d, j):
        """Insert (d, j) into the ascending K-buffer bd/bj holding cnt entries; returns the new cnt."""
        if cnt == k:
            if d > bd[k - 1] or (d == bd[k - 1] and j > bj[k - 1]):
                return cnt
            p = k - 1
        else:
            p = cnt
            cnt += 1
        while p > 0 and (bd[p - 1] > d or (bd[p - 1] == d and bj[p - 1] > j)):
            bd[p] = bd[p - 1]
            bj[p] = bj[p - 1]
            p -= 1
        bd[p] = d
        bj[p] = j
        return cnt

    @njit(cache=True, boundscheck=False, inline="always")
    def _face(v, c, h):
        """Distance of coordinate v to the faces of its cell c (offset coordinate)."""
        lo = np.float64(c - OFF) * h
        return min(v - lo, lo + h - v)

    @njit(cache=True, parallel=True, boundscheck=False)
    def query_rows(Q, P, h, cell_c, cell_of, cell_nb, cstart, cend, X, Y, Z, J, kth2, n_old, mark, k, nbr, d2, d0,
                   fail, aff, nparts):
        """Rows of the queried points Q (in nparts parallel chunks; sorted by cell for locality)
        from their cell's 3x3x3 block: nbr/d2 sorted by (d2, index), d0 the smallest positive d2
        (inf if none), kth2 the K-th d2; fail[i] = 1 where the K-th distance exceeds the block's
        guaranteed radius (search again with rings). With ``mark``, every old point (index < n_old)
        within ``h`` of a queried point and closer to it than its own K-th neighbour (kth2, read
        for the old points) is flagged in aff (the same value from any thread)."""
        nq = Q.shape[0]
        h2 = h * h
        for t in prange(nparts):
            bd = np.empty(k)
            bj = np.empty(k, np.int64)
            thr = 0.5 * h2  # then guessed from the previous point (the rows are sorted by cell)
            for qi in range(t * nq // nparts, (t + 1) * nq // nparts):
                i = Q[qi]
                c = cell_of[i]
                px = np.float64(P[i, 0])
                py = np.float64(P[i, 1])
                pz = np.float64(P[i, 2])
                mk = mark
                while True:
                    # K best by (d2, index), self excluded, among the candidates within thr
                    cnt = 0
                    lim = thr
                    for o in range(27):
                        cc = cell_nb[c, o]
                        if cc < 0:
                            continue
                        for p in range(cstart[cc], cend[cc]):
                            ex = X[p] - px
                            ey = Y[p] - py
                            ez = Z[p] - pz
                            d = ex * ex + ey * ey + ez * ez
                            j = J[p]
                            if mk and d < h2 and j < n_old and d < kth2[j]:
                                aff[j] = 1
                            if d <= lim and j != i:
                                cnt = _push(bd, bj, cnt, k, d, j)
                                if cnt == k:
                                    lim = min(lim, bd[k - 1])
                    if cnt == k or thr == np.inf:
                        break
                    thr = thr * 4.0 if thr < 16.0 * h2 else np.inf  # too few within the guess: wider
                    mk = False  # flags are set already
                for e in range(cnt, k):  # fewer than K candidates: fail below
                    bd[e] = np.inf
                    bj[e] = i
                cx, cy, cz = cell_c[c, 0], cell_c[c, 1], cell_c[c, 2]
                fd = min(_face(px, cx, h), _face(py, cy, h), _face(pz, cz, h)) + h
                fail[i] = 1 if (cnt < k or bd[k - 1] > fd * fd) else 0
                thr = bd[k - 1] * 1.5 if cnt == k else 0.5 * h2
                _store_row(i, bd, bj, k, nbr, d2, d0, kth2)

    @njit(cache=True, parallel=True, boundscheck=False)
    def merge_rows(Q, P, cell_of, cell_nb, cend, fresh, X, Y, Z, J, k, nbr, d2, d0, kth2, nparts):
        """Old rows Q (each with its K-th distance within the cell side; nparts parallel chunks)
        updated with the new points of their cell's 3x3x3 block (the runs' tails
        fresh[c]..cend[c]-1): the K best of the current row and those, by (d2, index)."""
        nq = Q.shape[0]
        for t in prange(nparts):
            bd = np.empty(k)
            bj = np.empty(k, np.int64)
            for qi in range(t * nq // nparts, (t + 1) * nq // nparts):
                i = Q[qi]
                c = cell_of[i]
                px = np.float64(P[i, 0])
                py = np.float64(P[i, 1])
                pz = np.float64(P[i, 2])
                for e in range(k):
                    bd[e] = d2[i, e]
                    bj[e] = nbr[i, e]
                cnt = k
                for o in range(27):
                    cc = cell_nb[c, o]
                    if cc < 0 or fresh[cc] == cend[cc]:
                        continue
                    for p in range(fresh[cc], cend[cc]):
                        ex = X[p] - px
                        ey = Y[p] - py
                        ez = Z[p] - pz
                        d = ex * ex + ey * ey + ez * ez
                        if d <= bd[k - 1]:
                            cnt = _push(bd, bj, cnt, k, d, J[p])
                _store_row(i, bd, bj, k, nbr, d2, d0, kth2)

    @njit(cache=True, parallel=True, boundscheck=False)
    def query_rings(rows, P, h, hk, hv, bits, cstart, cend, X, Y, Z, J, cmin, cmax, k, nbr, d2, d0, kth2):
        """Exact rows of the given points by rings of cells around each point's cell, stopping
        when the K-th distance is within the rings' guaranteed radius or the rings cover every
        cell (cmin/cmax: (3,) the cells' coordinate bounds). Needs more than K points."""
        for t in prange(rows.shape[0]):
            i = rows[t]
            bd = np.empty(k)
            bj = np.empty(k, np.int64)
            px = np.float64(P[i, 0])
            py = np.float64(P[i, 1])
            pz = np.float64(P[i, 2])
            cx = _coord(P[i, 0], h)
            cy = _coord(P[i, 1], h)
            cz = _coord(P[i, 2], h)
            fd = min(_face(px, cx, h), _face(py, cy, h), _face(pz, cz, h))
            rmax = max(max(cx - cmin[0], cmax[0] - cx), max(cy - cmin[1], cmax[1] - cy),
                       max(cz - cmin[2], cmax[2] - cz))
            cnt = 0
            r = 0
            while True:
                for ax in range(-r, r + 1):
                    for ay in range(-r, r + 1):
                        edge = abs(ax) == r or abs(ay) == r
                        az = -r
                        while az <= r:
                            s = _find(hk, bits, _ckey(cx + ax, cy + ay, cz + az))
                            if hk[s] != -1:
                                cc = hv[s]
                                for p in range(cstart[cc], cend[cc]):
                                    j = J[p]
                                    if j == i:
                                        continue
                                    ex = X[p] - px
                                    ey = Y[p] - py
                                    ez = Z[p] - pz
                                    cnt = _push(bd, bj, cnt, k, ex * ex + ey * ey + ez * ez, j)
                            az = az + 1 if (edge or az == r) else r  # only the shell of ring r
                        # (az jumps from -r to r inside the shell's interior columns)
                g = r * h + fd
                if (cnt == k and bd[k - 1] <= g * g) or r >= rmax:
                    break
                r += 1
            _store_row(i, bd, bj, k, nbr, d2, d0, kth2)

    @njit(cache=True, parallel=True, boundscheck=False)
    def row_weights(rows, nbr, d2, N, use_n, invariant, a_d, a_s, w, wsum, nparts):
        """Eq. 4 for the given rows (in nparts parallel chunks): w = exp(-d2 a_d - |n_i - n_j|^2 a_s)
        (float64, stored float32; padded entries have d2 = inf, so weight 0), wsum the float64 row sums."""
        k = nbr.shape[1]
        nr = rows.shape[0]
        for t in prange(nparts):
            ex = np.empty(k)
            pw = np.empty(k, np.int64)
            pwf = pw.view(np.float64)
            for q in range(t * nr // nparts, (t + 1) * nr // nparts):
                i = rows[q]
                if use_n:
                    n0 = np.float64(N[i, 0])
                    n1 = np.float64(N[i, 1])
                    n2 = np.float64(N[i, 2])
                    for e in range(k):
                        j = nbr[i, e]
                        dot = n0 * np.float64(N[j, 0]) + n1 * np.float64(N[j, 1]) + n2 * np.float64(N[j, 2])
                        if invariant:
                            dot = abs(dot)
                        tt = 2.0 - 2.0 * dot
                        ex[e] = -d2[i, e] * a_d - (tt if tt > 0.0 else 0.0) * a_s
                else:
                    for e in range(k):
                        ex[e] = -d2[i, e] * a_d
                for e in range(k):
                    ex[e], pw[e] = exp_split(ex[e])
                acc = 0.0
                for e in range(k):
                    v = np.float32(ex[e] * pwf[e])
                    w[i, e] = v
                    acc += np.float64(v)
                wsum[i] = acc
