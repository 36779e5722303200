"""The recording's overhead, two source trees side by side (issue 50's before/after table): for
each round, each tree runs ``python -m diffuser_lab ARGS record=off`` and ``record=both`` (fresh
processes, the commands of tests/benchmarks/test_recording_budget.py), interleaved so a noisy
neighbour hits all four; one line per run, then medians per case and tree.

    python scripts/record_overhead.py OUT_DIR before=/tmp/h50before after=$PWD \\
        [--cases demo,scannet0470,demo-566k,online-growing] [--rounds 3] [--start 0]

(``git worktree add --detach /tmp/h50before 58b6009`` gives a before tree; scannet0470 reads
../shared beside each tree.) Per run: wall s, CPU s of the command and its recording process
(children's rusage: what a loaded machine blurs least), recorded bytes per diffused point, online
runs' median update latency (ms, summary.json), the 1-minute load average.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

CASES = {
    "demo": [],
    "scannet0470": ["scene=scannet0470"],
    "demo-566k": ["scene.options.point_spacing=0.012"],
    "online-growing": ["protocol=online", "online.map=growing"],
}


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def one(root: str, args: list[str], run_dir: Path, online: bool) -> dict:
    """One command in tree ``root``: wall, cpu (s), bpp (bytes per diffused point), lat (ms), load."""
    env = dict(os.environ, PYTHONPATH=root, DIFFUSER_LAB_NUMBA="1")
    c, t = _cpu(), time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "diffuser_lab", *args, "output.quiet=true", f"hydra.run.dir={run_dir}"],
                       cwd=root, env=env, capture_output=True, text=True)
    wall, cpu = time.perf_counter() - t, _cpu() - c
    if p.returncode:
        raise RuntimeError(p.stderr[-2000:])
    s = json.loads((run_dir / "summary.json").read_text())
    size = sum((run_dir / f).stat().st_size for f in ("run.rrd", "run.mcap") if (run_dir / f).is_file())
    return {"wall": wall, "cpu": cpu, "bpp": size / s["n_points_diffused"],
            "lat": s["online"]["latency_ms"]["median"] if online else None, "load": os.getloadavg()[0]}


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("trees", nargs="+", help="NAME=PATH of a source tree")
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--start", type=int, default=0, help="first round's number (run folders are never reused)")
    a = ap.parse_args(argv)
    trees = dict(t.split("=", 1) for t in a.trees)
    res: dict = {}
    for case in a.cases.split(","):
        for r in range(a.start, a.start + a.rounds):
            for tree, root in trees.items():
                for rec in ("off", "both"):
                    row = one(root, [*CASES[case], f"record={rec}"], a.out / f"{case}-{tree}-{rec}{r}",
                              case == "online-growing")
                    res.setdefault((case, tree), {}).setdefault(rec, []).append(row)
                    print(time.strftime("%H:%M:%S"), case, tree, rec, r,
                          {k: (round(v, 3) if v is not None else None) for k, v in row.items()}, flush=True)
    for (case, tree), recs in res.items():
        m = {rec: {k: statistics.median([x[k] for x in v]) for k in ("wall", "cpu", "bpp")} for rec, v in recs.items()}
        line = (f"{case} {tree}: wall {m['off']['wall']:.1f} / {m['both']['wall']:.1f} s "
                f"({m['both']['wall'] / m['off']['wall']:.2f}x), CPU {m['off']['cpu']:.1f} / {m['both']['cpu']:.1f} s "
                f"({m['both']['cpu'] / m['off']['cpu']:.2f}x), {m['both']['bpp']:.0f} bytes per point")
        if case == "online-growing":
            lo, lb = (statistics.median([x["lat"] for x in recs[k]]) for k in ("off", "both"))
            line += f", latency {lo:.0f} / {lb:.0f} ms ({lb / lo:.2f}x)"
        print(line, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
