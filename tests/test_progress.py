"""Progress lines (diffuser_lab/progress.py): shown on a terminal or when forced, silent otherwise,
and never a change to what a run computes."""
import io
import logging
import re
import sys
import warnings

import numpy as np
import pytest
from conftest import SMALL_DEMO, run_cli

from diffuser_lab import progress
from diffuser_lab.backends import numba as nb
from diffuser_lab.backends.numba import jacobi as kernels
from diffuser_lab.config import default_config
from diffuser_lab.method.diffusion import diffuse, normalise
from diffuser_lab.method.graph import build_graph
from diffuser_lab.runs.pipeline import run

needs_numba = pytest.mark.skipif(not nb.available(), reason="numba not installed")


class Terminal(io.StringIO):
    """A stderr that says it is a terminal."""

    def isatty(self):
        return True


@pytest.fixture
def auto(monkeypatch):
    """Progress in its default mode (no DIFFUSER_LAB_PROGRESS), as on a user's machine."""
    monkeypatch.delenv(progress.ENV, raising=False)


@pytest.fixture
def forced(monkeypatch):
    monkeypatch.setenv(progress.ENV, "1")


@pytest.mark.slow
def test_cli_shows_stages_only_when_forced(tmp_path):
    """Forced on: the stages and their counts are on stderr, the result table alone on stdout.
    Not a terminal (pytest's pipes): stderr stays empty. Same labels either way."""
    on = run_cli(*SMALL_DEMO, "record=off", f"hydra.run.dir={tmp_path / 'on'}", env={progress.ENV: "1"})
    off = run_cli(*SMALL_DEMO, "record=off", f"hydra.run.dir={tmp_path / 'off'}", env={progress.ENV: ""})
    assert on.returncode == 0 and off.returncode == 0, on.stderr + off.stderr
    for text in ("loading scene (demo) [", "choosing camera views:", "rendering views:", "10/10",
                 "frames: simulated 2D predictions + evidence: 10/10 frame", "kNN graph (k=24,",
                 "diffusion (jacobi, ", "60/60 it", "writing labels.npy"):
        assert text in on.stderr, on.stderr
    assert off.stderr == ""
    assert on.stdout.splitlines()[:6] == off.stdout.splitlines()[:6]  # the table, up to its timings
    assert "\r" not in on.stdout and "rendering" not in on.stdout
    np.testing.assert_array_equal(np.load(tmp_path / "on" / "labels.npy"), np.load(tmp_path / "off" / "labels.npy"))


def test_pipeline_results_do_not_depend_on_progress(small_demo_scene, monkeypatch, capsys):
    cfg = default_config(**{"solver.max_iter": 80})
    monkeypatch.setenv(progress.ENV, "0")
    a = run(cfg, scene=small_demo_scene)
    assert capsys.readouterr().err == ""
    monkeypatch.setenv(progress.ENV, "1")
    b = run(cfg, scene=small_demo_scene)
    err = capsys.readouterr().err
    n = len(small_demo_scene.frames)
    assert f"evidence: {n}/{n} frame" in err and "80/80 it" in err and "kNN graph" in err
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.bayesian_labels, b.bayesian_labels)
    np.testing.assert_array_equal(a.diffusion.Z, b.diffusion.Z)
    assert a.diffusion.residuals == b.diffusion.residuals


@pytest.mark.parametrize("backend", [pytest.param("numba", marks=needs_numba), "scipy"])
def test_diffusion_split_for_progress_stops_at_the_same_iteration(small_demo_scene, backend, monkeypatch, capsys):
    """Shown, the diffusion returns to Python every progress_chunk() iterations; the iterations,
    residuals, Z and the early stop (here mid-chunk, at 34) are those of the unsplit run."""
    s = small_demo_scene
    ev = run(default_config(**{"method.name": "bayesian"}), scene=s).evidence
    system = normalise(build_graph(s.points, 16, s.normals), ev.mass, 1e-4)
    monkeypatch.setenv(progress.ENV, "0")
    full = diffuse(system, max_iter=80, tol=0.0, backend=backend)
    tol = full.residuals[33] * 1.0000001
    calls = []
    if backend == "numba":
        real = kernels.StepRunner.run
        monkeypatch.setattr(kernels.StepRunner, "run",  # a[8]: n_steps (then the statistics' arguments)
                            lambda self, *a: calls.append(a[8]) or real(self, *a))
    a = diffuse(system, max_iter=80, tol=tol, backend=backend)
    n_plain = len(calls)
    monkeypatch.setenv(progress.ENV, "1")
    b = diffuse(system, max_iter=80, tol=tol, backend=backend)
    assert a.converged and a.iterations == b.iterations == 34
    assert a.residuals == b.residuals == full.residuals[:34]
    np.testing.assert_array_equal(a.Z, b.Z)
    if backend == "numba":
        assert n_plain == 1 and calls[n_plain:] == [10, 10, 10, 10]  # one compiled call, then 4 chunks
    err = capsys.readouterr().err
    assert "diffusion (jacobi, " in err and "34/80 it" in err and "converged" in err


def test_on_a_terminal_only_stages_longer_than_the_delay_print(auto, monkeypatch):
    term = Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    assert progress.enabled()
    with progress.quiet():  # as diffuser-lab-bench times its runs
        assert not progress.enabled()
    with progress.stage("quick", total=3) as p:  # well within DELAY
        p.update(3)
    assert term.getvalue() == ""
    monkeypatch.setattr(progress, "DELAY", 0.0)
    with progress.stage("shown", total=3, unit="frame") as p:
        p.update(3)
    with progress.stage("one call"):
        pass
    out = term.getvalue()
    assert "shown: 3/3 frame [00:00]" in out and "one call [00:00]" in out and out.endswith("\n")


def test_not_a_terminal_or_switched_off_prints_nothing(auto, monkeypatch):
    monkeypatch.setattr(progress, "DELAY", 0.0)
    for stream, env in [(io.StringIO(), None), (Terminal(), "0")]:
        if env is not None:
            monkeypatch.setenv(progress.ENV, env)
        monkeypatch.setattr(sys, "stderr", stream)
        assert not progress.enabled()
        with progress.stage("hidden", total=2) as p:
            assert not p.enabled
            p.update(2)
            p.note("x")
        assert stream.getvalue() == ""


def test_nested_and_failed_stages_are_erased_and_warnings_go_above(forced, monkeypatch):
    term = Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    handler = logging.StreamHandler(sys.stderr)  # a console log handler, as Hydra's
    log = logging.getLogger("diffuser_lab")
    log.addHandler(handler)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            # as the command line prints them: one line on stderr
            warnings.showwarning = lambda msg, cat, *a, **k: sys.stderr.write(f"{cat.__name__}: {msg}\n")
            with progress.stage("outer", total=1, unit="target") as p:
                with progress.stage("inner", total=5):
                    warnings.warn("mid-bar", UserWarning)
                    log.warning("logged mid-bar")
                p.update()
            assert warnings.showwarning.__module__ == __name__  # put back
        assert "emit" not in vars(handler)
    finally:
        log.removeHandler(handler)
    out = term.getvalue()
    assert "outer: 1/1 target" in out and "inner: 5/5" not in out  # nested: erased, not finished
    for text in ("UserWarning: mid-bar\n", "logged mid-bar\n"):
        line = out[: out.index(text)].rsplit("\n", 1)[-1]
        assert "\r" in line and re.sub(r"\x1b\[A|\s", "", line.rsplit("\r", 1)[-1]) == ""  # on a cleared line
    term.seek(0), term.truncate()
    with pytest.raises(RuntimeError):
        with progress.stage("failing"):
            raise RuntimeError("boom")
    assert "\n" not in term.getvalue()  # cleared, no finished line left behind
