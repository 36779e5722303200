"""What recording a run's inputs costs (issue 60): the same run with a fresh hash cache (cold: every
input hashed) and with the cache of an earlier run (warm: every hash looked up), side by side, and
optionally the code of an earlier commit that recorded nothing (``--base DIR``: a checkout of it,
e.g. ``git archive 2aed40b | tar -x -C DIR``, imported from DIR with this venv).

    python scripts/hash_cost.py --rounds 3 -- scene=scannet scene.options.root=/tmp/seq1000/scene0470_00 \\
        scene.options.frame_step=1 predictions=files predictions.folder=/tmp/seq1000/predictions record=off \\
        output.labels_ply=false

Each round runs every mode once, interleaved (a loaded machine moves all of them alike); per mode the
median and every round of the wall time (the command's, start-up included), the CPU seconds (user +
system of the process and its children), and from summary.json the seconds spent recording inputs
(``inputs.hashing.seconds``, summed over the reading threads), the files and bytes hashed.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def run_once(args: list[str], out: Path, env: dict, cwd: Path) -> dict:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "diffuser_lab", *args, f"hydra.run.dir={out}", "output.quiet=true"],
                       cwd=cwd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed:\n{p.stderr[-2000:]}")
    s = json.loads((out / "summary.json").read_text())
    h = (s.get("inputs") or {}).get("hashing") or {}
    return {"wall": wall, "cpu": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
            "run_total": (s.get("timings_s") or {}).get("total"), "hash_s": h.get("seconds"),
            "seal_s": (s.get("timings_s") or {}).get("hashes"),
            "hashed": h.get("hashed"), "bytes": h.get("bytes_hashed"), "files": h.get("files")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--base", help="a checkout of an earlier commit (no input recording), run as a third mode")
    ap.add_argument("run", nargs="+", help="the diffuser-lab overrides (after --)")
    a = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="hash-cost-"))
    warm_cache = tmp / "warm.sqlite"
    env = dict(os.environ, DIFFUSER_LAB_NUMBA="1", RUST_LOG="off")
    # the warm cache filled once (and numba's kernels loaded) before any round
    run_once(a.run, tmp / "fill", dict(env, DIFFUSER_LAB_HASH_CACHE=str(warm_cache)), ROOT)
    modes = {"cold": lambda i: (dict(env, DIFFUSER_LAB_HASH_CACHE=str(tmp / f"cold{i}.sqlite")), ROOT),
             "warm": lambda i: (dict(env, DIFFUSER_LAB_HASH_CACHE=str(warm_cache)), ROOT)}
    if a.base:
        modes["base"] = lambda i: (dict(env, PYTHONPATH=a.base), Path(a.base))
        run_once(a.run, tmp / "base_fill", *modes["base"](0))  # its numba cache
    got: dict[str, list[dict]] = {m: [] for m in modes}
    for i in range(a.rounds):  # interleaved rounds
        for m, setup in modes.items():
            got[m].append(run_once(a.run, tmp / f"{m}{i}", *setup(i)))
            r = got[m][-1]
            print(f"round {i + 1} {m:5s} wall {r['wall']:6.2f} s  cpu {r['cpu']:6.2f} s  run total "
                  f"{r['run_total']:6.2f} s  recording {r['hash_s'] or 0:.3f} s  summary's hashes "
                  f"{r['seal_s'] or 0:.3f} s  hashed {r['hashed']} files, "
                  f"{(r['bytes'] or 0) / 1e6:.1f} MB", flush=True)
    print("\n| mode | wall (s), median | rounds | CPU (s), median | run's total (s) | recording inputs (s) | "
          "summary's hashes (s) | share of the run's total | files hashed / read |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for m, rs in got.items():
        med = lambda k: statistics.median(r[k] for r in rs)  # noqa: E731
        none = rs[0]["hash_s"] is None
        share = "-" if none else f"{100 * (med('hash_s') + med('seal_s')) / med('run_total'):.2f} %"
        hs = "- | -" if none else f"{med('hash_s'):.3f} | {med('seal_s'):.3f}"
        rounds = " / ".join(f"{r['wall']:.2f}" for r in rs)
        print(f"| {m} | {med('wall'):.2f} | {rounds} | {med('cpu'):.2f} | "
              f"{med('run_total'):.2f} | {hs} | {share} | {rs[0]['hashed']} / {rs[0]['files']} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
