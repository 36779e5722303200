"""A growing point map and its kNN graph (paper Eqs. 3-4), extended frame by frame for the online
protocol instead of rebuilt.

:class:`VoxelMap` merges each frame's back-projected points on a fixed world voxel grid (one point
per occupied voxel; a point never moves once made). :class:`IncrementalKnnGraph` appends the new
points and keeps the graph equal to :func:`~diffuser_lab.method.graph.build_graph` on the same
points (neighbour sets per row, up to exact distance ties): the new rows get their K nearest among
all points, and an old row is recomputed only when a new point is closer than its K-th neighbour
(points only arrive, so no other row can change).

With numba (:func:`diffuser_lab.backends.numba.available`, decided when an object is made) both use
hash tables compiled in :mod:`diffuser_lab.backends.numba.growing`; otherwise numpy (sorted voxel
keys) and scipy's cKDTree (rebuilt per add; slower, same results).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from diffuser_lab.data.geometry import _spread_bits
from diffuser_lab.method.graph import normal_distance2

_OFF = 1 << 20  # signed voxel / cell coordinates -> 21 unsigned bits


def voxel_keys(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """(M, 3) world points -> (M,) int64 Morton codes of their voxels' integer coordinates
    ``floor(x / voxel_size)`` (offset by 2^20, so +-2^20 voxels per axis around the world origin)."""
    q = np.floor(np.asarray(points, np.float64) / voxel_size)
    q = (np.clip(q, -_OFF, _OFF - 1) + _OFF).astype(np.uint64)
    code = _spread_bits(q[:, 0]) | (_spread_bits(q[:, 1]) << np.uint64(1)) | (_spread_bits(q[:, 2]) << np.uint64(2))
    return code.astype(np.int64)


def _unit(nsum: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Normalised rows of the (m, 3) float64 sums; a zero sum takes the row of ``fallback``."""
    norm = np.sqrt(np.einsum("ij,ij->i", nsum, nsum))
    out = nsum / np.where(norm > 0, norm, 1.0)[:, None]
    bad = ~(norm > 0)
    out[bad] = fallback[bad]
    return out.astype(np.float32)


def _use_numba() -> bool:
    from diffuser_lab.backends import numba as nb

    return nb.available()


class _Table:
    """Open-addressing int64 -> int64 hash table (numba path), kept at most half full."""

    def __init__(self, bits: int = 12):
        self.bits = bits
        self.keys = np.full(1 << bits, -1, np.int64)
        self.vals = np.empty(1 << bits, np.int64)
        self.used = 0

    def reserve(self, extra: int) -> None:
        """Room for ``extra`` more keys."""
        need = 2 * (self.used + extra)
        if need <= self.keys.shape[0]:
            return
        from diffuser_lab.backends.numba import growing as kg

        bits = self.bits
        while (1 << bits) < need:
            bits += 1
        nk = np.full(1 << bits, -1, np.int64)
        nv = np.empty(1 << bits, np.int64)
        kg.rehash(self.keys, self.vals, nk, nv, bits)
        self.keys, self.vals, self.bits = nk, nv, bits


class VoxelMap:
    """Points merged on a voxel grid of ``voxel_size`` metres (world frame, grid anchored at the
    world origin so it never moves as the map grows): one point per occupied voxel.

    Attributes:
        n: occupied voxels so far. voxel_size: metres.
    """

    def __init__(self, voxel_size: float):
        if not voxel_size > 0:
            raise ValueError(f"voxel_size must be positive, got {voxel_size}")
        self.voxel_size = float(voxel_size)
        self.n = 0
        self._nb = _use_numba()
        if self._nb:
            self._table = _Table()
        else:
            self._sorted = np.empty(0, np.int64)  # occupied voxels' keys, ascending

    def occupied(self, points: np.ndarray) -> np.ndarray:
        """(M,) bool: the point's voxel already holds a map point (:meth:`insert` would drop it)."""
        points = np.ascontiguousarray(points, np.float32)
        if self.n == 0 or points.shape[0] == 0:
            return np.zeros(points.shape[0], bool)
        if self._nb:
            from diffuser_lab.backends.numba import growing as kg

            out = np.empty(points.shape[0], np.bool_)
            kg.voxel_occupied(points, self.voxel_size, self._table.keys, self._table.bits, out)
            return out
        keys = voxel_keys(points, self.voxel_size)
        pos = np.minimum(np.searchsorted(self._sorted, keys), self._sorted.shape[0] - 1)
        return self._sorted[pos] == keys

    def insert(self, points: np.ndarray, normals: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
        """Merge one frame.

        Args:
            points: (M, 3) float32 world points, metres; normals: (M, 3) unit normals or None.
        Returns:
            the NEW map points (m, 3) float32 and their normals (m, 3) float32 or None, in Morton
            order of their voxel keys. Points in voxels occupied by earlier frames are dropped (the
            map point there stays); the points of this frame in one new voxel become their centroid
            (float64 sums) and the normalised sum of their normals (the first point's normal if that
            sum is 0).
        """
        points = np.ascontiguousarray(points, np.float32)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must be (M, 3), got {points.shape}")
        use_n = normals is not None
        if use_n:
            normals = np.ascontiguousarray(normals, np.float32)
            if normals.shape != points.shape:
                raise ValueError(f"normals must be (M, 3) like the points, got {normals.shape}")
        m = points.shape[0]
        if self._nb:
            from diffuser_lab.backends.numba import growing as kg

            tb = self._table
            tb.reserve(m)
            keys = np.empty(m, np.int64)
            slots = np.empty(m, np.int64)
            sums = np.empty((m, 3))
            nsums = np.empty((m, 3))
            counts = np.empty(m, np.int64)
            first = np.empty(m, np.int64)
            t = kg.voxel_insert(points, normals if use_n else points, use_n, self.voxel_size, tb.keys, tb.vals,
                                tb.bits, self.n, keys, slots, sums, nsums, counts, first)
            order = np.argsort(keys[:t], kind="stable")  # keys are unique
            tb.vals[slots[:t][order]] = self.n + np.arange(t)
            tb.used += t
            sums, nsums, counts, first = sums[order], nsums[order], counts[order], first[order]
        else:
            keys = voxel_keys(points, self.voxel_size)
            uk, first, inv, counts = np.unique(keys, return_index=True, return_inverse=True, return_counts=True)
            inv = inv.ravel()
            pos = np.searchsorted(self._sorted, uk)
            hit = np.zeros(uk.shape, bool)
            inside = pos < self._sorted.shape[0]
            hit[inside] = self._sorted[pos[inside]] == uk[inside]
            new = ~hit
            # per-voxel sums in input order (bincount adds sequentially, like the compiled loop)
            p64 = points.astype(np.float64)
            sums = np.stack([np.bincount(inv, p64[:, a], uk.shape[0]) for a in range(3)], 1)[new]
            if use_n:
                n64 = normals.astype(np.float64)
                nsums = np.stack([np.bincount(inv, n64[:, a], uk.shape[0]) for a in range(3)], 1)[new]
            self._sorted = np.insert(self._sorted, pos[new], uk[new])
            counts, first = counts[new], first[new]
            t = int(new.sum())
        self.n += t
        pts = (sums / counts[:, None]).astype(np.float32)
        nrm = _unit(nsums, normals[first]) if use_n else None
        return pts, nrm


class IncrementalKnnGraph:
    """K-nearest-neighbour graph of a growing point set, rows in insertion order (capacity grows
    by doubling). Same definition as :func:`~diffuser_lab.method.graph.build_graph`: K nearest by
    Euclidean distance (self excluded, duplicates kept, ties by index), Eq. 4 weights.

    While the set has at most K points, a row has fewer than K real neighbours: the missing
    entries are the row's own index with squared distance inf and weight 0 (row sums count only
    real neighbours).

    Attributes (views of the first ``n`` rows):
        n: points so far; k.
        points: (n, 3) float32 world points, metres; normals: (n, 3) float32 or None.
        neighbors: (n, K) int32, each row sorted by distance (ties by index).
        dist2: (n, K) float64 squared distances of those neighbours, m^2.
        weights: (n, K) float32 Eq. 4 with the current sigma_d; row_sums: (n,) float64.
        rho: mean distance of a point to its nearest distinct neighbour (0 distances skipped),
            maintained from each row's nearest distinct distance; nan until one exists.
        sigma_d: the bandwidth of the weights: the given one, or sigma_d_factor * rho_w with
            rho_w the rho at the last weight refresh (refreshed when rho moves more than rho_tol).
    """

    CELL_QUANTILE = 0.97
    """Grid cell side (numba path): this quantile of the rows' K-th neighbour distances."""

    def __init__(self, k: int = 24, *, sigma_s: float = 0.2, sigma_d: float | None = None, sigma_d_factor: float = 2.0,
                 invariant_normals: bool = False, rho_tol: float = 0.02):
        if k < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        self.k = int(k)
        self.sigma_s = float(sigma_s)
        self._sigma_d_fixed = None if sigma_d is None else float(sigma_d)
        self.sigma_d_factor = float(sigma_d_factor)
        self.invariant_normals = bool(invariant_normals)
        self.rho_tol = float(rho_tol)
        self.n = 0
        self._use_n: bool | None = None  # fixed by the first add
        self._cap = 0
        self._P = np.empty((0, 3), np.float32)
        self._N = np.empty((0, 3), np.float32)
        self._nbr = np.empty((0, self.k), np.int32)
        self._d2 = np.empty((0, self.k))
        self._w = np.empty((0, self.k), np.float32)
        self._ws = np.empty(0)
        self._d0 = np.empty(0)  # per row the smallest positive squared distance (inf: none)
        self._kth = np.empty(0)  # per row the K-th squared distance (= dist2[:, -1], contiguous)
        self._rsum = 0.0  # sum of sqrt(d0) over the finite d0, and their count
        self._rcnt = 0
        self._rho_w: float | None = None
        self.sigma_d = float("nan") if sigma_d is None else float(sigma_d)
        self._nb = _use_numba()
        self._grid: dict | None = None  # numba path: hash grid (see _grid_*)

    # --- views ---
    @property
    def points(self) -> np.ndarray:
        return self._P[: self.n]

    @property
    def normals(self) -> np.ndarray | None:
        return self._N[: self.n] if self._use_n else None

    @property
    def neighbors(self) -> np.ndarray:
        return self._nbr[: self.n]

    @property
    def dist2(self) -> np.ndarray:
        return self._d2[: self.n]

    @property
    def weights(self) -> np.ndarray:
        return self._w[: self.n]

    @property
    def row_sums(self) -> np.ndarray:
        return self._ws[: self.n]

    @property
    def rho(self) -> float:
        return self._rsum / self._rcnt if self._rcnt else float("nan")

    def __repr__(self) -> str:
        return f"IncrementalKnnGraph(n={self.n}, k={self.k}, rho={self.rho:.4g}, sigma_d={self.sigma_d:.4g})"

    # --- storage ---
    def _reserve(self, n: int) -> None:
        if n <= self._cap:
            return
        cap = max(1024, self._cap)
        while cap < n:
            cap *= 2
        k = self.k

        def grow(a, shape, dtype):
            b = np.empty(shape, dtype)
            b[: self.n] = a[: self.n]
            return b

        self._P = grow(self._P, (cap, 3), np.float32)
        if self._use_n:
            self._N = grow(self._N, (cap, 3), np.float32)
        self._nbr = grow(self._nbr, (cap, k), np.int32)
        self._d2 = grow(self._d2, (cap, k), np.float64)
        self._w = grow(self._w, (cap, k), np.float32)
        self._ws = grow(self._ws, (cap,), np.float64)
        self._d0 = grow(self._d0, (cap,), np.float64)
        self._kth = grow(self._kth, (cap,), np.float64)
        if self._grid is not None:
            self._grid["cell_of"] = grow(self._grid["cell_of"], (cap,), np.int64)
        self._cap = cap

    # --- the update ---
    def add(self, points: np.ndarray, normals: np.ndarray | None) -> np.ndarray:
        """Append (m, 3) float32 world points (and (m, 3) unit normals, or None: given with every
        add or with none) and update the graph.

        Returns:
            (r,) int64 sorted indices of every row whose neighbours or weights changed: the new
            rows, the old rows a new point entered, or every row when the weights were refreshed
            because rho moved by more than rho_tol.
        """
        points = np.ascontiguousarray(points, np.float32)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must be (m, 3), got {points.shape}")
        m = points.shape[0]
        if self._use_n is None and m:
            self._use_n = normals is not None
        if m and (normals is not None) != self._use_n:
            raise ValueError("normals must be given with every add or with none")
        if normals is not None and np.shape(normals) != (m, 3):
            raise ValueError(f"normals must be (m, 3) like the points, got {np.shape(normals)}")
        if m == 0:
            return np.empty(0, np.int64)
        n_old, n = self.n, self.n + m
        self._reserve(n)
        self._P[n_old:n] = points
        if self._use_n:
            self._N[n_old:n] = normals
        self.n = n
        k = self.k
        if n <= k:  # too few points for K neighbours: all pairs, padded with the row itself
            self._small()
            changed = np.arange(n, dtype=np.int64)
            self._resum_rho()
        elif n_old <= k:  # the first full graph
            changed = np.arange(n, dtype=np.int64)
            if self._nb:
                self._grid_build()
                self._nb_rows(changed, n_old=0, mark=False)
            else:
                self._kd_rows(changed, cKDTree(self._P[:n]))
            self._resum_rho()
        else:
            old_rows = self._nb_add(n_old) if self._nb else self._kd_add(n_old)
            changed = np.concatenate([old_rows, np.arange(n_old, n, dtype=np.int64)])
            self._update_rho(changed, np.concatenate([self._d0_before, np.full(m, np.inf)]))
        if self._sigma_d_fixed is None:
            rho = self.rho
            if self._rcnt and (self._rho_w is None or abs(rho - self._rho_w) > self.rho_tol * self._rho_w):
                self.refresh_weights()
                return np.arange(n, dtype=np.int64)
            if self._rho_w is None:  # no distinct neighbour yet: no bandwidth
                self._w[changed] = 0
                self._ws[changed] = 0
                return changed
        self._weights(changed)
        return changed

    def refresh_weights(self) -> None:
        """Recompute every weight with sigma_d = sigma_d_factor * rho (rho recomputed from the rows'
        nearest distinct distances), as :func:`~diffuser_lab.method.graph.build_graph` on the same points."""
        self._resum_rho()
        if self._sigma_d_fixed is None:
            if not self._rcnt:
                raise ValueError("all points coincide: the mean point spacing rho is 0")
            d0 = self._d0[: self.n]
            self._rho_w = float(np.sqrt(d0[np.isfinite(d0)]).mean())  # as build_graph
            self._rsum = self._rho_w * self._rcnt
            self.sigma_d = self.sigma_d_factor * self._rho_w
        self._weights(np.arange(self.n, dtype=np.int64))

    def _resum_rho(self) -> None:
        d0 = self._d0[: self.n]
        pos = np.sqrt(d0[np.isfinite(d0)])
        self._rsum, self._rcnt = float(pos.sum()), int(pos.size)

    def _update_rho(self, rows: np.ndarray, old_d0: np.ndarray) -> None:
        new = self._d0[rows]
        fo, fn = np.isfinite(old_d0), np.isfinite(new)
        self._rsum += float(np.sqrt(new[fn]).sum() - np.sqrt(old_d0[fo]).sum())
        self._rcnt += int(fn.sum() - fo.sum())

    def _weights(self, rows: np.ndarray) -> None:
        sd = self.sigma_d
        a_d, a_s = 0.5 / sd**2, 0.5 / self.sigma_s**2
        if self._nb:
            from diffuser_lab.backends.numba import growing as kg

            from diffuser_lab.backends import numba as nb

            parts = max(1, min(nb.n_threads() * 8, rows.size // 256 + 1))
            kg.row_weights(rows, self._nbr, self._d2, self._N if self._use_n else self._P, bool(self._use_n),
                           self.invariant_normals, a_d, a_s, self._w, self._ws, parts)
            return
        d2 = self._d2[rows]
        expo = d2 * -a_d
        if self._use_n:
            nrm = self._N
            expo -= normal_distance2(nrm[rows][:, None, :].astype(np.float64), nrm[self._nbr[rows]].astype(np.float64),
                                     self.invariant_normals) * a_s
        w = np.exp(expo).astype(np.float32)
        self._w[rows] = w
        self._ws[rows] = w.sum(1, dtype=np.float64)

    def _small(self) -> None:
        """Every row of a set of n <= K points: all others by (d2, index), then the row itself at inf."""
        n, k = self.n, self.k
        p = self._P[:n].astype(np.float64)
        d2 = ((p[:, None, :] - p[None, :, :]) ** 2).sum(-1)
        np.fill_diagonal(d2, np.inf)
        idx = np.broadcast_to(np.arange(n), (n, n))
        o = np.lexsort((idx, d2), axis=-1)
        nb = np.repeat(np.arange(n, dtype=np.int32)[:, None], k, 1)
        dd = np.full((n, k), np.inf)
        nb[:, :n] = np.take_along_axis(idx, o, 1)
        dd[:, :n] = np.take_along_axis(d2, o, 1)
        nb[:, n - 1] = np.arange(n)  # the last of the n sorted is the row itself (inf)
        self._nbr[:n], self._d2[:n] = nb, dd
        self._d0[:n] = np.where(dd > 0, dd, np.inf).min(1)
        self._kth[:n] = dd[:, -1]

    # --- scipy path ---
    def _kd_rows(self, rows: np.ndarray, tree: cKDTree) -> None:
        """Rows recomputed from a KD-tree of all points (as build_graph's scipy path), sorted by (d2, index)."""
        k = self.k
        if rows.size == 0:
            return
        dist, idx = tree.query(self._P[rows], k=k + 1)
        is_self = idx == rows[:, None]
        is_self[~is_self.any(1), -1] = True
        keep = ~(is_self & (is_self.cumsum(1) == 1))
        r = rows.shape[0]
        idx = idx[keep].reshape(r, k)
        # squared distances recomputed in float64 from the float32 coordinates (as the compiled path)
        d2 = ((self._P[idx].astype(np.float64) - self._P[rows][:, None, :].astype(np.float64)) ** 2).sum(-1)
        o = np.lexsort((idx, d2), axis=-1)
        idx, d2 = np.take_along_axis(idx, o, 1), np.take_along_axis(d2, o, 1)
        self._nbr[rows] = idx
        self._d2[rows] = d2
        self._d0[rows] = np.where(d2 > 0, d2, np.inf).min(1)
        self._kth[rows] = d2[:, -1]

    def _kd_add(self, n_old: int) -> np.ndarray:
        n = self.n
        tree = cKDTree(self._P[:n])
        # old rows a new point is strictly closer to than their K-th neighbour
        dn, _ = cKDTree(self._P[n_old:n]).query(self._P[:n_old], k=1)
        kth2 = self._kth[:n_old]
        aff = np.flatnonzero(dn.astype(np.float64) ** 2 < kth2 * (1 + 1e-12) + 1e-300).astype(np.int64)
        aff = aff[self._closer(aff, n_old)]
        self._d0_before = self._d0[aff].copy()
        self._kd_rows(np.concatenate([aff, np.arange(n_old, n)]), tree)
        return aff

    def _closer(self, rows: np.ndarray, n_old: int) -> np.ndarray:
        """Mask of ``rows`` (old rows near a new point by the KD-tree's float distance) whose exact
        float64 squared distance to some new point is below their K-th (decides ties as the compiled path)."""
        if rows.size == 0:
            return np.zeros(0, bool)
        kth2 = self._kth[rows]
        lists = cKDTree(self._P[n_old : self.n]).query_ball_point(self._P[rows], np.sqrt(kth2) * (1 + 1e-9))
        lens = np.fromiter((len(x) for x in lists), np.int64, rows.size)
        cand = np.concatenate([np.asarray(x, np.int64) for x in lists]) + n_old if lens.sum() else np.zeros(0, np.int64)
        owner = np.repeat(np.arange(rows.size), lens)
        d2 = ((self._P[cand].astype(np.float64) - self._P[rows[owner]].astype(np.float64)) ** 2).sum(-1)
        ok = np.zeros(rows.size, bool)
        ok[owner[d2 < kth2[owner]]] = True
        return ok

    # --- numba path ---
    def _grid_build(self) -> None:
        """Hash grid over all points, cell side from the current rows (or, before any, a KD-tree sample)."""
        n, k = self.n, self.k
        kth2 = self._kth[:n]
        if self._grid is not None and np.isfinite(kth2).all():
            r = float(np.sqrt(np.quantile(kth2, self.CELL_QUANTILE)))
        else:
            s = self._P[np.linspace(0, n - 1, min(n, 2048)).astype(np.int64)]
            d, _ = cKDTree(self._P[:n]).query(s, k=k + 1)
            r = float(np.quantile(d[:, -1], self.CELL_QUANTILE))
        if not r > 0:
            r = 1.0
        c0 = 1024
        self._grid = dict(h=r, table=_Table(), ncells=0, cell_c=np.empty((c0, 3), np.int64),
                          cell_nb=np.empty((c0, 27), np.int64), cstart=np.zeros(c0, np.int64),
                          cend=np.zeros(c0, np.int64), climit=np.zeros(c0, np.int64), fresh=np.zeros(c0, np.int64),
                          pool=tuple(np.empty(2 * n + 4096) for _ in range(3)) + (np.empty(2 * n + 4096, np.int64),),
                          pend=0, cell_of=np.empty(self._cap, np.int64), cmin=None, cmax=None)
        self._grid_add(0, n)

    def _grid_add(self, lo: int, hi: int) -> None:
        """Points lo..hi-1 into their cells (new cells linked to their neighbours) and the pool."""
        from diffuser_lab.backends.numba import growing as kg

        g = self._grid
        tb = g["table"]
        tb.reserve(hi - lo)
        nc0 = g["ncells"]
        if g["cell_c"].shape[0] < nc0 + hi - lo:
            cap = max(2 * g["cell_c"].shape[0], nc0 + hi - lo)
            for name in ("cell_c", "cell_nb", "cstart", "cend", "climit", "fresh"):
                a = np.zeros((cap,) + g[name].shape[1:], g[name].dtype)
                a[:nc0] = g[name][:nc0]
                g[name] = a
        nc = kg.grid_assign(self._P, lo, hi, g["h"], tb.keys, tb.vals, tb.bits, g["cell_c"], g["cell_nb"], nc0,
                            g["cell_of"])
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
            i, g["pend"] = kg.grid_append(i, hi, self._P, g["cell_of"], g["cstart"], g["cend"], g["climit"], g["fresh"],
                                          X, Y, Z, J, g["pend"])
            if i >= hi:
                break
            # pool full: a compacted pool with room for the rest
            ln = g["cend"][:nc] - g["cstart"][:nc]
            size = 2 * int(np.maximum(4, 2 * ln).sum()) + 4 * (hi - i) + 4096
            new = tuple(np.empty(size) for _ in range(3)) + (np.empty(size, np.int64),)
            g["pend"] = kg.pool_compact(nc, g["cstart"], g["cend"], g["climit"], g["fresh"], X, Y, Z, J, *new)
            g["pool"] = new

    def _by_cell(self, rows: np.ndarray) -> tuple[np.ndarray, int]:
        """``rows`` sorted by cell (neighbouring rows read the same cells) and a parallel part count."""
        from diffuser_lab.backends import numba as nb

        Q = rows[np.argsort(self._grid["cell_of"][rows], kind="stable")]
        return Q, max(1, min(nb.n_threads() * 8, rows.size // 64 + 1))

    def _nb_rows(self, rows: np.ndarray, n_old: int, mark: bool) -> np.ndarray:
        """Recompute ``rows`` from the grid; with ``mark``, returns the flags (n_old,) of the old
        rows a new point (index >= n_old) is closer to than their K-th neighbour."""
        from diffuser_lab.backends.numba import growing as kg

        g = self._grid
        aff = np.zeros(n_old if mark else 1, np.uint8)
        if rows.size == 0:
            return aff
        Q, parts = self._by_cell(rows)
        fail = np.zeros(self.n, np.uint8)
        kg.query_rows(Q, self._P, g["h"], g["cell_c"], g["cell_of"], g["cell_nb"], g["cstart"], g["cend"], *g["pool"],
                      self._kth, n_old, mark, self.k, self._nbr, self._d2, self._d0, fail, aff, parts)
        self._nb_rings(rows[fail[rows] != 0])
        return aff

    def _nb_rings(self, rows: np.ndarray) -> None:
        if rows.size:
            from diffuser_lab.backends.numba import growing as kg

            g = self._grid
            tb = g["table"]
            kg.query_rings(rows, self._P, g["h"], tb.keys, tb.vals, tb.bits, g["cstart"], g["cend"], *g["pool"],
                           g["cmin"], g["cmax"], self.k, self._nbr, self._d2, self._d0, self._kth)

    def _nb_add(self, n_old: int) -> np.ndarray:
        from diffuser_lab.backends.numba import growing as kg

        n, k = self.n, self.k
        h2 = self._grid["h"] ** 2
        kth2 = self._kth[:n_old]
        # old rows reaching beyond the block around a new point: checked against the new points directly
        wide = np.flatnonzero(kth2 > h2)
        q = self.CELL_QUANTILE
        if wide.size > 2 * (1 - q) * n_old or np.count_nonzero(kth2 > h2 / 2) < (1 - q) * n_old:
            self.n = n_old  # cell side off the rows' K-th distances: a new grid of the old points
            self._grid_build()
            self.n = n
            h2 = self._grid["h"] ** 2
            wide = np.flatnonzero(kth2 > h2)
        self._grid_add(n_old, n)
        new = np.arange(n_old, n, dtype=np.int64)
        aff = self._nb_rows(new, n_old, mark=True)
        if wide.size:
            # their nearest new point, searched no farther than their own reach (bounds the
            # KD-tree's work for the many far from this add); the few near ones are recomputed
            # by rings, exactly (one at a tie of its K-th distance is reported though unchanged)
            tree = cKDTree(self._P[n_old:n])
            reach = np.sqrt(kth2[wide]) * (1 + 1e-9)
            short = reach <= 2 * self._grid["h"]
            dn = np.full(wide.size, np.inf)
            if short.any():
                dn[short] = tree.query(self._P[wide[short]], k=1, distance_upper_bound=float(reach[short].max()))[0]
            if (~short).any():
                dn[~short] = tree.query(self._P[wide[~short]], k=1)[0]
            aff[wide[dn < reach]] = 1
        rows = np.flatnonzero(aff).astype(np.int64)
        self._d0_before = self._d0[rows].copy()
        far = kth2[rows] > h2
        self._nb_rings(rows[far])  # wide rows: new points may lie beyond the block
        near = rows[~far]
        if near.size:
            g = self._grid
            Q, parts = self._by_cell(near)
            kg.merge_rows(Q, self._P, g["cell_of"], g["cell_nb"], g["cend"], g["fresh"], *g["pool"], k, self._nbr,
                          self._d2, self._d0, self._kth, parts)
        return rows
