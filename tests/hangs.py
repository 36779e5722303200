"""A hang is a failure, with its stack (issue 61 item 2): a pytest plugin (``pytest_plugins`` in
tests/conftest.py) beside pytest-timeout.

pytest-timeout (``timeout`` and ``timeout_method = "signal"`` in pyproject.toml, ``@pytest.mark.timeout(N)``
on a test that needs more) fails a test that runs over its time: SIGALRM's handler dumps the other
threads' stacks and fails the test with its own, and the worker goes on. A signal handler runs only
between bytecodes, so a hang inside C code that holds the GIL (a compiled loop, a C library retrying
its call after EINTR) never reaches it; neither would pytest-timeout's ``thread`` method, whose timer
thread needs the GIL too (measured: both waited for ever on ``sum(itertools.repeat(0))``). Hence a
second bound, :func:`watchdog`: faulthandler's C thread, armed :func:`grace` seconds after the
timeout, writes every thread's Python stack and ends the process. Under xdist the controller adds
what the dead worker wrote to the test's "worker crashed" report (:func:`pytest_handlecrashitem`);
in one process (``-n0``) it goes to the terminal's stderr.

tests/bounded.py (the readers' fuzz cases) arms :func:`watchdog` for each case, inside the test's own.
"""
from __future__ import annotations

import contextlib
import faulthandler
import os
import shutil
import tempfile
import time
from pathlib import Path

import pytest

DUMPS_ENV = "PYTEST_HANG_DUMPS"
"""The folder the xdist controller makes for its workers' stack dumps (one file per worker)."""

_out: list = []  # the file faulthandler writes to (kept open: it takes a file descriptor)
_deadline: list[float] = []  # monotonic times at which the armed watchdogs fire, outermost first


def grace(timeout: float) -> float:
    """Seconds after pytest-timeout's failure before the watchdog ends the process: time for the
    failed test's teardown (3 s for a 2 s timeout, 30 s for the default 300 s)."""
    return min(30.0, max(3.0, timeout / 10))


def _file(worker: str | None = None):
    if not _out:
        folder = os.environ.get(DUMPS_ENV)
        if worker and folder and Path(folder).is_dir():
            _out.append(open(Path(folder) / f"{worker}.txt", "w"))  # noqa: SIM115 - open for the process's life
        else:  # one pytest process, or no pytest (a script using bounded())
            _out.append(os.fdopen(os.dup(2), "w"))  # the terminal's stderr (dup'ed before capture swaps fd 2)
    f = _out[0]
    if f.seekable():  # this test's stacks only
        f.seek(0)
        f.truncate()
    return f


def _arm() -> None:
    if _deadline:
        faulthandler.dump_traceback_later(max(_deadline[-1] - time.monotonic(), 1e-3), exit=True, file=_file())
    else:
        faulthandler.cancel_dump_traceback_later()


@contextlib.contextmanager
def watchdog(seconds: float):
    """End this process with every thread's stack if the block runs over ``seconds`` (even inside C
    code holding the GIL); the watchdog of an enclosing block is armed again after it."""
    _deadline.append(time.monotonic() + seconds)
    _arm()
    try:
        yield
    finally:
        _deadline.pop()
        _arm()


def pytest_configure(config):
    if hasattr(config, "workerinput"):
        _file(config.workerinput["workerid"])
    elif getattr(config.option, "numprocesses", None):
        os.environ[DUMPS_ENV] = tempfile.mkdtemp(prefix="pytest-hangs-")  # the workers inherit it
    else:
        _file()  # fd 2 is still the terminal's here


def pytest_unconfigure(config):
    if not hasattr(config, "workerinput") and os.environ.get(DUMPS_ENV):
        shutil.rmtree(os.environ.pop(DUMPS_ENV), ignore_errors=True)


@pytest.hookimpl(optionalhook=True, tryfirst=True)
def pytest_timeout_set_timer(item, settings):
    """pytest-timeout's timer (set by its own implementation after this one) and the watchdog behind it."""
    _deadline[:] = [time.monotonic() + settings.timeout + grace(settings.timeout)]
    _arm()


@pytest.hookimpl(optionalhook=True, tryfirst=True)
def pytest_timeout_cancel_timer(item):
    _deadline.clear()
    _arm()


@pytest.hookimpl(optionalhook=True)
def pytest_handlecrashitem(crashitem, report, sched):
    """The xdist controller: the stacks the crashed worker's watchdog wrote, in the test's report; the
    test listed as run (xdist's loadfile scheduling hands a crashed test's module out again, the
    crashed test included: it would end worker after worker)."""
    folder = os.environ.get(DUMPS_ENV)
    if not folder:
        return
    dump = Path(folder) / f"{report.node.gateway.id}.txt"
    if dump.is_file() and dump.read_text().strip():
        report.longrepr = f"{report.longrepr}\n{dump.read_text()}"
    with open(Path(folder) / "crashed.txt", "a") as f:
        f.write(crashitem + "\n")


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_protocol(item, nextitem):
    """A worker skips a test that ended an earlier worker: its failure is reported already."""
    crashed = Path(os.environ.get(DUMPS_ENV, "/nonexistent")) / "crashed.txt"
    if hasattr(item.config, "workerinput") and crashed.is_file() and item.nodeid in crashed.read_text().splitlines():
        return True
    return None
