"""Compiled CPU kernels (numba), grouped by what they compute: ``knn.py`` (Morton order, grid
kNN, Eq. 4 weights, the Eqs. 14-15 rows), ``jacobi.py`` (the Jacobi steps of Eq. 10 on threads
meeting at a barrier, ``_sync.py``; generated row kernels in ``_unrolled.py``), ``evidence.py``
(the fused evidence of one frame, Eqs. 1-2) and ``float16.py`` (Z states encoded for run.mcap).

This module is the one switch: numba is used when it is installed and ``DIFFUSER_LAB_NUMBA`` is
not ``0`` (:func:`available`); every kernel has a numpy/scipy twin that runs otherwise. It also
sets how many threads the kernels use (:func:`n_threads`).
"""
from __future__ import annotations

import contextlib
import os


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


NB = _numba()
"""The numba module, or None when the compiled kernels are off."""


def available() -> bool:
    """Whether the compiled kernels can be used (numba installed and not disabled)."""
    return NB is not None


@contextlib.contextmanager
def slp():
    """Compile with LLVM's SLP vectoriser on (numba's default is off)."""
    cfg = NB.config
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
    if NB is None:
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
    if NB is None:
        return 1
    n = int(NB.get_num_threads())
    for cap in (*_thread_cap, _env_cpus()):
        if cap:
            n = min(n, cap)
    return max(1, n)
