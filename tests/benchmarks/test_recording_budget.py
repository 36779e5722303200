"""The recording budget (issues 19 and 50), on what a user waits for and keeps: the `diffuser-lab`
command with the default record (both files) against `record=off`, and the recorded bytes per
diffused point (map point, online), on four runs:

    demo                                        budget: wall <= 1.20x, <= 300 bytes per point
    scene=scannet0470 (../shared)               budget: wall <= 1.10x, <= 300 bytes per point
    demo, scene.options.point_spacing=0.012     budget: wall <= 1.10x, <= 300 bytes per point
    demo, protocol=online online.map=growing    budget: per frame <= 1.10x, <= 300 bytes per point

(wall: the command's wall time; per frame: the median update latency of the frames,
summary.json's ``online.latency_ms.median``; the commands' CPU seconds and the load average are
printed and kept beside them: on a machine shared with other work the wall ratio measures the
neighbours as much as the recorder). Measure with

    .venv/bin/python -m pytest tests/benchmarks/test_recording_budget.py --benchmark-enable -s

Each run is the command as a user types it, in a fresh process, `off` and `both` alternating
(side by side, so a noisy neighbour hits both), medians of ``DIFFUSER_LAB_BUDGET_ROUNDS`` (default
5) rounds; the table row is printed and the ratio and the bytes asserted, in the same benchmark.
With benchmarks disabled (the default test run) each case runs `record=both` once on small demo settings and
only the bytes and the run's success are checked.
"""
from __future__ import annotations

import json
import os
import resource
import statistics
import time

import pytest
from conftest import SHARED, run_cli

pytestmark = pytest.mark.slow  # timing runs (also run once as tests): not the quick loop

SCANNET = SHARED / "data" / "scannet" / "scene0470_00" / "scene0470_00_vh_clean_2.labels.ply"
SMALL = ["scene.options.n_views=10", "scene.options.point_spacing=0.08", "solver.max_iter=60"]
CASES = {  # (arguments, budget of record=both / record=off, what is timed)
    "demo": ([], 1.20, "wall"),
    "scannet0470": (["scene=scannet0470"], 1.10, "wall"),
    "demo-566k": (["scene.options.point_spacing=0.012"], 1.10, "wall"),
    "online-growing": (["protocol=online", "online.map=growing"], 1.10, "frame"),
}
BYTES = 300


def _cpu() -> float:
    """CPU seconds (user + system) of the finished commands this process waited for, and theirs."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _one(tmp_path, tag: str, args: list[str]) -> tuple[float, float, dict, float]:
    """(wall s, CPU s of the command and its recorder process, summary.json, recorded bytes per
    diffused point) of one command."""
    d = tmp_path / tag
    c, t = _cpu(), time.perf_counter()
    p = run_cli(*args, "output.quiet=true", f"hydra.run.dir={d}")
    wall, cpu = time.perf_counter() - t, _cpu() - c
    assert p.returncode == 0, p.stderr
    s = json.loads((d / "summary.json").read_text())
    size = sum((d / f).stat().st_size for f in ("run.rrd", "run.mcap") if (d / f).is_file())
    return wall, cpu, s, size / s["n_points_diffused"]


def _timed(s: dict, wall: float, what: str) -> float:
    return s["online"]["latency_ms"]["median"] / 1e3 if what == "frame" else wall


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.benchmark(group="recording-budget")
def test_recording_budget(benchmark, tmp_path, case):
    args, ratio_budget, what = CASES[case]
    if case == "scannet0470" and not SCANNET.is_file():
        pytest.skip(f"real ScanNet data absent: {SCANNET} not found")
    if benchmark.disabled:
        if case not in ("demo", "online-growing"):
            pytest.skip("benchmark only (--benchmark-enable)")
        args = [*args, *SMALL]
    rounds = int(os.environ.get("DIFFUSER_LAB_BUDGET_ROUNDS", "5")) if not benchmark.disabled else 1
    times: dict[str, list[float]] = {"off": [], "both": []}
    walls: dict[str, list[float]] = {"off": [], "both": []}
    cpus: dict[str, list[float]] = {"off": [], "both": []}  # beside the wall: what a loaded machine does not blur
    per_point = None

    def measure():
        nonlocal per_point
        for i in range(rounds):
            for rec in ("off", "both") if not benchmark.disabled else ("both",):  # no ratio asserted: no off run
                wall, cpu, s, ppt = _one(tmp_path, f"{rec}{i}", [*args, f"record={rec}"])
                walls[rec].append(wall)
                cpus[rec].append(cpu)
                times[rec].append(_timed(s, wall, what))
                if rec == "both":
                    per_point = ppt
                    assert s["records"] == {"rrd": "run.rrd", "mcap": "run.mcap"}

    benchmark.pedantic(measure, rounds=1, iterations=1)
    if benchmark.disabled:  # the default test run: the records written, their bytes per point
        assert per_point <= BYTES, per_point
        return
    off, both = statistics.median(times["off"]), statistics.median(times["both"])
    unit = "s wall" if what == "wall" else "ms per frame (median update latency)"
    scale = 1.0 if what == "wall" else 1e3
    benchmark.extra_info.update(off=off, both=both, ratio=both / off, timed=what, bytes_per_point=per_point,
                                wall_off_s=statistics.median(walls["off"]), wall_both_s=statistics.median(walls["both"]),
                                cpu_off_s=statistics.median(cpus["off"]), cpu_both_s=statistics.median(cpus["both"]),
                                load=os.getloadavg()[0])
    print(f"\n[recording budget] {case}: record=off {off * scale:.2f}, both {both * scale:.2f} {unit}: "
          f"{both / off:.2f}x (budget {ratio_budget:.2f}x); {per_point:.0f} bytes per diffused point (budget {BYTES}); "
          f"off {[round(w * scale, 2) for w in times['off']]} both {[round(w * scale, 2) for w in times['both']]}"
          + (f"; walls off {[round(w, 2) for w in walls['off']]} both {[round(w, 2) for w in walls['both']]}"
             if what != "wall" else "")
          + f"; CPU s off {[round(c, 2) for c in cpus['off']]} both {[round(c, 2) for c in cpus['both']]}, "
            f"load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    assert per_point <= BYTES
    if not benchmark.disabled:
        assert both / off <= ratio_budget, f"{case}: {both / off:.2f}x > {ratio_budget:.2f}x"
