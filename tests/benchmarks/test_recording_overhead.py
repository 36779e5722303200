"""Cost of recording (issue 4): the demo run with record=off vs record=both, every 10th iteration.

Target: record=both at most 25% slower than record=off. Measure with

    .venv/bin/python -m pytest tests/benchmarks/test_recording_overhead.py --benchmark-enable

and compare the two rows of the ``recording`` group (min or median). With benchmarks
disabled (the default run) each case runs once, on small demo settings, as a smoke test.
"""
import shutil

import pytest

from diffuser_lab.config import default_config
from diffuser_lab.pipeline import run
from diffuser_lab.recording import make_hooks

SMALL = {"scene.demo.n_views": 10, "scene.demo.point_spacing": 0.08, "solver.max_iter": 60}


def _bench(benchmark, tmp_path, mode: str):
    overrides = {"record.mode": mode, "record.interval": 10}
    if benchmark.disabled:
        overrides.update(SMALL)
    cfg = default_config(**overrides)
    dirs = []

    def setup():
        for d in dirs:  # a fresh run folder per round; the previous round's files go
            shutil.rmtree(d, ignore_errors=True)
        d = tmp_path / f"round{len(dirs)}"
        dirs.append(d)
        return (d,), {}

    def one_run(run_dir):
        hooks = make_hooks(cfg, run_dir)
        try:
            return run(cfg, hooks=hooks)
        finally:
            hooks.close()

    res = benchmark.pedantic(one_run, setup=setup, rounds=5, iterations=1, warmup_rounds=1)
    assert res.labels.shape[0] > 0
    return res


@pytest.mark.benchmark(group="recording")
def test_demo_record_off(benchmark, tmp_path):
    _bench(benchmark, tmp_path, "off")


@pytest.mark.benchmark(group="recording")
def test_demo_record_both_every_10th(benchmark, tmp_path):
    _bench(benchmark, tmp_path, "both")
