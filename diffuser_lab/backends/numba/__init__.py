"""Compiled CPU kernels (numba), grouped by what they compute: ``morton.py`` (Morton order),
``grid_knn.py`` (the batch grid kNN), ``growing.py`` (the growing map's grid kNN),
``cell_search.py`` (the ring search both grids share), ``weights.py`` (Eq. 4), ``hashing.py``
and ``voxel_map.py`` (hash tables, the growing map's voxel merge), ``normalise.py`` (the rows of
Eqs. 14-15), ``jacobi.py`` (the Jacobi steps of Eq. 10 on threads
meeting at a barrier, ``_sync.py``; generated row kernels and step loops in ``_unrolled.py``, the
explicit 16-lane vectors they use in ``_zmm.py``), ``evidence.py``
(the fused evidence of one frame, Eqs. 1-2) and ``float16.py`` (Z states encoded for run.mcap).

This module is the one switch: numba is used when it is installed and ``DIFFUSER_LAB_NUMBA`` is
not ``0`` (:func:`available`); every kernel has a numpy/scipy twin that runs otherwise. It also
sets how many threads the kernels use (:func:`n_threads`).

Compiling the kernels takes ~25 s once per machine (numba caches them on disk). The command line
does not make a user wait for that: on an empty cache (:func:`cold`) its run takes the numpy/scipy
path (:func:`defer_compile`; same labels, 3-6x slower diffusion) and, once it has finished, fills
the cache in a background process (:func:`compile_in_background`, ``python -m
diffuser_lab.cli.warm``). ``DIFFUSER_LAB_NUMBA=1`` compiles in the foreground instead.
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


_deferred: list[bool] = []  # set by defer_compile()


def available() -> bool:
    """Whether the compiled kernels are used (numba installed, not disabled, not deferred)."""
    return NB is not None and not _deferred


def forced() -> bool:
    """Whether ``DIFFUSER_LAB_NUMBA=1`` asks for the compiled kernels even on an empty cache."""
    return os.environ.get("DIFFUSER_LAB_NUMBA", "").strip().lower() in ("1", "true", "yes", "on")


def defer_compile() -> None:
    """Use the numpy/scipy twins in this process (until :func:`undefer`): the kernels are not compiled here."""
    _deferred[:] = [True]


def undefer() -> None:
    _deferred[:] = []


def cold() -> bool:
    """Whether numba's on-disk cache holds none of the kernels a run needs first (the kNN graph
    and the evidence kernels), i.e. the next run would compile them (~25 s)."""
    if NB is None:
        return False
    from . import evidence, grid_knn, morton, weights

    return first_compile(morton, grid_knn, weights, evidence)


def _lock_path():
    from pathlib import Path

    base = Path(NB.config.CACHE_DIR) if NB.config.CACHE_DIR else Path(__file__).with_name("__pycache__")
    return base / "diffuser_lab_warm.lock"


def compile_in_background() -> bool:
    """Start ``python -m diffuser_lab.cli.warm`` detached (its output discarded) unless one is
    already running; it fills numba's cache for the next runs. True if one was started.

    The lock file (:func:`_lock_path`) is held with ``flock`` by the compiling process for as long as
    it lives (it inherits the locked descriptor), so a compile that died leaves no stale lock, and
    whoever wants to wait for the compile takes a shared ``flock`` on the file."""
    import subprocess
    import sys

    lock = _lock_path()
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock; the cache tolerates two compiles
        fcntl = None
    fd = -1
    try:
        lock.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        if fcntl is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:  # one compiling already
                return False
        os.ftruncate(fd, 0)
        os.write(fd, str(os.getpid()).encode())
        env = {k: v for k, v in os.environ.items() if k != "DIFFUSER_LAB_NUMBA"}
        subprocess.Popen([sys.executable, "-m", "diffuser_lab.cli.warm", str(lock)],
                         stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                         start_new_session=True, env=env, close_fds=True, pass_fds=(fd,))
    except OSError:  # a read-only install: the next run compiles in the foreground
        return False
    finally:
        if fd >= 0:
            os.close(fd)  # the lock stays with the child's copy of the descriptor
    return True


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


def parts(n: int) -> int:
    """Chunks for a parallel loop over n rows (several per thread, for balance)."""
    return max(1, min(n_threads() * 8, n // 512 + 1))
