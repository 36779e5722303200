"""Compiled CPU kernels (numba, optional extra ``fast``): the Jacobi step of Eq. 10, the fused
evidence of one frame and the un-permutation of Z (the graph's kernels are in
:mod:`diffuser_lab.knn`). Every kernel has a numpy/scipy twin in :mod:`diffuser_lab.diffusion`
and :mod:`diffuser_lab.evidence`; ``DIFFUSER_LAB_NUMBA=0`` (or numba missing) selects those.

The Jacobi step is the hot loop: for every row ``Z'_i = Sum_k P_ik Z_{j_k} + B_i`` over a
block of W classes. Its row kernels are generated with one scalar accumulator per class
(``_kernels_unrolled.py``, W in 8/16/24/32; regenerate with ``python -m diffuser_lab.kernels``) so
that LLVM's SLP vectoriser turns them into AVX loads and fused multiply-adds; numba leaves SLP
vectorisation off by default, so it is switched on while these kernels compile (:func:`slp`).
Rows are summed in the order of their neighbours, like scipy's CSR product. :class:`StepRunner`
runs them on plain threads, each thread doing a whole run of steps in one compiled call
(``steps_W``) that meets the others at a barrier between steps (atomics in :mod:`._sync`):
no step returns to Python, and none needs the GIL.
"""
from __future__ import annotations

import contextlib
import functools
import os
import queue
import threading
from pathlib import Path

import numpy as np

WIDTHS = (8, 16, 24, 32)
"""Class-block widths of the generated Jacobi kernels; wider problems are split into blocks."""


def _numba():
    if os.environ.get("DIFFUSER_LAB_NUMBA", "1").strip().lower() in ("0", "false", "no", "off"):
        return None
    try:
        import numba
    except ImportError:  # the optional extra is not installed
        return None
    if "NUMBA_THREADING_LAYER" not in os.environ:
        # numba's own thread pool: OpenMP's spinning workers stall every step by milliseconds
        # whenever the other core is busy (measured: 100 steps 2.4 s instead of 0.3 s)
        numba.config.THREADING_LAYER = "workqueue"
    return numba


_NB = _numba()


def available() -> bool:
    """Whether the compiled kernels can be used (numba installed and not disabled)."""
    return _NB is not None


@contextlib.contextmanager
def slp():
    """Compile with LLVM's SLP vectoriser on (numba's default is off)."""
    cfg = _NB.config
    old = cfg.SLP_VECTORIZE
    cfg.SLP_VECTORIZE = 1
    try:
        yield
    finally:
        cfg.SLP_VECTORIZE = old


_thread_cap: list[int] = []  # set by limit_threads()


def _env_cpus() -> int | None:
    """CPUs a scheduler gave this process, when it says so and numba was not told directly:
    Ray sets ``OMP_NUM_THREADS`` to a task's ``num_cpus``, SLURM ``SLURM_CPUS_PER_TASK``
    (joblib sets ``NUMBA_NUM_THREADS`` itself, which numba reads)."""
    if "NUMBA_NUM_THREADS" in os.environ:
        return None
    for var in ("OMP_NUM_THREADS", "SLURM_CPUS_PER_TASK"):
        try:
            n = int(os.environ.get(var, ""))
        except ValueError:
            continue
        if n >= 1:
            return n
    return None


def limit_threads(n: int | None) -> None:
    """Use at most ``n`` threads in the compiled kernels (a sweep job's share of the CPUs); None: no cap."""
    _thread_cap[:] = [int(n)] if n else []


def first_compile(*modules_or_kernels) -> bool:
    """Whether the compiled kernels of the given modules (or the given kernels) will be compiled
    before they run: none of them is compiled in this process yet and numba's on-disk cache
    holds none of them (reads the small cache index files, ~20 us each). A hint for progress
    lines only: a new signature of a cached kernel goes unnoticed, and any doubt says False."""
    if _NB is None:
        return False
    from numba.core.registry import CPUDispatcher

    kernels = []
    for m in modules_or_kernels:
        if isinstance(m, CPUDispatcher):
            kernels.append(m)
        else:
            kernels += [v for v in vars(m).values() if isinstance(v, CPUDispatcher)]
    try:
        for k in kernels:
            if k.overloads:
                return False
            cache_file = getattr(getattr(k, "_cache", None), "_cache_file", None)
            if cache_file is None or cache_file._load_index():  # uncached kernel, or cached entries
                return False
    except Exception:  # noqa: BLE001 - numba internals moved: no hint
        return False
    return bool(kernels)


def n_threads() -> int:
    """Threads of the compiled kernels: numba's count, capped by :func:`limit_threads` and by
    the CPUs a scheduler gave the process (:func:`_env_cpus`); threads give identical results."""
    if _NB is None:
        return 1
    n = int(_NB.get_num_threads())
    for cap in (*_thread_cap, _env_cpus()):
        if cap:
            n = min(n, cap)
    return max(1, n)


# ---------------------------------------------------------------------------------------------
# generated Jacobi row kernels


def generate_source() -> str:
    """Source of ``_kernels_unrolled.py``: one row kernel per width W in :data:`WIDTHS`.

    ``rows_W(nbr, wts, Zf, Znf, Bf, floor, lo, hi)`` computes rows lo..hi-1 of
    ``Zn = P Z + B`` (entries below ``floor`` flushed to 0) for fixed-length rows (``nbr``,
    ``wts``: (N, K) int32 / float32) on flat (N*W,) float32 arrays and returns
    (max |Zn - Z|, max Zn) over those rows. One scalar accumulator per class lets LLVM's SLP
    vectoriser put a row in AVX-512 registers (W = 24: one zmm + one ymm, one FMA each per
    neighbour); the epilogue is written as selects, not branches, so that it vectorises too
    (measured: 1.5 instead of 2.6 ms per step on 30k points, one core). Neighbours are summed in
    row order; ``contract`` lets multiply-add fuse (differences to scipy ~1e-7 relative).
    """
    out = ['"""Generated by ``python -m diffuser_lab.kernels``: do not edit by hand."""',
           "import numpy as np",
           "from numba import njit",
           "",
           "from ._sync import atomic_add, wait_until",
           ""]
    for W in WIDTHS:
        L = ["@njit(cache=True, boundscheck=False, nogil=True, fastmath={'contract'})",
             f"def rows_{W}(nbr, wts, Zf, Znf, Bf, floor, lo, hi):",
             "    K = nbr.shape[1]",
             "    z = np.float32(0.0)"]
        for c in range(W):  # this declaration order vectorises best (measured: 2x on W = 24)
            L += [f"    ch{c} = np.float32(0.0)", f"    tp{c} = np.float32(0.0)"]
        L += ["    for i in range(lo, hi):"]
        L += [f"        a{c} = np.float32(0.0)" for c in range(W)]
        L += ["        for kk in range(K):",
              f"            b = np.uint64(nbr[i, kk]) * np.uint64({W})",
              "            w = wts[i, kk]"]
        L += [f"            a{c} += w * Zf[b + np.uint64({c})]" for c in range(W)]
        L += [f"        ib = np.uint64(i) * np.uint64({W})"]
        L += [f"        v{c} = a{c} + Bf[ib + np.uint64({c})]" for c in range(W)]
        L += [f"        v{c} = v{c} if v{c} >= floor else z" for c in range(W)]
        L += [f"        d{c} = abs(v{c} - Zf[ib + np.uint64({c})])" for c in range(W)]
        L += [f"        ch{c} = d{c} if d{c} > ch{c} else ch{c}" for c in range(W)]
        L += [f"        tp{c} = v{c} if v{c} > tp{c} else tp{c}" for c in range(W)]
        L += [f"        Znf[ib + np.uint64({c})] = v{c}" for c in range(W)]
        L += ["    change = max(" + ", ".join(f"ch{c}" for c in range(W)) + ")",
              "    top = max(" + ", ".join(f"tp{c}" for c in range(W)) + ")",
              "    return change, top", "", ""]
        out += L
        out += [line.format(W=W) for line in _STEPS_TEMPLATE]
    return "\n".join(out).rstrip() + "\n"


_STEPS_TEMPLATE = """\
@njit(cache=True, boundscheck=False, nogil=True)
def steps_{W}(nbr, wts, Za, Zb, Bf, floor, tol, n_steps, chunk, tid, nthreads, ctrl, res):
    n = nbr.shape[0]
    nchunks = (n + chunk - 1) // chunk
    for s in range(n_steps):
        src = Za if s % 2 == 0 else Zb
        dst = Zb if s % 2 == 0 else Za
        ch = np.float32(0.0)
        tp = np.float32(0.0)
        while True:
            c = atomic_add(ctrl, 1 + s, 1)
            if c >= nchunks:
                break
            lo = c * chunk
            a, b = rows_{W}(nbr, wts, src, dst, Bf, floor, lo, min(lo + chunk, n))
            ch = max(ch, a)
            tp = max(tp, b)
        res[s, tid, 0] = ch
        res[s, tid, 1] = tp
        atomic_add(ctrl, 0, 1)
        wait_until(ctrl, 0, (s + 1) * nthreads)
        gch = np.float32(0.0)
        gtp = np.float32(0.0)
        for t in range(nthreads):
            gch = max(gch, res[s, t, 0])
            gtp = max(gtp, res[s, t, 1])
        if (np.float64(gch) / np.float64(gtp) if gtp > 0 else 0.0) <= tol:
            return s + 1
    return n_steps


""".splitlines()
"""``steps_W(nbr, wts, Za, Zb, Bf, floor, tol, n_steps, chunk, tid, nthreads, ctrl, res)``: thread
``tid`` of ``nthreads`` runs up to ``n_steps`` Jacobi steps on (N*W,) blocks, Za -> Zb -> Za ...
Every step's rows are taken ``chunk`` at a time from the ticket counter ``ctrl[1 + s]`` (so a
thread that the OS parks is made up for by the others), each thread writes its (max |Zn - Z|,
max Zn) to ``res[s, tid]`` and all meet at the barrier ``ctrl[0]`` (arrivals, never reset);
after it every thread sees the same residual and stops after the first step whose relative
change is <= ``tol``. Returns the number of steps done."""


_GEN = Path(__file__).with_name("_kernels_unrolled.py")
_STEPS = None


def _step_kernels():
    """{W: steps_W} of the generated module (see :data:`_STEPS_TEMPLATE`)."""
    global _STEPS
    if _STEPS is None:
        from . import _kernels_unrolled as g

        _STEPS = {W: getattr(g, f"steps_{W}") for W in WIDTHS}
    return _STEPS


class StepRunner:
    """Runs Jacobi steps on the calling thread plus ``threads - 1`` helper threads.

    :meth:`run` hands every thread one compiled call (``steps_W``, see :data:`_STEPS_TEMPLATE`)
    that does up to ``n_steps`` steps and meets the others at a barrier inside compiled code, so
    between the iterations an observer wants to see no thread needs the GIL (a recorder holding
    it would otherwise stall each ~1 ms step by up to the interpreter's 5 ms switch interval) and
    no step pays a Python hand-off (numba's ``prange`` costs ~0.5 ms per launch with its
    workqueue layer, a ``ThreadPoolExecutor`` ~0.1 ms: both measured against ~0.6 ms of work per
    step on 30k points). Rows are claimed ``chunk`` at a time, so a core that another thread
    (a recorder) takes for a while is made up for by the others. Helpers wait on a ``SimpleQueue``.

    Args:
        n: number of rows; threads: worker count (default: numba's thread count); rows below
            ``min_rows_per_thread`` per thread run on the calling thread alone; chunk: rows per
            claim (~20 us of work on 30k points: the longest a thread waits at the barrier for
            a running other).
    """

    def __init__(self, n: int, threads: int | None = None, min_rows_per_thread: int = 8000, chunk: int = 512):
        self.threads = max(1, min(threads or n_threads(), n // max(min_rows_per_thread, 1) or 1))
        self.chunk = int(max(1, chunk if self.threads > 1 else max(n, 1)))
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._done: queue.SimpleQueue = queue.SimpleQueue()
        self._helpers = [threading.Thread(target=self._serve, name="diffuser-lab-jacobi", daemon=True)
                         for _ in range(self.threads - 1)]
        for t in self._helpers:
            t.start()

    def _serve(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:
                self._done.put(job())
            except BaseException as exc:  # noqa: BLE001 - re-raised by run() in the caller
                self._done.put(exc)

    def run(self, W: int, nbr, wts, Za, Zb, B, floor, tol: float, n_steps: int) -> np.ndarray:
        """Up to ``n_steps`` Eq. 10 steps on an (N, W) block, ``Za`` -> ``Zb`` -> ``Za`` ...
        (entries below ``floor`` flushed to 0), stopping after the first step whose relative
        change max|Zn - Z| / max Zn is <= ``tol``. Returns (steps done, 2) float32: per step
        (max |Zn - Z|, max Zn); the last state is in ``Zb`` after an odd number, else ``Za``."""
        f = _step_kernels()[W]
        n_steps = int(n_steps)
        nt = self.threads
        ctrl = np.zeros(1 + n_steps, np.int64)
        res = np.zeros((n_steps, nt, 2), np.float32)
        args = (nbr, wts, Za.reshape(-1), Zb.reshape(-1), B.reshape(-1), np.float32(floor), float(tol),
                n_steps, self.chunk)
        with slp():
            for tid in range(1, nt):
                self._jobs.put(functools.partial(f, *args, tid, nt, ctrl, res))
            done = [f(*args, 0, nt, ctrl, res)]
            for _ in self._helpers:
                r = self._done.get()
                if isinstance(r, BaseException):
                    raise r
                done.append(r)
        assert len(set(done)) == 1, done  # every thread stops after the same step
        return res[:done[0]].max(axis=1)

    def step(self, W: int, nbr, wts, Z, Zn, B, floor) -> tuple[float, float]:
        """One step: Zn <- floor(P Z + B); returns (max|Zn - Z|, max Zn)."""
        ch, tp = self.run(W, nbr, wts, Z, Zn, B, floor, -1.0, 1)[0]
        return float(ch), float(tp)

    def close(self) -> None:
        for _ in self._helpers:
            self._jobs.put(None)
        for t in self._helpers:
            t.join(timeout=5.0)  # a helper left at a barrier by an interrupted caller is a daemon
        self._helpers = []

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def fixed_rows(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CSR -> (N, K) int32 neighbours and float32 weights, K = longest row; shorter rows are
    padded with weight 0 on the row itself (no copy when every row has K entries)."""
    n = len(indptr) - 1
    lens = np.diff(indptr)
    k = int(lens.max()) if n else 0
    if n and (lens == k).all():
        return indices.astype(np.int32, copy=False).reshape(n, k), data.astype(np.float32, copy=False).reshape(n, k)
    nbr = np.repeat(np.arange(n, dtype=np.int32)[:, None], max(k, 1), 1)
    wts = np.zeros((n, max(k, 1)), np.float32)
    rows = np.repeat(np.arange(n), lens)
    slot = np.arange(len(indices)) - np.repeat(indptr[:-1], lens)
    nbr[rows, slot] = indices
    wts[rows, slot] = data
    return nbr, wts


# ---------------------------------------------------------------------------------------------
# un-permuting Z and the fused evidence of one frame (the kNN and the edge weights of the graph
# are compiled in :mod:`diffuser_lab.knn`)

if _NB is not None:
    from numba import njit, prange

    @njit(cache=True, parallel=True, boundscheck=False)
    def _unpermute_scaled(Zs, order, active, scale, out):
        """out[order[i], active[c]] = Zs[i, c] * scale (float32)."""
        n = Zs.shape[0]
        na = active.shape[0]
        for i in prange(n):
            o = order[i]
            for c in range(na):
                out[o, active[c]] = Zs[i, c] * scale

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

    @njit(cache=True, parallel=True, boundscheck=False)
    def _evidence_hard(pts, R, t, K, depth, labels, tol, mass, links, seen):
        n = pts.shape[0]
        h, w = depth.shape
        for i in prange(n):
            x, y, z = np.float64(pts[i, 0]), np.float64(pts[i, 1]), np.float64(pts[i, 2])
            xc = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]
            yc = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]
            zc = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
            seen[i] = False
            if not zc > 1e-6:
                continue
            u = K[0, 0] * (xc / zc) + K[0, 1] * (yc / zc) + K[0, 2]
            v = K[1, 1] * (yc / zc) + K[1, 2]
            col = np.rint(u)
            row = np.rint(v)
            if not (col >= 0 and col < w and row >= 0 and row < h):
                continue
            r, c = int(row), int(col)
            d = depth[r, c]
            if not (d > 0 and abs(zc - d) <= tol):
                continue
            seen[i] = True
            lab = labels[r, c]
            if lab >= 0:
                mass[i, lab] += 1.0
                links[i] += 1


def transpose_into(a: np.ndarray, out: np.ndarray) -> None:
    """out[...] = a.T for a 2-D ``a`` (M, C) and a C-contiguous ``out`` (C, M) of the same dtype:
    compiled for float32 (4x numpy's strided copy at 51k x 20), numpy otherwise."""
    if _NB is not None and a.dtype == np.float32 and out.dtype == np.float32 and a.flags.c_contiguous:
        _transpose_f32(a, out)
    else:
        np.copyto(out, a.T)


def to_float16(a: np.ndarray) -> np.ndarray | None:
    """``a.astype("<f2")`` for C-contiguous float32 ``a``, bit for bit, compiled (numpy takes a
    slow path for values that become float16 subnormals: ~50 ms on a 1M-value Z state); None
    without numba."""
    if _NB is None or a.dtype != np.float32 or not a.flags.c_contiguous:
        return None
    out = np.empty(a.shape, "<f2")
    _f32_to_f16_bits(a.reshape(-1).view(np.uint32), out.reshape(-1).view(np.uint16))
    return out


def unpermute_scaled(Zs, order, active, scale, out):
    _unpermute_scaled(Zs, order, active, np.float32(scale), out)


def evidence_hard(points, frame_R, frame_t, K, depth, labels, depth_tol, mass, links):
    """Project, depth-check and add one frame's hard labels in one pass; returns (N,) bool seen."""
    seen = np.empty(len(points), np.bool_)
    _evidence_hard(points, frame_R, frame_t, K, depth, labels, float(depth_tol), mass, links, seen)
    return seen


if __name__ == "__main__":  # regenerate the unrolled kernels
    _GEN.write_text(generate_source())
    print(f"wrote {_GEN}")
