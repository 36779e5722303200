"""A hang is a failure with its stack (issue 61 item 2; tests/hangs.py): pytest-timeout's signal
method for a test stuck in Python or in a call a signal interrupts, the watchdog for one stuck in C
code holding the GIL, under xdist as the suite runs; and the fuzz cases' bound (tests/bounded.py)."""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from bounded import bounded

ROOT = Path(__file__).resolve().parent.parent

HANGS = textwrap.dedent("""\
    import itertools
    import time

    import pytest


    @pytest.mark.timeout(2)
    def test_sleeps():
        time.sleep(60)


    @pytest.mark.timeout(2)
    def test_spins_in_c_holding_the_gil():
        sum(itertools.repeat(0))


    def test_after():
        pass
    """)


@pytest.mark.slow  # a pytest of its own, two timeouts and a watchdog: ~10 s
def test_a_hang_in_python_and_one_in_c_fail_with_their_stacks_under_xdist(tmp_path):
    """The suite's own settings (pyproject.toml's, tests/hangs.py) on a module whose tests hang: each
    fails with the line it hung on, the next test still runs, and the run ends (10 s measured,
    2026-12-07)."""
    (tmp_path / "test_hang.py").write_text(HANGS)
    p = subprocess.run([sys.executable, "-m", "pytest", "-c", str(ROOT / "pyproject.toml"), "--rootdir", str(tmp_path),
                        "-p", "hangs", "-p", "no:dash", "-n", "1", str(tmp_path / "test_hang.py")],
                       env={**{k: v for k, v in os.environ.items() if not k.startswith(("PYTEST_XDIST", "PYTEST_HANG"))},
                            "PYTHONPATH": str(ROOT / "tests")}, capture_output=True, text=True,
                       timeout=120, cwd=tmp_path)
    out = p.stdout + p.stderr
    assert p.returncode == 1 and "2 failed, 1 passed" in out, out[-3000:]
    assert "Failed: Timeout (>2.0s) from pytest-timeout" in out  # the signal: the test fails, the worker lives
    sleeps = out[out.index("___ test_sleeps ___"):]
    assert "test_hang.py:9: Failed" in sleeps, sleeps[:2000]
    crashed = out[out.index("crashed while running 'test_hang.py::test_spins_in_c_holding_the_gil'"):]
    assert 'test_hang.py", line 14 in test_spins_in_c_holding_the_gil' in crashed, crashed[:3000]  # the watchdog
    # one crash report (the short summary may repeat its line, as wide as the terminal)
    assert len(re.findall(r"^worker 'gw\d+' crashed while running", out, re.M)) == 1  # the crashed test is not handed to the next worker


def test_a_fuzz_case_stuck_in_c_ends_its_process_with_the_stack():
    """bounded(): its alarm cannot interrupt C code holding the GIL; the watchdog 2 s later can."""
    code = ("import itertools, sys; sys.path.insert(0, sys.argv[1]); from bounded import bounded\n"
            "with bounded(0.3):\n"
            "    sum(itertools.repeat(0))\n")
    p = subprocess.run([sys.executable, "-c", code, str(ROOT / "tests")], capture_output=True, text=True, timeout=30)
    assert p.returncode == 1 and 'File "<string>", line 3 in <module>' in p.stderr, p.stderr


def test_a_fuzz_case_gives_the_test_its_timer_back():
    """bounded() takes SIGALRM for its case and sets pytest-timeout's timer again, less the case's time."""
    before = signal.getitimer(signal.ITIMER_REAL)[0]
    with bounded(1.0):
        sum(range(1000))
    after = signal.getitimer(signal.ITIMER_REAL)[0]
    assert 250 < before < 300.01 and before - 1 < after <= before  # the default 300 s, running
