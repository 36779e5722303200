"""The tests' command-line server (tests/cli_server.py) runs a command as a fresh interpreter does:
the same exit status, output and files; an environment other than its own goes to a fresh one."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT, _cli_server, run_cli

pytestmark = pytest.mark.slow

TINY = ["scene.options.n_views=5", "scene.options.point_spacing=0.1", "record=off"]


def _fresh(*args: str) -> subprocess.CompletedProcess:
    e = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    return subprocess.run([sys.executable, "-m", "diffuser_lab", *args], cwd=ROOT, env=e, capture_output=True,
                          text=True, timeout=600)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork here: every command runs in a fresh interpreter")
def test_a_forked_command_is_the_fresh_interpreters(tmp_path):
    server = _cli_server()
    assert server is not None
    e = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    forked = server.run([sys.executable, "-m", "diffuser_lab"], [*TINY, f"hydra.run.dir={tmp_path / 'a'}"], ROOT, e)
    fresh = _fresh(*TINY, f"hydra.run.dir={tmp_path / 'b'}")
    assert forked is not None and forked.returncode == fresh.returncode == 0, forked and forked.stderr
    def printed(p, run):  # the timings' line apart (this process loaded its kernels before the fork)
        return [ln for ln in p.stdout.replace(str(run), "RUN").splitlines() if " total " not in ln]

    assert printed(forked, tmp_path / "a") == printed(fresh, tmp_path / "b")
    np.testing.assert_array_equal(np.load(tmp_path / "a" / "labels.npy"), np.load(tmp_path / "b" / "labels.npy"))
    # a bad value: the same one line and status 2
    bad = ["solver.max_iter=-3", f"hydra.run.dir={tmp_path / 'c'}"]
    f, g = server.run([sys.executable, "-m", "diffuser_lab"], bad, ROOT, e), _fresh(*bad)
    assert f.returncode == g.returncode == 2 and f.stderr == g.stderr and len(f.stderr.strip().splitlines()) == 1
    # another environment: not the server's to run (run_cli starts a fresh interpreter)
    assert server.run([sys.executable, "-m", "diffuser_lab"], bad, ROOT, {**e, "NUMBA_OPT": "0"}) is None
    # a variable read at run time only (the command line sets RUST_LOG itself): the server runs it
    assert server.run([sys.executable, "-m", "diffuser_lab"], bad, ROOT, {**e, "RUST_LOG": "warn"}) is not None
    p = run_cli(*bad, env={"NUMBA_OPT": "0"})
    assert p.returncode == 2 and p.stderr == g.stderr
