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


class _Capture:
    """Everything the recorders are handed during a run (Z states copied), to hand it again."""

    def __init__(self, interval):
        from diffuser_lab.hooks import RunHooks

        calls = self.calls = []

        class Capture(RunHooks):
            def on_scene(self, scene):
                calls.append(("on_scene", (scene,)))

            def on_frame(self, index, frame):
                calls.append(("on_frame", (index, frame)))

            def on_evidence(self, points, grid, evidence, bayesian):
                calls.append(("on_evidence", (points, grid, evidence, bayesian)))

            def wants(self, it):
                return it == 1 or it % interval == 0

            def observe(self, it, Z, stats):
                calls.append(("observe", (it, Z.copy(), dict(stats))))

            def on_result(self, result):
                calls.append(("on_result", (result,)))

        self.hooks = Capture()


@pytest.mark.benchmark(group="recording-content")
def test_recording_content_cost_without_a_diffusion(benchmark, tmp_path):
    """What recording the demo costs by itself: the calls a record=both run makes (scene, 30
    cameras with images, evidence, 21 Z states, result) replayed into fresh recorders in-line,
    with no diffusion competing; CPU time of the whole process (Rerun's and MCAP's threads
    included). On a machine whose cores the diffusion keeps busy, this is about what recording
    adds to a run; compare it with a quarter of the record=off run."""
    import time

    from diffuser_lab import recording

    overrides = {"record.mode": "both", "record.interval": 10}
    if benchmark.disabled:
        overrides.update(SMALL)
    cfg = default_config(**overrides)
    run(cfg)  # warm: scene cache, compiled kernels
    cap = _Capture(10)
    t = time.perf_counter()
    run(cfg, hooks=cap.hooks)
    off_s = time.perf_counter() - t
    cpu = []

    def setup():
        d = tmp_path / f"round{len(cpu)}"
        return (d,), {}

    def replay(run_dir):
        c = time.process_time()
        old = recording.ASYNC
        recording.ASYNC = False
        try:
            hooks = make_hooks(cfg, run_dir)
        finally:
            recording.ASYNC = old
        try:
            for name, args in cap.calls:
                getattr(hooks, name)(*args)
        finally:
            hooks.close()
        cpu.append(time.process_time() - c)
        shutil.rmtree(run_dir, ignore_errors=True)

    benchmark.pedantic(replay, setup=setup, rounds=5, iterations=1, warmup_rounds=1)
    med = sorted(cpu)[len(cpu) // 2]
    benchmark.extra_info.update(cpu_s=med, record_off_run_s=off_s, cpu_over_off=med / off_s)
    print(f"\n[recording content] cpu {med:.3f} s (all threads) vs record=off run {off_s:.3f} s: {med / off_s:.2f}")
    assert sum(1 for name, _ in cap.calls if name == "observe") == (21 if not benchmark.disabled else 7)
