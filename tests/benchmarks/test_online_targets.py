"""Online Diffuser rate targets (issue 57): per frame, from the frame's arrival to its updated labels
(``latency_ms`` in summary.json: map, graph, evidence, steps and labels; the network and the file
reading excluded), through the command line as the README runs it (``record=off``), on 2 cores:

    demo room, growing map (30 frames, 3 cm)                   median <= 25 ms, p95 <= 50 ms
    7-Scenes sample, growing map (100 frames, 640x480, 3 cm)   median <= 33 ms, p95 <= 66 ms
    scene=scannet0470, given map (40 views, ~48k points)       median <= 10 ms
    (the 7-Scenes frames labelled by the tests' toy network tests.toy_networks.grey_levels: the
    sample has no ground truth)

Their accuracy targets (final labels equal to the batch's, mIoU within 0.5, no class lost) are
tests in tests/method/test_online.py (``test_the_documented_accuracy_targets_at_full_size``).

Measure with

    .venv/bin/python -m pytest tests/benchmarks/test_online_targets.py --benchmark-enable -s -n 0

Each case runs its command :data:`ROUNDS` times (the first run of a fresh interpreter loads the
compiled kernels: its first frame is slow, as a user's); the figures are the medians of the runs'
median and p95. A case whose target is not met today is in :data:`NOT_MET`, with the figure
measured: it is reported as an expected failure while it stays unmet, and fails (take it out)
once met. With benchmarks disabled (the default test run) the cases are skipped.
"""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import SHARED

pytestmark = pytest.mark.slow  # timing runs: not the quick loop

SCANNET = SHARED / "data" / "scannet" / "scene0470_00"
SEVEN = SHARED / "data" / "7scenes_sample"
ROUNDS = 3
CASES = {
    "demo-growing": (["protocol=online", "online.map=growing"], 25.0, 50.0, None),
    "7scenes-growing": (["scene=rgbd_folder", f"scene.options.root={SEVEN}", "protocol=online", "online.map=growing",
                         "predictions=model", "predictions.model._target_=tests.toy_networks.grey_levels"],
                        33.0, 66.0, SEVEN),
    "scannet0470-given": (["scene=scannet0470", "protocol=online"], 10.0, None, SCANNET),
}
NOT_MET = {
    "demo-growing": "measured 2026-12-07 (5 runs, AMD EPYC, 2 cores): median 33.7 ms, p95 71.1 ms",
    "7scenes-growing": "measured 2026-12-07 (5 runs): median 36.8 ms, p95 54.5 ms (the p95 target met)",
}
"""Cases whose target is not met today (docs/results/online.md, issue 57), with the figures."""


def _run(args: list[str], run_dir) -> dict:
    cmd = [sys.executable, "-m", "diffuser_lab.cli.main", *args, "record=off", "output.quiet=true",
           f"hydra.run.dir={run_dir}"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    return json.loads((run_dir / "summary.json").read_text())


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.benchmark(group="online")
def test_online_rate_targets(benchmark, case, tmp_path):
    args, med_t, p95_t, data = CASES[case]
    if benchmark.disabled:
        pytest.skip("benchmark only (--benchmark-enable)")
    if data is not None and not data.is_dir():
        pytest.skip(f"real data absent: {data} not found")
    runs = [_run(args, tmp_path / f"r{i}") for i in range(ROUNDS - 1)]
    runs.append(benchmark.pedantic(lambda: _run(args, tmp_path / "timed"), rounds=1, iterations=1))
    med = float(np.median([r["online"]["latency_ms"]["median"] for r in runs]))
    p95 = float(np.median([r["online"]["latency_ms"]["p95"] for r in runs]))
    frames = [f for f in runs[-1]["online"]["frames"] if not f.get("skipped")]
    parts = {k: float(np.median([f[k] for f in frames])) for k in ("map_ms", "graph_ms", "evidence_ms", "steps_ms")}
    print(f"\n{case}: {runs[-1]['n_points_diffused']:,} points, {len(frames)} frames: median {med:.1f} ms "
          f"(target {med_t}), p95 {p95:.1f} ms (target {p95_t}); last run's parts "
          f"{', '.join(f'{k} {v:.1f}' for k, v in parts.items())}")
    assert len(frames) == runs[-1]["n_frames"] and all(f["latency_ms"] > 0 for f in frames)
    met = med <= med_t and (p95_t is None or p95 <= p95_t)
    if case in NOT_MET:
        assert not met, f"the target is met now (median {med:.1f}, p95 {p95:.1f}): take {case} out of NOT_MET"
        pytest.xfail(f"target not met: median {med:.1f} ms, p95 {p95:.1f} ms ({NOT_MET[case]})")
    assert met, (med, p95)
