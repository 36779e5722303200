import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest_plugins = ["hangs"]  # a hang, in C code too, fails with its stack (tests/hangs.py)

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared"

# The suite compiles numba's kernels in the foreground: a CLI run in a subprocess would otherwise
# take the numpy/scipy path while the cache is cold (tests/cli/test_first_run.py covers that path).
os.environ.setdefault("DIFFUSER_LAB_NUMBA", "1")

if os.environ.get("PYTEST_XDIST_WORKER"):
    # Workers run side by side, as a sweep's jobs do: each gets its share of the cores for the compiled
    # kernels and BLAS (two-thread barriers and OpenBLAS's spinning workers on a core the other worker
    # is using cost more than they gain). BLAS through threadpoolctl in this process, so that a test can
    # still raise it (tests/method/test_online.py); through the environment for the commands it starts.
    import numpy  # noqa: F401 - loads OpenBLAS with the machine's thread count before the variables below

    _share = str(max(1, len(os.sched_getaffinity(0)) // int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))))
    for _var in ("NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
        os.environ.setdefault(_var, _share)
    import threadpoolctl

    threadpoolctl.threadpool_limits(int(_share))

# Small demo settings for tests that only need the mechanics (seconds, not tens of seconds).
SMALL_DEMO = ["scene.options.n_views=10", "scene.options.point_spacing=0.08", "solver.max_iter=60"]


QUICK_BUDGET_S = 5.0
"""A test without the ``slow`` marker should take at most this (its call, on 2 cores): the quick loop
(``-m "not slow"``) stays under 90 s. The suite lists the ones over it at the end (docs/testing.md)."""


@pytest.hookimpl(tryfirst=True)
def pytest_configure(config):
    # benchmarks time one process: pytest-benchmark switches itself off under xdist
    if config.getoption("benchmark_enable", False) and getattr(config.option, "numprocesses", None):
        config.option.numprocesses = None
        config.option.dist = "no"
    config.prewarm = _start_prewarm(config)


def _start_prewarm(config) -> list:
    """In xdist's controller, on an empty numba cache: tests/prewarm.py's two halves, started now;
    the scheduler hands out work once they are done (:func:`pytest_xdist_make_scheduler`)."""
    if hasattr(config, "workerinput") or not getattr(config.option, "numprocesses", None) \
            or config.getoption("collectonly"):
        return []
    from diffuser_lab.backends import numba as nb

    if not nb.available() or not nb.cold():
        return []
    return [subprocess.Popen([sys.executable, str(ROOT / "tests" / "prewarm.py"), part], cwd=ROOT,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for part in ("graph", "rest")]


def work_unit(nodeid: str) -> str:
    """What pytest-xdist hands a worker at once: a test module (its module-scoped fixtures, a run
    many tests read, are made once), or one chain of the README's commands
    (``readme_commands.chain``: commands reading each other's outputs)."""
    path, _, rest = nodeid.partition("::")
    if path.endswith("test_readme.py") and rest.startswith("test_readme_command["):
        from readme_commands import readme_chains

        cid = rest[len("test_readme_command["):-1]
        return f"{path}::{readme_chains().get(cid, cid)}"
    return path


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile`` (pyproject.toml) with the README's chains as units of their own
    (pytest 9's node ids cannot carry xdist_group's suffix, so loadgroup cannot group them)."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class Units(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return work_unit(nodeid)

        def schedule(self) -> None:
            for proc in getattr(config, "prewarm", []):  # the kernels compiled once, on both cores
                proc.wait()
            config.prewarm = []
            super().schedule()

    return Units(config, log)


def pytest_collection_modifyitems(config, items):
    """The work units (:func:`work_unit`) with a slow test first, stable otherwise (with
    ``--no-loadscope-reorder`` xdist hands the units out in this order): the long ones start while
    every worker still has short ones to fill in with, so the workers finish together."""
    slow = {work_unit(item.nodeid) for item in items if item.get_closest_marker("slow") is not None}
    items.sort(key=lambda item: work_unit(item.nodeid) not in slow)


@pytest.fixture(autouse=True)
def _environment_given_back():
    """os.environ as it was before each test: what a test's code sets in this process (ray.init's
    KMP_DUPLICATE_LIB_OK and PYTHONBREAKPOINT, a sweep's job count) stays with that test. Left behind,
    it made every later command of the worker differ from its command-line server's environment
    (:func:`run_cli`), so each ran in a fresh interpreter (tests/cli/test_bad_input.py after
    test_verify.py's Ray run: 30 -> 82 s)."""
    before = dict(os.environ)
    yield
    if dict(os.environ) != before:
        os.environ.clear()
        os.environ.update(before)


_over_budget: list[tuple[float, str]] = []
_unit_seconds: dict[str, float] = {}


def pytest_runtest_logreport(report):
    # setup + call + teardown of each work unit: what the suite's 10 minutes are spent on (CI prints it)
    _unit_seconds[work_unit(report.nodeid)] = _unit_seconds.get(work_unit(report.nodeid), 0.0) + report.duration
    if report.when == "call" and report.passed and report.duration > QUICK_BUDGET_S \
            and "slow" not in report.keywords:
        _over_budget.append((report.duration, report.nodeid))


def pytest_terminal_summary(terminalreporter):
    if _over_budget:
        terminalreporter.write_sep("-", f"tests without the slow marker over {QUICK_BUDGET_S:g} s (docs/testing.md)")
        for d, nodeid in sorted(_over_budget, reverse=True):
            terminalreporter.write_line(f"{d:6.1f} s  {nodeid}")
    if _unit_seconds:
        total = sum(_unit_seconds.values())
        terminalreporter.write_sep("-", f"the 40 longest work units of {total:.0f} s on all workers")
        for unit, d in sorted(_unit_seconds.items(), key=lambda kv: -kv[1])[:40]:
            terminalreporter.write_line(f"{d:6.1f} s  {unit}")


def run_cli(*args: str, cwd: Path | None = None, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run `diffuser-lab ARGS` as a user would (python -m diffuser_lab): in a process forked from
    this worker's :mod:`cli_server` (the package imported once), or in a fresh interpreter where
    the environment differs from the server's (``env``; a variable read at import time) or the
    server is busy or gone. ``DIFFUSER_LAB_TEST_FRESH=1``: always a fresh interpreter."""
    e = dict(os.environ)
    e.pop("HYDRA_FULL_ERROR", None)
    e.update(env or {})
    cmd = [sys.executable, "-m", "diffuser_lab", *args]
    server = _cli_server()  # its environment is compared with the command's (env included) below
    if server is not None and server.lock.acquire(blocking=False):
        try:
            p = server.run(cmd, list(args), Path(cwd or ROOT), e)
        finally:
            server.lock.release()
        if p is not None:
            return p
    return subprocess.run(cmd, cwd=cwd or ROOT, env=e, capture_output=True, text=True, timeout=600)


IMPORT_ENV = ("NUMBA_", "NPY_", "OPENBLAS_", "GOTO", "MKL_", "OMP_", "KMP_", "VECLIB_", "PYTHON", "LD_", "MALLOC_",
              "GLIBC_", "DIFFUSER_LAB_")
"""Environment variables read when the interpreter starts or the package is imported (numba's
config, numpy's dispatch, BLAS, ...) or by this package at any time: a command whose values of
these differ from the server's runs in a fresh interpreter. The others are set in the forked child
before the command runs, as a fresh interpreter would have them."""


def _import_env(env: dict) -> dict:
    return {k: v for k, v in env.items() if k.startswith(IMPORT_ENV)}


class _CliServer:
    """The client of one :mod:`cli_server` process (per xdist worker, started at first use)."""

    def __init__(self):
        import tempfile
        import threading

        self.lock = threading.Lock()
        self.env = _import_env(os.environ)
        self.dir = Path(tempfile.mkdtemp(prefix="diffuser-lab-cli-"))
        self.proc = subprocess.Popen([sys.executable, str(ROOT / "tests" / "cli_server.py")], cwd=ROOT,
                                     # the checkout's package, not an editable install's of another tree
                                     env={**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "tests"), str(ROOT)])},
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1)
        import atexit
        import shutil

        atexit.register(shutil.rmtree, self.dir, True)  # the server ends with this process (its stdin closes)

    def run(self, cmd: list[str], args: list[str], cwd: Path, env: dict) -> subprocess.CompletedProcess | None:
        """The command's result, or None where this server cannot run it (the caller starts a fresh
        interpreter): other values of the variables of :data:`IMPORT_ENV` than the server's, or a
        server that died."""
        if _import_env(env) != self.env or self.proc.poll() is not None:
            return None
        out, err = self.dir / "out", self.dir / "err"
        try:
            self.proc.stdin.write(json.dumps({"args": args, "cwd": str(cwd), "env": env, "out": str(out),
                                              "err": str(err)}) + "\n")
            self.proc.stdin.flush()
            pid = json.loads(self.proc.stdout.readline())["pid"]
        except (OSError, ValueError, KeyError):
            return None
        import selectors

        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        if not sel.select(timeout=600):  # as subprocess.run's timeout
            os.kill(pid, 9)
            self.proc.stdout.readline()
            raise subprocess.TimeoutExpired(cmd, 600)
        status = json.loads(self.proc.stdout.readline())["status"]
        return subprocess.CompletedProcess(cmd, status, out.read_text(errors="replace"), err.read_text(errors="replace"))


_server: list = []


def _cli_server() -> _CliServer | None:
    if os.environ.get("DIFFUSER_LAB_TEST_FRESH") == "1" or not hasattr(os, "fork"):
        return None
    if not _server:
        _server.append(_CliServer())
    return _server[0]


@pytest.fixture(scope="session")
def small_demo_scene():
    from diffuser_lab.config import default_config
    from diffuser_lab.runs.pipeline import load_scene

    cfg = default_config(**{"scene.options.n_views": 12, "scene.options.point_spacing": 0.07})
    return load_scene(cfg.scene)


def compose(*overrides):
    """The validated config of ``diffuser-lab`` with these overrides (Hydra composes it from conf/)."""
    from hydra import compose as hcompose
    from hydra import initialize_config_dir

    from diffuser_lab.cli.main import config_dir
    from diffuser_lab.config import register, to_object

    register()
    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        return to_object(hcompose("config", overrides=list(overrides)))


PROVENANCE_ISA = {"avx512", "avx2", "avx", "sse4.2", "sve", "neon", "baseline"}


def check_provenance(b: dict) -> None:
    """What every run's ``provenance`` holds (also used on real runs' summaries)."""
    assert set(b) == {"host", "machine", "versions", "diffuser_lab"}
    m = b["machine"]
    assert {"cpu_model", "cpu_vendor", "arch", "libc", "cpus", "cpus_usable", "isa", "numba", "numpy_simd",
            "blas"} == set(m)
    assert m["cpu_model"] and isinstance(m["cpus"], int) and 1 <= m["cpus_usable"] <= m["cpus"]
    assert m["isa"] in PROVENANCE_ISA
    if m["numba"] is not None:
        assert {"target", "host", "env_cpu_name", "avx512", "avx2", "fma", "enabled"} == set(m["numba"])
        assert all(isinstance(m["numba"][k], bool) for k in ("avx512", "avx2", "fma", "enabled"))
    assert set(m["numpy_simd"]) == {"baseline", "dispatched"}
    assert all({"library", "internal_api", "version", "architecture", "threading_layer"} == set(e) for e in m["blas"])
    from diffuser_lab.backends.provenance import DISTRIBUTIONS

    assert set(b["versions"]) == {"python", *DISTRIBUTIONS}
    assert b["versions"]["numpy"] and b["versions"]["hydra-core"]
    d = b["diffuser_lab"]
    assert set(d) == {"version", "commit", "dirty"}
    assert d["commit"] is None and d["dirty"] is None or len(d["commit"]) == 40 and isinstance(d["dirty"], bool)
    json.dumps(b)  # plain values only
