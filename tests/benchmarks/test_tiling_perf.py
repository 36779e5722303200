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
import time

import numpy as np
import pytest

from diffuser_lab.runs import tiled
from conftest import compose

SMALL = ["scene.demo.n_views=8", "scene.demo.point_spacing=0.1", "solver.max_iter=30", "tiling.size=2"]
CITY = ["scene=city", "predictions=realistic_city", "tiling.size=30"]


@pytest.fixture(scope="module")
def enabled(request) -> bool:
    return bool(request.config.getoption("benchmark_enable", default=False))


@pytest.mark.benchmark(group="tiling")
def test_two_workers_vs_one(benchmark, enabled, tmp_path):
    pytest.importorskip("ray")
    keys = ["protocol=tiled", "record=off", *(CITY if enabled else SMALL)]
    runs = {}

    def run(workers: int):
        t0 = time.perf_counter()
        res = tiled.tiled(compose(*keys, f"tiling.workers={workers}"), run_dir=tmp_path / f"w{workers}")
        runs[workers] = (time.perf_counter() - t0, res)
        return res

    run(1)
    benchmark.pedantic(run, args=(2,), rounds=1, iterations=1)
    (t1, one), (t2, two) = runs[1], runs[2]
    np.testing.assert_array_equal(two.labels, one.labels)
    assert not one.failed and not two.failed
    tiles = lambda res: sum(r["time_s"] for r in res.tiles)  # noqa: E731 - the tasks' own seconds
    info = {"n_points": one.scene.n_points, "tiles": len(one.tiles), "one_worker_s": round(t1, 2),
            "two_workers_s": round(t2, 2), "speedup": round(t1 / t2, 3),
            "tiles_phase_speedup": round(one.timings_s["diffusion"] / two.timings_s["diffusion"], 3),
            "task_seconds": [round(tiles(one), 1), round(tiles(two), 1)],
            "pids_two": len({r["pid"] for r in two.tiles}), "target": ">= 1.7x"}
    benchmark.extra_info.update(info)
    print("\n[tiling workers] " + json.dumps(info))
