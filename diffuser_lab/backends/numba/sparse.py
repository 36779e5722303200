"""Compiled Jacobi steps on a sparse per-point class set (``solver.sparse_classes``; the numpy twin
and the approximation are in :mod:`diffuser_lab.backends.sparse`).

Every point keeps at most M (class, score) slots. A step of row i gathers its neighbours' slots
and its own evidence B_i into a per-thread dense accumulator of C floats (classes stamped with the
row they were last touched for; the touched entries are zeroed after the row), flushes scores below the
floor, keeps the M largest and adds what it dropped to the row's error bound
``e_i <- Sum_k P_ik e_{j_k} + dropped_i``. Cost per row O(K * M), independent of C.
Threads: :class:`~diffuser_lab.backends.numba.jacobi.StepRunner` (same barrier and row claiming).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from ..sparse import SparseClassesBase, SparseState
from . import first_compile
from ._sync import all_converged, atomic_add, wait_until
from .jacobi import StepRunner, fixed_rows

RES = 4
"""Per step and thread: max |Zn - Z|, max Zn, dropped mass (sum), kept mass (sum)."""


@njit(cache=True, boundscheck=False, nogil=True)
def sparse_rows(nbr, wts, cls, val, cnt, err, rs, ncls, nval, ncnt, nerr, nrs, bptr, bcls, bval, floor, rel, lo, hi,
                key0, acc, stamp, oldv, ostamp, touched):
    """Rows lo..hi-1 of one step (see module doc); returns (change, top, dropped, kept) over them.
    ``key0 + i`` stamps row i's classes in the scratch arrays (unique across steps: no clearing)."""
    K = nbr.shape[1]
    M = cls.shape[1]
    z = np.float32(0.0)
    change = z
    top = z
    dropped = np.float64(0.0)
    kept = np.float64(0.0)
    for i in range(lo, hi):
        key = key0 + i
        t = 0
        e = z
        for kk in range(K):
            j = nbr[i, kk]
            w = wts[i, kk]
            e += w * err[j]
            for s in range(cnt[j]):  # branch-free: acc is all zero between rows
                c = cls[j, s]
                acc[c] += w * val[j, s]
                touched[t] = c
                t += np.int64(stamp[c] != key)
                stamp[c] = key
        for p in range(bptr[i], bptr[i + 1]):
            c = bcls[p]
            acc[c] += bval[p]
            touched[t] = c
            t += np.int64(stamp[c] != key)
            stamp[c] = key
        for s in range(cnt[i]):  # the row's previous state, for the change
            oldv[cls[i, s]] = val[i, s]
            ostamp[cls[i, s]] = key
        # keep the M largest scores >= max(floor, rel * the row's largest): insertion into a
        # list of at most M by (descending score, class), so an exact tie keeps the lower class
        # (as the numpy twin's stable sort); what falls below rel is dropped mass, below floor flushed
        cut = z
        if rel > 0:
            for q in range(t):
                v = acc[touched[q]]
                cut = v if v > cut else cut
            cut *= rel
        n = 0
        d = z
        for q in range(t):
            c = touched[q]
            v = acc[c]
            acc[c] = z
            if v < floor:
                continue
            if v < cut:
                d += v
                continue
            if n < M:
                p = n
                n += 1
            elif v > nval[i, M - 1] or (v == nval[i, M - 1] and c < ncls[i, M - 1]):
                d += nval[i, M - 1]
                p = M - 1
            else:
                d += v
                continue
            while p > 0 and (nval[i, p - 1] < v or (nval[i, p - 1] == v and ncls[i, p - 1] > c)):
                nval[i, p] = nval[i, p - 1]
                ncls[i, p] = ncls[i, p - 1]
                p -= 1
            nval[i, p] = v
            ncls[i, p] = c
        ncnt[i] = n
        nerr[i] = e + d
        dropped += d
        # change max |Zn - Z| over the union of old and new entries
        row = np.float32(0.0)
        for s in range(n):
            c = ncls[i, s]
            v = nval[i, s]
            row += v
            top = v if v > top else top
            o = oldv[c] if ostamp[c] == key else z
            ostamp[c] = -1  # matched
            dv = abs(v - o)
            change = dv if dv > change else change
        nrs[i] = row
        kept += row
        for s in range(cnt[i]):
            c = cls[i, s]
            if ostamp[c] == key:  # an old entry that is no longer kept
                dv = val[i, s]
                change = dv if dv > change else change
    return change, top, dropped, kept


@njit(cache=True, boundscheck=False, nogil=True)
def index_rows(nbr, cls, cnt, bptr, bcls, bval, idx, bsel, bout, lo, hi, key0, stamp, pos):
    """For rows lo..hi-1 and their current class sets: idx[i, k, s] = the slot of class cls[i, s]
    in neighbour k's row (M = the always-zero slot when it has none), bsel[i, s] = B_i of that
    class, bout[i] = the evidence outside the set (dropped by every fixed-set step)."""
    K = nbr.shape[1]
    M = cls.shape[1]
    for i in range(lo, hi):
        key = key0 + i
        for s in range(M):
            bsel[i, s] = 0.0
        for s in range(cnt[i]):
            stamp[cls[i, s]] = key
            pos[cls[i, s]] = s
        out = np.float32(0.0)
        for p in range(bptr[i], bptr[i + 1]):
            c = bcls[p]
            if stamp[c] == key:
                bsel[i, pos[c]] = bval[p]
            else:
                out += bval[p]
        bout[i] = out
        for kk in range(K):
            j = nbr[i, kk]
            for s in range(M):
                idx[i, kk, s] = M
            for s2 in range(cnt[j]):
                c = cls[j, s2]
                if stamp[c] == key:
                    idx[i, kk, pos[c]] = s2


@njit(cache=True, boundscheck=False, nogil=True, fastmath={'contract'})
def fixed_rows_step(nbr, wts, idx, cls, val, cnt, err, rs, ncls, nval, ncnt, nerr, nrs, bsel, bout, floor, lo, hi):
    """Rows lo..hi-1 of a step on fixed class sets: gathers only (``idx``), no search, no
    selection; the dropped mass is what flows to classes outside the set:
    Sum_k P_ik rs_{j_k} + Sum_c B_ic - (kept). Returns (change, top, dropped, kept)."""
    K = nbr.shape[1]
    M = cls.shape[1]
    z = np.float32(0.0)
    change = z
    top = z
    dropped = np.float64(0.0)
    kept = np.float64(0.0)
    acc = np.empty(M, np.float32)
    for i in range(lo, hi):
        for s in range(M):
            acc[s] = z
        e = z
        r = z
        for kk in range(K):
            j = nbr[i, kk]
            w = wts[i, kk]
            e += w * err[j]
            r += w * rs[j]
            for s in range(M):
                acc[s] += w * val[j, idx[i, kk, s]]
        row = z
        m = cnt[i]
        for s in range(m):
            v = acc[s] + bsel[i, s]
            v = v if v >= floor else z
            dv = abs(v - val[i, s])
            change = dv if dv > change else change
            top = v if v > top else top
            row += v
            nval[i, s] = v
            ncls[i, s] = cls[i, s]
        ncnt[i] = m
        d = r + bout[i]
        for s in range(M):
            d += bsel[i, s]
        d = d - row
        d = d if d > z else z
        nrs[i] = row
        nerr[i] = e + d
        dropped += d
        kept += row
    return change, top, dropped, kept


@njit(cache=True, boundscheck=False, nogil=True)
def sparse_steps(nbr, wts, cA, vA, nA, eA, rA, cB, vB, nB, eB, rB, bptr, bcls, bval, idx, bsel, bout, n_classes,
                 floor, rel, refresh, step0, tol, n_steps, chunk, tid, nthreads, ctrl, res):
    """Thread ``tid`` of ``nthreads`` runs up to ``n_steps`` steps, state A -> B -> A ...; step
    ``step0 + s`` re-selects the class sets (:func:`sparse_rows`) when it is a multiple of
    ``refresh`` and then rebuilds the gather index (:func:`index_rows`), the others keep them
    (:func:`fixed_rows_step`). Rows are claimed ``chunk`` at a time from the ticket counters
    ``ctrl[1 + 2 s]`` and ``ctrl[2 + 2 s]``, the threads meet at the barrier ``ctrl[0]`` (as
    ``steps_W`` of :mod:`~diffuser_lab.backends.numba.jacobi`). Returns the steps done."""
    n = nbr.shape[0]
    nchunks = (n + chunk - 1) // chunk
    acc = np.zeros(n_classes, np.float32)  # zero between rows
    oldv = np.zeros(n_classes, np.float32)
    stamp = np.full(n_classes, -1, np.int64)
    ostamp = np.full(n_classes, -1, np.int64)
    pos = np.zeros(n_classes, np.int64)
    touched = np.empty(nbr.shape[1] * cA.shape[1] + n_classes, np.int32)
    barriers = 0
    for s in range(n_steps):
        even = s % 2 == 0
        select = (step0 + s) % refresh == 0
        ch = np.float32(0.0)
        tp = np.float32(0.0)
        dr = 0.0
        kp = 0.0
        while True:
            c = atomic_add(ctrl, 1 + 2 * s, 1)
            if c >= nchunks:
                break
            lo = c * chunk
            hi = min(lo + chunk, n)
            if select and even:
                a, b, d, k = sparse_rows(nbr, wts, cA, vA, nA, eA, rA, cB, vB, nB, eB, rB, bptr, bcls, bval, floor,
                                         rel, lo, hi, 2 * (step0 + s) * n, acc, stamp, oldv, ostamp, touched)
            elif select:
                a, b, d, k = sparse_rows(nbr, wts, cB, vB, nB, eB, rB, cA, vA, nA, eA, rA, bptr, bcls, bval, floor,
                                         rel, lo, hi, 2 * (step0 + s) * n, acc, stamp, oldv, ostamp, touched)
            elif even:
                a, b, d, k = fixed_rows_step(nbr, wts, idx, cA, vA, nA, eA, rA, cB, vB, nB, eB, rB, bsel, bout,
                                             floor, lo, hi)
            else:
                a, b, d, k = fixed_rows_step(nbr, wts, idx, cB, vB, nB, eB, rB, cA, vA, nA, eA, rA, bsel, bout,
                                             floor, lo, hi)
            ch = max(ch, a)
            tp = max(tp, b)
            dr += d
            kp += k
        res[s, tid, 0] = ch
        res[s, tid, 1] = tp
        res[s, tid, 2] = dr
        res[s, tid, 3] = kp
        barriers += 1
        atomic_add(ctrl, 0, 1)
        wait_until(ctrl, 0, barriers * nthreads)
        if select and refresh > 1:  # the gather index of the new sets (all rows' sets are known now)
            while True:
                c = atomic_add(ctrl, 2 + 2 * s, 1)
                if c >= nchunks:
                    break
                lo = c * chunk
                hi = min(lo + chunk, n)
                if even:
                    index_rows(nbr, cB, nB, bptr, bcls, bval, idx, bsel, bout, lo, hi, (2 * (step0 + s) + 1) * n,
                               stamp, pos)
                else:
                    index_rows(nbr, cA, nA, bptr, bcls, bval, idx, bsel, bout, lo, hi, (2 * (step0 + s) + 1) * n,
                               stamp, pos)
            barriers += 1
            atomic_add(ctrl, 0, 1)
            wait_until(ctrl, 0, barriers * nthreads)
        if all_converged(res, s, nthreads, tol):
            return s + 1
    return n_steps


class NumbaSparseJacobi(SparseClassesBase):
    """Sparse class-set steps (:mod:`diffuser_lab.backends.sparse`) compiled, on :class:`StepRunner`
    threads; all ``count`` steps and the stopping rule in one compiled call per thread."""

    name = "numba-sparse"

    def __init__(self, inputs, tol: float, per_point: int, rel: float = 0.0, refresh: int = 4, rows_hint: int = 0):
        self.refresh = max(1, int(refresh))
        self.done = 0
        self.runner = StepRunner(max(inputs.shape[0], int(rows_hint)))
        super().__init__(inputs, tol, per_point, rel, rows_hint)

    def setup(self, inputs) -> None:
        super().setup(inputs)
        n, M = inputs.shape[0], self.per_point
        self.nbr, self.wts = fixed_rows(inputs.indptr, inputs.indices, inputs.data)
        self.other = SparseState(n, M)
        k = self.nbr.shape[1] if self.refresh > 1 else 0
        self.idx = np.zeros((n, k, M), np.uint8 if M < 255 else np.uint16)
        self.bsel = np.zeros((n, M if k else 0), np.float32)
        self.bout = np.zeros(n if k else 0, np.float32)
        self.done = 0  # the next step re-selects the class sets (the fixed-set steps' index is stale)

    def details(self) -> dict:
        return {**super().details(), "sparse_refresh": self.refresh}

    @property
    def compiling(self) -> bool:
        return first_compile(sparse_steps)

    def steps(self, count: int) -> np.ndarray:
        if self.tracking is not None:  # statistics beside each step, on the row-order state (base class)
            return super().steps(count)
        return self._compiled_steps(count)

    def step(self) -> tuple[float, float]:
        change, top = self._compiled_steps(1)[0]
        return float(change), float(top)

    def _compiled_steps(self, count: int) -> np.ndarray:
        a, b = self.state_, self.other
        args = (self.nbr, self.wts, a.cls, a.val, a.cnt, a.err, a.rs, b.cls, b.val, b.cnt, b.err, b.rs, self.bptr,
                self.bcls, self.bval, self.idx, self.bsel, self.bout, int(self.inputs.shape[1]),
                np.float32(self.inputs.floor), np.float32(self.rel), self.refresh, self.done, float(self.tol))
        res = self.runner.launch(sparse_steps, args, count, RES, tickets=2)
        self.done += len(res)
        if len(res) % 2:
            self.state_, self.other = b, a
        self.dropped += float(res[:, :, 2].sum(dtype=np.float64))
        self.kept += float(res[:, :, 3].sum(dtype=np.float64))
        return np.ascontiguousarray(res[:, :, :2].max(axis=1))

    def close(self) -> None:
        self.runner.close()
