"""Run a command and report the peak memory of its whole process tree (Ray's raylet and workers too).

    python scripts/peak_rss.py [--interval 0.5] [--json out.json] -- diffuser-lab scene=city ...

Samples every process descended from the command (psutil, every ``--interval`` seconds) and prints
the largest single-process RSS (with its command line), the largest sum over the tree at one instant,
and the wall time. A sampler misses peaks shorter than its interval; /usr/bin/time's "maximum
resident set size" covers the command's own process exactly, not the processes Ray starts apart.
Needs psutil (it comes with Ray: the ``test`` and ``ray`` extras).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import psutil


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--interval", type=float, default=0.5, help="seconds between samples")
    ap.add_argument("--json", help="write the figures to this file")
    ap.add_argument("command", nargs=argparse.REMAINDER, help="-- then the command")
    a = ap.parse_args(argv)
    cmd = a.command[1:] if a.command[:1] == ["--"] else a.command
    if not cmd:
        ap.error("no command given (put it after --)")
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd)
    root = psutil.Process(proc.pid)
    peak_one, peak_one_cmd, peak_sum, peak_n = 0, "", 0, 0
    seen: set[int] = set()
    while proc.poll() is None:
        try:
            procs = [root] + root.children(recursive=True)
        except psutil.NoSuchProcess:
            break
        total = 0
        for p in procs:  # loop over the tree's processes (tens)
            try:
                rss = p.memory_info().rss
            except (psutil.NoSuchProcess, psutil.AccessDenied):
                continue
            seen.add(p.pid)
            total += rss
            if rss > peak_one:
                try:
                    peak_one, peak_one_cmd = rss, " ".join(p.cmdline())[:160]
                except (psutil.NoSuchProcess, psutil.AccessDenied):
                    peak_one = rss
        if total > peak_sum:
            peak_sum, peak_n = total, len(procs)
        time.sleep(a.interval)
    rc = proc.wait()
    wall = time.perf_counter() - t0
    out = {"command": cmd, "rc": rc, "wall_s": round(wall, 1), "peak_process_gb": round(peak_one / 2**30, 3),
           "peak_process": peak_one_cmd, "peak_tree_gb": round(peak_sum / 2**30, 3),
           "processes_at_peak": peak_n, "processes_seen": len(seen)}
    print(f"peak_rss: rc {rc} | wall {wall:.1f} s | largest process {out['peak_process_gb']:.2f} GB "
          f"({peak_one_cmd[:80]}) | tree at its peak {out['peak_tree_gb']:.2f} GB over {peak_n} processes "
          f"({len(seen)} seen)", file=sys.stderr)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)
    return rc


if __name__ == "__main__":
    sys.exit(main())
