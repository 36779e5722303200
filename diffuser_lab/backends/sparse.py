"""Jacobi steps on a sparse per-point class set, for many classes (``solver.sparse_classes``).

Dense Eq. 10 moves N x C scores per step although a point's scores are non-negligible only for
the few classes seen around it. Here every point keeps at most M = ``solver.classes_per_point``
(class, score) slots, in descending order of score. One step of row i:

    y_i = Sum_k P_ik Zhat_{j_k} + B_i          (over the classes in the neighbours' slots and B_i)
    y_i <- 0 where y_i < floor                 (the dense path's floor, module doc of diffusion.py)
    Zhat_i = the M largest entries of y_i, the rest dropped; d_i = the dropped mass Sum (dropped)
    e_i   <- Sum_k P_ik e_{j_k} + d_i          (the error bound, from e = 0)

Cost per step O(N * K * M) instead of O(N * K * C).

The approximation, exactly: P >= 0, B >= 0 and truncation only removes mass, so by induction
0 <= Zhat_t <= Z_t elementwise (Z_t the dense iterate), and the row sums of Z_t - Zhat_t obey
the recurrence of e with equality (the rows of P sum to <= 1), so for every point and class

    Zhat_ic <= Z_ic <= Zhat_ic + e_i.

Nothing is dropped (e = 0, Zhat = Z up to float32 summation order) while no point's neighbourhood
holds more than M classes with scores above the floor; in particular the result is exact when
every point's (T-hop) neighbourhood sees at most M classes. A point's label is certified equal to
the dense one when its top score exceeds its second by more than e_i (``info["certified"]``: the
fraction of points so certified; ``info["error_bound_max"]``: max e_i / max Z). The floors add at
most ``floor`` per entry and step to the bound (1e-18 of max B), as in the dense path.

:class:`SparseClassesJacobi` is the numpy/scipy twin (a sparse-sparse CSR product per step); the
compiled backend is :class:`~diffuser_lab.backends.numba.sparse.NumbaSparseJacobi`.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import scipy.sparse as sp

from diffuser_lab import seeding

from .base import IterationInputs, JacobiBackend


def neighbourhood_classes(inputs: IterationInputs, sample: int = 4096, seed: int = 0) -> float:
    """Mean number of distinct classes with evidence in a point's 1-hop neighbourhood (itself
    included), over a fixed random sample of ``sample`` points: what ``sparse_classes=auto`` looks at."""
    n = inputs.shape[0]
    if n == 0:
        return 0.0
    rows = np.sort(seeding.keyed("sparse.sample", seed).choice(n, size=min(n, sample), replace=False))
    P = sp.csr_matrix((inputs.data, inputs.indices, inputs.indptr), shape=(n, n))[rows]
    P.eliminate_zeros()
    A = (P + sp.csr_matrix((np.ones(len(rows), np.float32), (np.arange(len(rows)), rows)), shape=P.shape)).tocsr()
    A.data[:] = 1.0
    cols = np.unique(A.indices)
    seen = sp.csr_matrix(inputs.B[cols] > 0, dtype=np.float32)
    return float((A[:, cols] @ seen).getnnz(axis=1).mean())


class SparseState:
    """The sparse per-point state in the iteration's row order: cls (N, M) int32 and val (N, M + 1)
    float32 (first cnt[i] valid, on Z / max(B); column M stays 0: the slot a gather of an absent
    class reads), cnt (N,) int32, err (N,) float32 (the bound e), rs (N,) float32 (row sums)."""

    def __init__(self, n: int, m: int):
        self.cls = np.zeros((n, m), np.int32)
        self.val = np.zeros((n, m + 1), np.float32)
        self.cnt = np.zeros(n, np.int32)
        self.err = np.zeros(n, np.float32)
        self.rs = np.zeros(n, np.float32)


class SparseClassesBase(JacobiBackend):
    """What both sparse backends share: B as CSR (iteration order, on Z / scale), the state, Z in
    the paper's units, the drop statistics and the certificate (see module doc)."""

    def __init__(self, inputs: IterationInputs, tol: float, per_point: int, rel: float = 0.0, rows_hint: int = 0):
        self.rel = float(rel)
        self.per_point = int(min(per_point, max(inputs.shape[1], 1)))
        self.dropped = 0.0  # Sum over steps of the dropped mass
        self.kept = 0.0  # Sum over steps of the kept mass
        super().__init__(inputs, tol, rows_hint)

    def setup(self, inputs: IterationInputs) -> None:
        super().setup(inputs)
        n = inputs.shape[0]
        Bc = sp.csr_matrix(inputs.B)
        Bc.data /= inputs.scale
        Bc.data[Bc.data < inputs.floor] = 0.0
        Bc.eliminate_zeros()
        self.bptr, self.bcls, self.bval = Bc.indptr.astype(np.int64), Bc.indices.astype(np.int32), Bc.data.astype(
            np.float32)
        self.state_ = SparseState(n, self.per_point)

    def update(self, inputs: IterationInputs, rows: Optional[np.ndarray] = None,
               moved: Optional[np.ndarray] = None) -> None:
        """Keeps the slots and the error bound (they hold class ids, not columns): rows follow
        ``moved``, new rows start empty."""
        old = self.state_
        self.setup(inputs)
        new = self.state_
        for name in ("cls", "val", "cnt", "err", "rs"):
            a = getattr(old, name)
            if moved is not None:
                a = a[moved]
            getattr(new, name)[: a.shape[0]] = a

    def state(self) -> np.ndarray:
        inp, st = self.inputs, self.state_
        out = np.zeros((inp.shape[0], len(inp.active)), np.float32)
        valid = np.arange(self.per_point)[None, :] < st.cnt[:, None]
        r = np.broadcast_to(np.arange(inp.shape[0])[:, None], valid.shape)[valid]
        out[r, np.searchsorted(inp.active, st.cls[valid])] = st.val[:, :self.per_point][valid]
        return out

    def load(self, Z: np.ndarray) -> None:
        """The M largest scores of each row of ``Z`` (N, A) (error bound 0)."""
        st, M = self.state_, self.per_point
        st.cls[:] = 0
        st.val[:] = 0
        st.err[:] = 0
        if Z.shape[1] == 0:
            st.cnt[:] = 0
            return
        top = np.argsort(-Z, axis=1, kind="stable")[:, :M]
        v = np.take_along_axis(Z, top, 1)
        keep = v > 0
        st.cnt[:] = keep.sum(1)
        st.cls[:, : top.shape[1]] = np.where(keep, self.inputs.active[top], 0)
        st.val[:, : top.shape[1]] = np.where(keep, v, 0)
        st.rs[:] = st.val[:, :M].sum(1)

    def details(self) -> dict:
        return {"backend": self.name, "sparse_classes": self.per_point, "sparse_rel": self.rel}

    def paper_units(self, out: Optional[np.ndarray] = None) -> np.ndarray:
        inp, st = self.inputs, self.state_
        n = inp.shape[0]
        if out is None:
            out = np.zeros(inp.shape, np.float32)
        else:
            out[:] = 0.0  # the kept classes move: no column stays 0
        rows = np.arange(n) if inp.order is None else inp.order
        valid = np.arange(self.per_point)[None, :] < st.cnt[:, None]
        r = np.broadcast_to(rows[:, None], valid.shape)[valid]
        out[r, st.cls[valid]] = st.val[:, :self.per_point][valid] * inp.scale
        return out

    def report(self) -> dict:
        """The approximation of this run (module doc): certified fraction, bound, dropped mass."""
        st, M = self.state_, self.per_point
        v = np.where(np.arange(M)[None, :] < st.cnt[:, None], st.val[:, :M], 0.0)
        top = -np.partition(-v, min(1, M - 1), axis=1)  # the two largest first
        top1 = top[:, 0]
        top2 = top[:, 1] if M > 1 else np.zeros_like(top1)
        certified = np.where(st.cnt > 0, top1 - top2 > st.err, st.err <= 0)
        zmax = float(top1.max()) if len(top1) else 0.0
        return {"certified": float(certified.mean()) if len(certified) else 1.0,
                "error_bound_max": float(st.err.max()) / zmax if zmax > 0 else 0.0,
                "dropped_fraction": self.dropped / (self.dropped + self.kept) if self.kept > 0 else 0.0,
                "classes_kept_mean": float(st.cnt.mean()) if len(st.cnt) else 0.0}

    def error_bound(self) -> np.ndarray:
        """(N,) float32 e_i in the caller's order and the paper's units: Zhat_ic <= Z_ic <= Zhat_ic + e_i."""
        inp = self.inputs
        e = self.state_.err * inp.scale
        if inp.order is None:
            return e
        out = np.empty_like(e)
        out[inp.order] = e
        return out


class SparseClassesJacobi(SparseClassesBase):
    """The numpy/scipy twin: per step one sparse-sparse CSR product P @ Zhat, then top-M per row."""

    name = "scipy-sparse"

    def setup(self, inputs: IterationInputs) -> None:
        super().setup(inputs)
        n, C = inputs.shape
        self.P = sp.csr_matrix((inputs.data, inputs.indices, inputs.indptr), shape=(n, n), copy=True)
        self.P.eliminate_zeros()
        self.B = sp.csr_matrix((self.bval, self.bcls, self.bptr), shape=(n, C))

    def _matrix(self) -> sp.csr_matrix:
        st = self.state_
        n, C = self.inputs.shape
        valid = np.arange(self.per_point)[None, :] < st.cnt[:, None]
        indptr = np.concatenate([[0], np.cumsum(st.cnt, dtype=np.int64)])
        return sp.csr_matrix((st.val[:, :self.per_point][valid], st.cls[valid], indptr), shape=(n, C))

    def step(self) -> tuple[float, float]:
        st, M = self.state_, self.per_point
        n = self.inputs.shape[0]
        old = self._matrix()
        Y = (self.P @ old + self.B).tocsr()
        Y.sum_duplicates()
        Y.data[Y.data < self.inputs.floor] = 0.0
        Y.eliminate_zeros()
        row = np.repeat(np.arange(n), np.diff(Y.indptr))
        order = np.lexsort((-Y.data, row))  # per row, descending score
        rank = np.arange(len(order)) - Y.indptr[row[order]]
        top = np.zeros(n, np.float32)
        np.maximum.at(top, row, Y.data)
        low = Y.data[order] < np.float32(self.rel) * top[row[order]]
        rank = np.where(low, M, rank)  # below rel x the row's largest: dropped like rank >= M
        keep = order[rank < M]
        drop = order[rank >= M]
        d = np.bincount(row[drop], weights=Y.data[drop], minlength=n).astype(np.float32)
        err = (self.P @ st.err).astype(np.float32) + d
        new = SparseState(n, M)
        r, k = row[keep], rank[rank < M]
        new.cls[r, k] = Y.indices[keep]
        new.val[r, k] = Y.data[keep]
        new.cnt[:] = np.bincount(r, minlength=n)
        new.err[:] = err
        self.state_ = new
        self.dropped += float(d.sum(dtype=np.float64))
        self.kept += float(new.val.sum(dtype=np.float64))
        diff = self._matrix() - old
        change = float(np.abs(diff.data).max()) if diff.nnz else 0.0
        top = float(new.val[:, 0].max()) if n else 0.0
        return change, top
