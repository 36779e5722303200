"""The first run on a machine (numba's kernel cache empty): the command line does not wait ~25 s
for the kernels; it runs on the numpy/scipy path with the same labels, says so in one line, and
fills the cache in the background so that the next run is compiled. (The <= 8 s wall-time target
of such a run is a benchmark: tests/benchmarks/test_performance.py::test_first_run_cold_cache.)"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from diffuser_lab.backends import numba as nb
from conftest import SMALL_DEMO, run_cli

pytestmark = pytest.mark.skipif(not nb.available(), reason="numba not importable or DIFFUSER_LAB_NUMBA=0")

LINE = "numba kernels are not compiled yet"


def _cold(env) -> bool:
    out = subprocess.run([sys.executable, "-c", "from diffuser_lab.backends import numba as nb; print(nb.cold())"],
                         env=env, capture_output=True, text=True, timeout=120)
    return out.stdout.strip() == "True"


def _lock_released(lock, timeout: float) -> bool:
    """Wait for the compiling process to let go of ``lock`` (it holds an exclusive flock while it
    lives): a shared flock taken on a thread, no polling."""
    import fcntl
    import threading

    try:
        fd = os.open(lock, os.O_RDONLY)
    except FileNotFoundError:  # done and removed already
        return True
    got = threading.Event()
    threading.Thread(target=lambda: (fcntl.flock(fd, fcntl.LOCK_SH), got.set()), daemon=True).start()
    if got.wait(timeout):
        os.close(fd)
        return True
    return False


def _cold_modules() -> set[str]:
    """The modules of the kernels whose empty cache makes a run cold (those
    :func:`diffuser_lab.backends.numba.cold` looks at, the helpers they import among them)."""
    from numba.core.registry import CPUDispatcher

    from diffuser_lab.backends.numba import evidence, grid_knn, morton, weights

    return {v.py_func.__module__.rsplit(".", 1)[-1] for m in (morton, grid_knn, weights, evidence)
            for v in vars(m).values() if isinstance(v, CPUDispatcher)}


def _seed_but_cold(cache) -> int:
    """Copy the suite's own compiled kernels into ``cache`` (numba's layout for NUMBA_CACHE_DIR)
    except those of :func:`_cold_modules`: the cache is cold as a fresh machine's, and the background
    compile does the cold kernels only (the kNN graph's: ~half of the ~50 s). Returns files copied."""
    import hashlib
    import shutil

    src = Path(nb.__file__).resolve().parent
    dst = cache / f"{src.name}_{hashlib.sha1(str(src).encode()).hexdigest()}"  # numba's cache subpath
    dst.mkdir(parents=True, exist_ok=True)
    n, cold = 0, _cold_modules()
    for f in (src / "__pycache__").glob("*.nb[ic]"):
        if f.name.split(".")[0] not in cold:
            shutil.copy2(f, dst / f.name)
            n += 1
    return n


@pytest.mark.slow  # the cold kernels' compile (~25 s) in a process of its own
def test_cold_cache_runs_on_scipy_then_compiles_in_background(tmp_path):
    cache = tmp_path / "numba-cache"
    env = {k: v for k, v in os.environ.items() if k != "DIFFUSER_LAB_NUMBA"}
    env["NUMBA_CACHE_DIR"] = str(cache)
    _seed_but_cold(cache)
    assert _cold(env)

    first = run_cli(*SMALL_DEMO, f"hydra.run.dir={tmp_path / 'first'}", env={"NUMBA_CACHE_DIR": str(cache),
                                                                           "DIFFUSER_LAB_NUMBA": "auto"})
    assert first.returncode == 0, first.stderr
    assert sum(LINE in ln for ln in first.stderr.splitlines()) == 1, first.stderr
    s1 = json.loads((tmp_path / "first" / "summary.json").read_text())
    assert s1["status"] == "ok" and s1["diffusion"]["backend"] == "scipy"

    # the same run compiled (the suite's own, warm cache): the same labels up to float32 ties
    # (1 of 12,748 points here; identical on the default demo)
    compiled = run_cli(*SMALL_DEMO, f"hydra.run.dir={tmp_path / 'compiled'}", env={"DIFFUSER_LAB_NUMBA": "1"})
    assert compiled.returncode == 0, compiled.stderr
    assert json.loads((tmp_path / "compiled" / "summary.json").read_text())["diffusion"]["backend"] == "numba"
    a, b = np.load(tmp_path / "first" / "labels.npy"), np.load(tmp_path / "compiled" / "labels.npy")
    assert a.shape == b.shape and np.mean(a == b) >= 0.999

    lock = cache / "diffuser_lab_warm.lock"
    assert _lock_released(lock, timeout=240), "the background compile (~25 s on 2 cores) did not finish in 240 s"
    assert not lock.exists()
    assert not _cold(env)

    second = run_cli(*SMALL_DEMO, f"hydra.run.dir={tmp_path / 'second'}", env={"NUMBA_CACHE_DIR": str(cache),
                                                                            "DIFFUSER_LAB_NUMBA": "auto"})
    assert second.returncode == 0, second.stderr
    assert LINE not in second.stderr
    assert json.loads((tmp_path / "second" / "summary.json").read_text())["diffusion"]["backend"] == "numba"


def test_forced_or_explicit_backend_compiles_in_the_foreground(tmp_path, monkeypatch):
    from types import SimpleNamespace

    from diffuser_lab.cli import main
    from diffuser_lab.config import SolverBackend

    conf = SimpleNamespace(solver=SimpleNamespace(backend=SolverBackend.numba))
    monkeypatch.setattr(nb, "cold", lambda: True)
    try:
        assert main._defer_compile(conf) is False  # an explicit backend
        monkeypatch.setenv("DIFFUSER_LAB_NUMBA", "1")
        assert main._defer_compile(SimpleNamespace(solver=SimpleNamespace(backend=SolverBackend.auto))) is False
        monkeypatch.setenv("DIFFUSER_LAB_NUMBA", "auto")
        assert main._defer_compile(SimpleNamespace(solver=SimpleNamespace(backend=SolverBackend.auto))) is True
        assert not nb.available()
    finally:
        nb.undefer()
    assert nb.available()


def test_one_background_compile_at_a_time_and_no_stale_lock(tmp_path, monkeypatch):
    """While a compile holds the lock (an exclusive flock) no second one starts; a lock file left
    by a compile that died holds no flock and does not stop the next one."""
    import fcntl
    import subprocess

    started = []
    monkeypatch.setattr(nb, "_lock_path", lambda: tmp_path / "warm.lock")
    monkeypatch.setattr(subprocess, "Popen", lambda argv, **kw: started.append((argv, kw)))
    fd = os.open(tmp_path / "warm.lock", os.O_RDWR | os.O_CREAT)
    fcntl.flock(fd, fcntl.LOCK_EX)  # a compile running
    try:
        assert nb.compile_in_background() is False and not started
    finally:
        os.close(fd)  # it died: the file stays, its lock does not
    assert (tmp_path / "warm.lock").exists()
    assert nb.compile_in_background() is True
    (argv, kw), = started
    assert argv[-2:] == ["diffuser_lab.cli.warm", str(tmp_path / "warm.lock")] and len(kw["pass_fds"]) == 1
