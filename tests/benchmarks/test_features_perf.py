"""Issue 49's targets: a features run (``predictions=features``, 512-D, ``predictions.basis=auto``)
against the labels run (``predictions=realistic``) of the same scene, each in its own process, in
turn, three rounds in one run (ratios, not absolute times: the machine is shared).

    .venv/bin/python -m pytest tests/benchmarks/test_features_perf.py --benchmark-enable -s

Targets (the median over the rounds of each round's ratio): the demo end to end (the run's
``total`` plus writing its files) <= 2x; ~300k points (``scene.options.point_spacing=0.016``)
<= 3x, the features evidence <= 3x the labels', peak RSS <= 1.5 GB. Reported (extra_info, printed)
with the full path's ratio (``predictions.basis=full``, today's path before the basis) beside them;
asserted: the runs' figures (mIoU of the auto and the full run within 0.1). Skipped without
``--benchmark-enable`` (minutes of runs; tests/runs/test_features_run.py checks the agreement).
"""
from __future__ import annotations

import json
import statistics
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow  # timing runs: not the quick loop

BASE = ["record=off", "output.labels_ply=false"]
WRAP = ("import resource, subprocess, sys; rc = subprocess.run(sys.argv[1:]).returncode; "
        "print('MAXRSS_KB', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr); sys.exit(rc)")
"""Runs a command and prints its peak RSS (the largest child's, KB)."""


@pytest.fixture(scope="module")
def enabled(request) -> bool:
    return bool(request.config.getoption("benchmark_enable", default=False))


def _run(args: list[str], run_dir) -> dict:
    p = subprocess.run([sys.executable, "-c", WRAP, sys.executable, "-m", "diffuser_lab", *BASE, *args,
                        f"hydra.run.dir={run_dir}"], capture_output=True, text=True, timeout=1800)
    assert p.returncode == 0, p.stderr[-2000:]
    kb = [int(x.split()[1]) for x in p.stderr.splitlines() if x.startswith("MAXRSS_KB")]
    s = json.loads((run_dir / "summary.json").read_text())
    t = s["timings_s"]
    return {"end_to_end": t["total"] + t.get("write", 0.0), "total": t["total"], "evidence": t["evidence"],
            "diffusion": t["diffusion"], "peak_gb": kb[-1] / 2**20, "miou": s["metrics"]["miou"],
            "basis": (s.get("features") or {}).get("basis")}


def _compare(tmp_path, scene: list[str], rounds: int = 3) -> dict:
    cases = {"labels": ["predictions=realistic"], "auto": ["predictions=features"],
             "full": ["predictions=features", "predictions.basis=full"]}
    got = {k: [] for k in cases}
    for r in range(rounds):  # round-robin: a change of the machine's load hits every case alike
        for name, args in cases.items():
            got[name].append(_run([*args, *scene], tmp_path / f"{name}_{r}"))
    out = {}
    for name in ("auto", "full"):
        ratio = lambda key: statistics.median(x[key] / y[key] for x, y in zip(got[name], got["labels"]))  # noqa: E731
        out[name] = {"end_to_end_x": round(ratio("end_to_end"), 2), "evidence_x": round(ratio("evidence"), 2),
                     "diffusion_x": round(ratio("diffusion"), 2),
                     "peak_gb": round(statistics.median(x["peak_gb"] for x in got[name]), 2),
                     "end_to_end_s": round(statistics.median(x["end_to_end"] for x in got[name]), 2)}
    out["labels"] = {"end_to_end_s": round(statistics.median(x["end_to_end"] for x in got["labels"]), 2),
                     "peak_gb": round(statistics.median(x["peak_gb"] for x in got["labels"]), 2)}
    out["basis"] = got["auto"][0]["basis"]
    assert abs(got["auto"][0]["miou"] - got["full"][0]["miou"]) < 0.1  # the same figures (labels exact)
    return out


@pytest.mark.benchmark(group="features")
def test_demo_features_vs_labels(benchmark, enabled, tmp_path):
    if not enabled:
        pytest.skip("nine command-line runs (minutes): run with --benchmark-enable")
    info = benchmark.pedantic(_compare, args=(tmp_path, []), rounds=1, iterations=1)
    info["target"] = "auto end_to_end_x <= 2 (the full path: 9.4x in the issue)"
    benchmark.extra_info.update(info)
    print("\n[features demo] " + json.dumps(info))


@pytest.mark.benchmark(group="features")
def test_300k_features_vs_labels(benchmark, enabled, tmp_path):
    if not enabled:
        pytest.skip("nine command-line runs at 300k points (tens of minutes): run with --benchmark-enable")
    info = benchmark.pedantic(_compare, args=(tmp_path, ["scene.options.point_spacing=0.016"]), rounds=1,
                              iterations=1)
    info["target"] = "auto end_to_end_x <= 3, evidence_x <= 3, peak_gb <= 1.5 (the full path: 17x, 60x, 3.1 GB)"
    benchmark.extra_info.update(info)
    print("\n[features 300k] " + json.dumps(info))
