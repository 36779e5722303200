"""A growing point set's kNN graph (paper Eqs. 3-4), extended frame by frame for the online protocol
instead of rebuilt (its points come from :class:`~diffuser_lab.data.voxel_map.VoxelMap`).

:class:`IncrementalKnnGraph` appends the new points and keeps the graph equal to
:func:`~diffuser_lab.method.graph.build_graph` on the same points (neighbour sets per row, up to
which of the points tied at the K-th distance a row keeps: the smaller index, which is the
insertion index here and the Morton index there): the new rows get their K nearest among all
points, and an old row is recomputed only when a new point is strictly closer than its K-th
neighbour (points only arrive, so no other row can change).

The rows and their weights are computed by a backend (:func:`diffuser_lab.backends.growing.rows_backend`,
decided when a graph is made): a compiled hash grid, or scipy's cKDTree (rebuilt per add; slower,
the same rows element for element, by the rule of :mod:`diffuser_lab.backends.knn`).
"""
from __future__ import annotations

import numpy as np

from diffuser_lab.backends.growing import rows_backend
from diffuser_lab.backends.knn import sq_dist


class IncrementalKnnGraph:
    """K-nearest-neighbour graph of a growing point set, rows in insertion order (capacity grows
    by doubling). Same definition as :func:`~diffuser_lab.method.graph.build_graph`: K nearest by
    Euclidean distance (self excluded, duplicates kept), rows by (d2, index) with the insertion
    index (the rule of :mod:`diffuser_lab.backends.knn`), Eq. 4 weights.

    While the set has at most K points, a row has fewer than K real neighbours: the missing
    entries are the row's own index with squared distance inf and weight 0 (row sums count only
    real neighbours).

    Attributes (views of the first ``n`` rows):
        n: points so far; k.
        points: (n, 3) float32 world points, metres; normals: (n, 3) float32 or None.
        neighbors: (n, K) int32, each row ascending by (squared distance, index).
        dist2: (n, K) float64 squared distances of those neighbours, m^2.
        weights: (n, K) float32 Eq. 4 with the current sigma_d; row_sums: (n,) float64.
        rho: mean distance of a point to its nearest distinct neighbour (0 distances skipped),
            maintained from each row's nearest distinct distance; nan until one exists.
        sigma_d: the bandwidth of the weights: the given one, or sigma_d_factor * rho_w with
            rho_w the rho at the last weight refresh (refreshed when rho moves more than rho_tol);
            with ``rho_tol=None`` the current rho, new and changed rows weighted with it, the other
            rows when the caller asks (:meth:`reweigh`; :meth:`refresh_weights`: every row).
    """

    def __init__(self, k: int = 24, *, sigma_s: float = 0.2, sigma_d: float | None = None, sigma_d_factor: float = 2.0,
                 invariant_normals: bool = False, rho_tol: float | None = 0.02):
        if k < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        self.k = int(k)
        self.sigma_s = float(sigma_s)
        self._sigma_d_fixed = None if sigma_d is None else float(sigma_d)
        self.sigma_d_factor = float(sigma_d_factor)
        self.invariant_normals = bool(invariant_normals)
        self.rho_tol = None if rho_tol is None else float(rho_tol)
        self.n = 0
        self.refreshed: np.ndarray | None = None  # the last add refreshed every weight: the rows its points changed
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
        self._rows = rows_backend(self.k)
        self._nb = self._rows.compiled

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
        self._cap = cap

    def _arrays(self) -> tuple:
        """What the rows backend reads and writes (see :mod:`diffuser_lab.backends.growing`)."""
        return self._P, self._nbr, self._d2, self._d0, self._kth

    # --- the update ---
    def add(self, points: np.ndarray, normals: np.ndarray | None) -> np.ndarray:
        """Append (m, 3) float32 world points (and (m, 3) unit normals, or None: given with every
        add or with none) and update the graph.

        Returns:
            (r,) int64 sorted indices of every row whose neighbours or weights changed: the new
            rows, the old rows a new point entered, or every row when the weights were refreshed
            because rho moved by more than rho_tol (then :attr:`refreshed` holds the former, else None).
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
        self.refreshed = None
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
            self._rows.build(self._arrays(), n)
            self._resum_rho()
        else:  # the new rows, then the old rows a new point entered
            old_rows = self._rows.extend(self._arrays(), n_old, n)
            d0_before = self._d0[old_rows]
            self._rows.update(self._arrays(), old_rows)
            changed = np.concatenate([old_rows, np.arange(n_old, n, dtype=np.int64)])
            self._update_rho(changed, np.concatenate([d0_before, np.full(m, np.inf)]))
        if self._sigma_d_fixed is None and self.rho_tol is None:  # sigma_d follows rho; rows take it as they change
            if self._rcnt:
                self._rho_w = self.rho
                self.sigma_d = self.sigma_d_factor * self._rho_w
            else:
                self._w[changed] = 0
                self._ws[changed] = 0
                return changed
        elif self._sigma_d_fixed is None:
            rho = self.rho
            if self._rcnt and (self._rho_w is None or abs(rho - self._rho_w) > self.rho_tol * self._rho_w):
                self.refresh_weights()
                self.refreshed = changed  # the rows the points changed (every weight moved a little)
                return np.arange(n, dtype=np.int64)
            if self._rho_w is None:  # no distinct neighbour yet: no bandwidth
                self._w[changed] = 0
                self._ws[changed] = 0
                return changed
        self._weights(changed)
        return changed

    def reweigh(self, rows: np.ndarray) -> None:
        """Eq. 4 for ``rows`` (int64) with the current sigma_d (``rho_tol=None``: the rows the
        points did not change keep the sigma_d of their last change until the caller brings them here)."""
        if self._rho_w is not None or self._sigma_d_fixed is not None:
            self._weights(np.asarray(rows, np.int64))

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
        self._rows.weights(rows, self._nbr, self._d2, self._N if self._use_n else None, self.invariant_normals,
                           self.sigma_d, self.sigma_s, self._w, self._ws)

    def _small(self) -> None:
        """Every row of a set of n <= K points: all others by (d2, index), then the row itself at inf."""
        n, k = self.n, self.k
        p = self._P[:n]
        d2 = sq_dist(p[:, None, :], p[None, :, :])  # the rule of every kNN row
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
