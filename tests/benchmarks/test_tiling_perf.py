"""Issue 28's tiled rows: two local Ray workers against one on the same tiles, measured side by side
in one run (a ratio, not an absolute time: the machine is shared).

    .venv/bin/python -m pytest tests/benchmarks/test_tiling_perf.py --benchmark-enable -s

Enabled: the default city (2 x 2 blocks, 923k points at 0.2 m, 32 frames, ``predictions=realistic_city``)
in 30 m tiles (a 5 x 5 grid); the default test run: a small demo in 2 m tiles. Labels of the two runs must be equal; the speed-up is reported (extra_info, printed),
not asserted. A worker is a Ray task with one CPU (its compiled kernels on one thread), so one
worker uses one core and two use both.
"""
from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest

from diffuser_lab.runs import tiled
from conftest import compose

pytestmark = pytest.mark.slow  # timing runs (also run once as tests): not the quick loop

SMALL = ["scene.options.n_views=8", "scene.options.point_spacing=0.1", "solver.max_iter=30", "tiling.size=2"]
CITY = ["scene=city", "predictions=realistic_city", "tiling.size=30"]


@pytest.fixture(scope="module")
def enabled(request) -> bool:
    return bool(request.config.getoption("benchmark_enable", default=False))


@pytest.mark.benchmark(group="tiling")
def test_two_workers_vs_one(benchmark, enabled, tmp_path):
    """Three runs on the same tiles: one worker alone on one core (the process tree's CPU affinity,
    which Ray's processes inherit), one worker with both cores free (part of a task, likely open3d's
    ray casting or BLAS, then uses the second core), two workers."""
    pytest.importorskip("ray")
    if not enabled:  # ~55 s even on a tiny demo (three Ray starts): the cluster test covers the mechanics
        pytest.skip("three Ray runs: run with --benchmark-enable")
    keys = ["protocol=tiled", "record=off", *(CITY if enabled else SMALL)]
    runs = {}

    def run(workers: int, cores=None):
        name = f"w{workers}" + ("_1core" if cores else "")
        old = os.sched_getaffinity(0)
        if cores:
            os.sched_setaffinity(0, cores)
        try:
            t0 = time.perf_counter()
            res = tiled.tiled(compose(*keys, f"tiling.workers={workers}"), run_dir=tmp_path / name)
            runs[name] = (time.perf_counter() - t0, res)
        finally:
            os.sched_setaffinity(0, old)
        return res

    run(1, cores={min(os.sched_getaffinity(0))})
    run(1)
    benchmark.pedantic(run, args=(2,), rounds=1, iterations=1)
    (t1c, one_core), (t1, one), (t2, two) = runs["w1_1core"], runs["w1"], runs["w2"]
    for res in (one_core, one):
        np.testing.assert_array_equal(two.labels, res.labels)
    assert not two.failed
    tiles = lambda res: round(sum(r["time_s"] for r in res.tiles), 1)  # noqa: E731 - the tasks' own seconds
    phase = lambda res: res.timings_s["diffusion"]  # noqa: E731 - Ray's start, the tiles' inputs and tasks
    info = {"n_points": one.scene.n_points, "tiles": len(one.tiles),
            "wall_s": {"one_worker_one_core": round(t1c, 2), "one_worker": round(t1, 2), "two_workers": round(t2, 2)},
            "speedup_vs_one_core": round(t1c / t2, 3), "tiles_phase_speedup_vs_one_core": round(phase(one_core) / phase(two), 3),
            "speedup_vs_one_worker": round(t1 / t2, 3), "tiles_phase_speedup_vs_one_worker": round(phase(one) / phase(two), 3),
            "task_seconds": {"one_worker_one_core": tiles(one_core), "one_worker": tiles(one), "two_workers": tiles(two)},
            "pids_two": len({r["pid"] for r in two.tiles}), "target": ">= 1.7x"}
    benchmark.extra_info.update(info)
    print("\n[tiling workers] " + json.dumps(info))
