"""Compiled (numba) kNN rows of the growing map's graph (:class:`~diffuser_lab.method.growing.IncrementalKnnGraph`):
a hash grid extended add by add (:class:`GridRows`).

Grid: cubic cells of ``h`` metres (a high quantile of the rows' K-th neighbour distance),
numbered once in a hash table of their packed coordinates (:mod:`.hashing`) and linked to their
26 neighbours (``cell_nb``), so a query reads no table. Each cell's points are one run of a pool
(float64 coordinates and indices, in index order, so an add's points are each run's tail) with
room to grow; a full run moves to the pool's end with twice the room (amortised O(new points) per
add). A query scans its cell's 3x3x3 block keeping the K best by (squared distance, index) under a
threshold guessed from the previous row, and is exact when the K-th distance is within the
block's guaranteed radius (``h`` + the point's distance to its cell's faces); the other points are
searched again ring by ring (:func:`~.cell_search.ring_knn`, the batch grid kNN's search) until no
closer point can remain. Rows follow the rule of :mod:`diffuser_lab.backends.knn` (float64
``((dx*dx + dy*dy) + dz*dz)`` from the float32 coordinates, no fastmath; by (d2, index)), as
:func:`~diffuser_lab.method.graph.build_graph` and the scipy twin
(:class:`~diffuser_lab.backends.growing.TreeRows`).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..knn import TIE_MARGIN, closer_rows
from . import NB, n_threads
from .hashing import OFF, HashTable
from .weights import row_weights

FACE_SLACK = 1e-9
"""Relative amount by which a point's distance to its cell's faces is taken short: the computed
distance rounds (~1e-16 of the coordinates), and a row is exact only if no point beyond it can tie."""

if NB is not None:
    from numba import njit, prange

    from .cell_search import push, ring_knn
    from .hashing import cell_key, coord, find

    @njit(cache=True, boundscheck=False)
    def grid_assign(P, lo, hi, h, hk, hv, bits, cell_c, cell_nb, ncells, cell_of):
        """Cells of points lo..hi-1 (new cells numbered from ncells on, linked both ways with their
        existing neighbours in cell_nb (ncells, 27): the id of the cell at offset
        (ax, ay, az) in -1..1 at column (ax+1)*9 + (ay+1)*3 + az+1, -1 if none); returns the new ncells."""
        last = np.int64(-1)
        cid = 0
        for i in range(lo, hi):
            cx = coord(P[i, 0], h)
            cy = coord(P[i, 1], h)
            cz = coord(P[i, 2], h)
            key = cell_key(cx, cy, cz)
            if key != last:
                last = key
                s = find(hk, bits, key)
                if hk[s] == -1:
                    hk[s] = key
                    hv[s] = ncells
                    cell_c[ncells, 0] = cx
                    cell_c[ncells, 1] = cy
                    cell_c[ncells, 2] = cz
                    for o in range(27):
                        ax, ay, az = o // 9 - 1, (o // 3) % 3 - 1, o % 3 - 1
                        t = find(hk, bits, cell_key(cx + ax, cy + ay, cz + az))
                        d = hv[t] if hk[t] != -1 else -1
                        cell_nb[ncells, o] = d
                        if d >= 0:
                            cell_nb[d, 26 - o] = ncells
                    ncells += 1
                cid = hv[s]
            cell_of[i] = cid
        return ncells

    @njit(cache=True, boundscheck=False, inline="always")
    def _move_run(c, pend, cap, cstart, cend, climit, fresh, X, Y, Z, J, nX, nY, nZ, nJ):
        """Cell c's run copied from the pool X/Y/Z/J to position pend of the pool nX/nY/nZ/nJ (the
        same or a new one) with room for cap points."""
        ln = cend[c] - cstart[c]
        for e in range(ln):
            nX[pend + e] = X[cstart[c] + e]
            nY[pend + e] = Y[cstart[c] + e]
            nZ[pend + e] = Z[cstart[c] + e]
            nJ[pend + e] = J[cstart[c] + e]
        fresh[c] = pend + fresh[c] - cstart[c]
        cstart[c] = pend
        cend[c] = pend + ln
        climit[c] = pend + cap

    @njit(cache=True, boundscheck=False)
    def grid_append(lo, hi, P, cell_of, cstart, cend, climit, fresh, X, Y, Z, J, pend):
        """Append points lo..hi-1 to their cells' runs in the pool X/Y/Z (float64 coordinates), J
        (indices): cell c holds cstart[c]..cend[c]-1 with room up to climit[c]; a full run moves to
        the pool's end with twice the room (fresh[c], the start of this add's points in the run,
        moves with it). Returns (the first point not appended: the pool is full, pend)."""
        for i in range(lo, hi):
            c = cell_of[i]
            if cend[c] == climit[c]:
                cap = max(4, 2 * (cend[c] - cstart[c]))
                if pend + cap > X.shape[0]:
                    return i, pend
                _move_run(c, pend, cap, cstart, cend, climit, fresh, X, Y, Z, J, X, Y, Z, J)
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
            _move_run(c, pend, max(4, 2 * (cend[c] - cstart[c])), cstart, cend, climit, fresh, X, Y, Z, J, nX, nY, nZ,
                      nJ)
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
    def _face(v, c, h):
        """Distance of coordinate v to the faces of its cell c (offset coordinate)."""
        lo = np.float64(c - OFF) * h
        return min(v - lo, lo + h - v)

    @njit(cache=True, parallel=True, boundscheck=False)
    def query_rows(Q, P, h, cell_c, cell_of, cell_nb, cstart, cend, X, Y, Z, J, kth2, n_old, mark, k, nbr, d2, d0,
                   fail, aff, nparts, cap):
        """Rows of the queried points Q (in nparts parallel chunks; sorted by cell for locality)
        from their cell's 3x3x3 block: nbr/d2 sorted by (d2, index), d0 the smallest positive d2
        (inf if none), kth2 the K-th d2; fail[i] = 1 where the K-th distance exceeds the block's
        guaranteed radius (search again with rings). With ``mark``, every old point (index < n_old)
        within ``h`` of a queried point and closer to it than its own K-th neighbour (kth2, read
        for the old points) is flagged in aff (the same value from any thread).

        The block's points are copied once per run of queries in one cell (``cap``: room for the
        largest block) and each query's squared distances to them computed in one pass (a loop
        without branches: vectorised); then the K best by (d2, index) under a threshold guessed
        from the previous query (measured, 2.4k queries on a 30k-point map, one thread: 7.0 ->
        4.5 ms)."""
        nq = Q.shape[0]
        h2 = h * h
        for t in prange(nparts):
            bd = np.empty(k)
            bj = np.empty(k, np.int64)
            bx = np.empty(cap)
            by = np.empty(cap)
            bz = np.empty(cap)
            bjs = np.empty(cap, np.int64)
            dd = np.empty(cap)
            prev = -1
            m = 0
            thr = 0.5 * h2  # then guessed from the previous point (the rows are sorted by cell)
            for qi in range(t * nq // nparts, (t + 1) * nq // nparts):
                i = Q[qi]
                c = cell_of[i]
                if c != prev:  # the block's points, contiguous
                    m = 0
                    for o in range(27):
                        cc = cell_nb[c, o]
                        if cc < 0:
                            continue
                        for p in range(cstart[cc], cend[cc]):
                            bx[m] = X[p]
                            by[m] = Y[p]
                            bz[m] = Z[p]
                            bjs[m] = J[p]
                            m += 1
                    prev = c
                px = np.float64(P[i, 0])
                py = np.float64(P[i, 1])
                pz = np.float64(P[i, 2])
                for e in range(m):
                    ex = bx[e] - px
                    ey = by[e] - py
                    ez = bz[e] - pz
                    dd[e] = ex * ex + ey * ey + ez * ez
                if mark:
                    for e in range(m):
                        j = bjs[e]
                        if dd[e] < h2 and j < n_old and dd[e] < kth2[j]:
                            aff[j] = 1
                while True:
                    # K best by (d2, index), self excluded, among the candidates within thr
                    cnt = 0
                    lim = thr
                    for e in range(m):
                        if dd[e] <= lim and bjs[e] != i:
                            cnt = push(bd, bj, cnt, k, dd[e], bjs[e])
                            if cnt == k:
                                lim = min(lim, bd[k - 1])
                    if cnt == k or thr == np.inf:
                        break
                    thr = thr * 4.0 if thr < 16.0 * h2 else np.inf  # too few within the guess: wider
                for e in range(cnt, k):  # fewer than K candidates: fail below
                    bd[e] = np.inf
                    bj[e] = i
                cx, cy, cz = cell_c[c, 0], cell_c[c, 1], cell_c[c, 2]
                # a point outside the block may be at exactly fd (and win a tie by index): >=, and
                # a relative slack for the faces' rounding
                fd = (min(_face(px, cx, h), _face(py, cy, h), _face(pz, cz, h)) + h) * (1.0 - FACE_SLACK)
                fail[i] = 1 if (cnt < k or bd[k - 1] >= fd * fd) else 0
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
                            cnt = push(bd, bj, cnt, k, d, J[p])
                _store_row(i, bd, bj, k, nbr, d2, d0, kth2)

    @njit(cache=True, parallel=True, boundscheck=False)
    def query_rings(rows, P, h, hk, hv, bits, cstart, cend, X, Y, Z, J, cmin, cmax, k, nbr, d2, d0, kth2):
        """Exact rows of the given points by rings of cells around each point's cell
        (:func:`~.cell_search.ring_knn`; cmin/cmax: (3,) the cells' coordinate bounds). Needs more
        than K points."""
        no_dims = np.ones(3, np.int64)
        for t in prange(rows.shape[0]):
            i = rows[t]
            bd = np.empty(k)
            bj = np.empty(k, np.int64)
            px = np.float64(P[i, 0])
            py = np.float64(P[i, 1])
            pz = np.float64(P[i, 2])
            cx = coord(P[i, 0], h)
            cy = coord(P[i, 1], h)
            cz = coord(P[i, 2], h)
            lx = np.float64(cx - OFF) * h
            ly = np.float64(cy - OFF) * h
            lz = np.float64(cz - OFF) * h
            e = FACE_SLACK * h  # the faces' distances a little short (rounding): never one too far
            ring_knn(i, px, py, pz, (cx, cy, cz), (px - lx - e, py - ly - e, pz - lz - e),
                     (lx + h - px - e, ly + h - py - e, lz + h - pz - e), h, cmin, cmax, no_dims, hk, hv, bits,
                     cstart, cend, X, Y, Z, J, k, bd, bj)
            _store_row(i, bd, bj, k, nbr, d2, d0, kth2)


class GridRows:
    """The rows of :class:`~diffuser_lab.method.growing.IncrementalKnnGraph` from the hash grid of
    this module (see module doc), and their Eq. 4 weights (:func:`~.weights.row_weights`).

    ``arrays`` below: the graph's (points, nbr, d2, d0, kth) of its capacity's rows: (cap, 3)
    float32 points; (cap, K) int32 neighbours and float64 squared distances, each row ascending by
    (d2, index); (cap,) float64 the smallest positive d2 (inf if none) and the K-th d2.
    """

    compiled = True
    CELL_QUANTILE = 0.97
    """Grid cell side: this quantile of the rows' K-th neighbour distances."""

    def __init__(self, k: int):
        self.k = k
        self._grid: dict | None = None

    def build(self, arrays: tuple, n: int) -> None:
        """Every row of the first n points (more than K), from a new grid."""
        self._grid_build(arrays, n)
        self._query(arrays, n, np.arange(n, dtype=np.int64), n_old=0, mark=False)

    def extend(self, arrays: tuple, n_old: int, n: int) -> np.ndarray:
        """Points n_old..n-1 into the grid and their rows; returns (r,) int64 the old rows (< n_old)
        a new point is closer to than their K-th neighbour (:meth:`update` recomputes them)."""
        P, _, _, _, kth = arrays
        h2 = self._grid["h"] ** 2
        kth2 = kth[:n_old]
        # old rows reaching beyond the block around a new point: checked against the new points directly
        wide = np.flatnonzero(kth2 > h2)
        q = self.CELL_QUANTILE
        if wide.size > 2 * (1 - q) * n_old or np.count_nonzero(kth2 > h2 / 2) < (1 - q) * n_old:
            self._grid_build(arrays, n_old)  # cell side off the rows' K-th distances: a new grid of the old points
            h2 = self._grid["h"] ** 2
            wide = np.flatnonzero(kth2 > h2)
        self._grid_add(P, n_old, n)
        aff = self._query(arrays, n, np.arange(n_old, n, dtype=np.int64), n_old, mark=True)
        if wide.size:
            # their nearest new point, searched no farther than their own reach (bounds the
            # KD-tree's work for the many far from this add); the few near ones are checked
            # exactly (a new point at a tie of the K-th distance loses to the older index)
            tree = cKDTree(P[n_old:n])
            reach = np.sqrt(kth2[wide]) * (1 + TIE_MARGIN)
            short = reach <= 2 * self._grid["h"]
            dn = np.full(wide.size, np.inf)
            if short.any():
                dn[short] = tree.query(P[wide[short]], k=1, distance_upper_bound=float(reach[short].max()))[0]
            if (~short).any():
                dn[~short] = tree.query(P[wide[~short]], k=1)[0]
            near = wide[dn < reach]
            aff[near[closer_rows(P, kth, near, n_old, n)]] = 1  # strictly closer by the rule, as the twin
        return np.flatnonzero(aff).astype(np.int64)

    def update(self, arrays: tuple, rows: np.ndarray) -> None:
        """Recompute the old ``rows`` :meth:`extend` returned with the points it added."""
        P, nbr, d2, d0, kth = arrays
        g = self._grid
        far = kth[rows] > g["h"] ** 2
        self._rings(arrays, rows[far])  # wide rows: new points may lie beyond the block
        near = rows[~far]
        if near.size:
            Q, parts = self._by_cell(near)
            merge_rows(Q, P, g["cell_of"], g["cell_nb"], g["cend"], g["fresh"], *g["pool"], self.k, nbr, d2, d0, kth,
                       parts)

    def weights(self, rows: np.ndarray, nbr: np.ndarray, d2: np.ndarray, normals: np.ndarray | None, invariant: bool,
                sigma_d: float, sigma_s: float, w: np.ndarray, wsum: np.ndarray) -> None:
        """Eq. 4 for ``rows``, in place (:func:`~.weights.row_weights`)."""
        row_weights(rows, nbr, d2, normals, invariant, sigma_d, sigma_s, w, wsum)

    def _grid_build(self, arrays: tuple, n: int) -> None:
        """Hash grid over the first n points, cell side from their rows (or, before any, a KD-tree sample)."""
        P, _, _, _, kth = arrays
        kth2 = kth[:n]
        if self._grid is not None and np.isfinite(kth2).all():
            r = float(np.sqrt(np.quantile(kth2, self.CELL_QUANTILE)))
        else:
            s = P[np.linspace(0, n - 1, min(n, 2048)).astype(np.int64)]
            d, _ = cKDTree(P[:n]).query(s, k=self.k + 1)
            r = float(np.quantile(d[:, -1], self.CELL_QUANTILE))
        if not r > 0:
            r = 1.0
        c0 = 1024
        self._grid = dict(h=r, table=HashTable(), ncells=0, cell_c=np.empty((c0, 3), np.int64),
                          cell_nb=np.empty((c0, 27), np.int64), cstart=np.zeros(c0, np.int64),
                          cend=np.zeros(c0, np.int64), climit=np.zeros(c0, np.int64), fresh=np.zeros(c0, np.int64),
                          pool=tuple(np.empty(2 * n + 4096) for _ in range(3)) + (np.empty(2 * n + 4096, np.int64),),
                          pend=0, cell_of=np.empty(P.shape[0], np.int64), cmin=None, cmax=None)
        self._grid_add(P, 0, n)

    def _grid_add(self, P: np.ndarray, lo: int, hi: int) -> None:
        """Points lo..hi-1 into their cells (new cells linked to their neighbours) and the pool."""
        g = self._grid
        if g["cell_of"].shape[0] < P.shape[0]:  # the graph's capacity grew
            cell_of = np.empty(P.shape[0], np.int64)
            cell_of[:lo] = g["cell_of"][:lo]
            g["cell_of"] = cell_of
        tb = g["table"]
        tb.reserve(hi - lo)
        nc0 = g["ncells"]
        if g["cell_c"].shape[0] < nc0 + hi - lo:
            cap = max(2 * g["cell_c"].shape[0], nc0 + hi - lo)
            for name in ("cell_c", "cell_nb", "cstart", "cend", "climit", "fresh"):
                a = np.zeros((cap,) + g[name].shape[1:], g[name].dtype)
                a[:nc0] = g[name][:nc0]
                g[name] = a
        nc = grid_assign(P, lo, hi, g["h"], tb.keys, tb.vals, tb.bits, g["cell_c"], g["cell_nb"], nc0, g["cell_of"])
        g["ncells"] = tb.used = nc
        newc = g["cell_c"][nc0:nc]
        if newc.shape[0]:
            g["cstart"][nc0:nc] = g["cend"][nc0:nc] = g["climit"][nc0:nc] = 0
            lo_c, hi_c = newc.min(0), newc.max(0)
            g["cmin"] = lo_c if g["cmin"] is None else np.minimum(g["cmin"], lo_c)
            g["cmax"] = hi_c if g["cmax"] is None else np.maximum(g["cmax"], hi_c)
        g["fresh"][:nc] = g["cend"][:nc]  # this add's points start at each run's current end
        i = lo
        while True:
            X, Y, Z, J = g["pool"]
            i, g["pend"] = grid_append(i, hi, P, g["cell_of"], g["cstart"], g["cend"], g["climit"], g["fresh"],
                                       X, Y, Z, J, g["pend"])
            if i >= hi:
                break
            # pool full: a compacted pool with room for the rest
            ln = g["cend"][:nc] - g["cstart"][:nc]
            size = 2 * int(np.maximum(4, 2 * ln).sum()) + 4 * (hi - i) + 4096
            new = tuple(np.empty(size) for _ in range(3)) + (np.empty(size, np.int64),)
            g["pend"] = pool_compact(nc, g["cstart"], g["cend"], g["climit"], g["fresh"], X, Y, Z, J, *new)
            g["pool"] = new

    def _by_cell(self, rows: np.ndarray) -> tuple[np.ndarray, int]:
        """``rows`` sorted by cell (neighbouring rows read the same cells) and a parallel part count."""
        Q = rows[np.argsort(self._grid["cell_of"][rows], kind="stable")]
        return Q, max(1, min(n_threads() * 8, rows.size // 64 + 1))

    def _query(self, arrays: tuple, n: int, rows: np.ndarray, n_old: int, mark: bool) -> np.ndarray:
        """Recompute ``rows`` from the grid; with ``mark``, returns the flags (n_old,) of the old
        rows a new point (index >= n_old) is closer to than their K-th neighbour."""
        P, nbr, d2, d0, kth = arrays
        g = self._grid
        aff = np.zeros(n_old if mark else 1, np.uint8)
        if rows.size == 0:
            return aff
        Q, parts = self._by_cell(rows)
        fail = np.zeros(n, np.uint8)
        nc = g["ncells"]
        cap = 27 * int((g["cend"][:nc] - g["cstart"][:nc]).max()) + 1  # room for the largest block
        query_rows(Q, P, g["h"], g["cell_c"], g["cell_of"], g["cell_nb"], g["cstart"], g["cend"], *g["pool"], kth,
                   n_old, mark, self.k, nbr, d2, d0, fail, aff, parts, cap)
        self._rings(arrays, rows[fail[rows] != 0])
        return aff

    def _rings(self, arrays: tuple, rows: np.ndarray) -> None:
        if rows.size:
            P, nbr, d2, d0, kth = arrays
            g = self._grid
            tb = g["table"]
            query_rings(rows, P, g["h"], tb.keys, tb.vals, tb.bits, g["cstart"], g["cend"], *g["pool"], g["cmin"],
                        g["cmax"], self.k, nbr, d2, d0, kth)
