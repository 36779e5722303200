"""What the per-iteration statistics cost the diffusion (issue 50): CPU and wall seconds of
``diffuse`` (numba, 200 iterations, tol 0) on a room workload, with no observer, with an observer
that asks for the statistics (computed by the backend in its step, :mod:`diffuser_lab.backends.stats`)
and with the way before issue 50 (an observer that sees every iteration's Z in the paper's units
and computes the statistics in a second pass, :func:`~diffuser_lab.backends.records.step_stats`).

    PYTHONPATH=$PWD .venv/bin/python scripts/stats_cost.py [N_POINTS (50000)] [ROUNDS (3)]

Prints each variant's CPU seconds (``time.process_time``: every thread of this process; steadier
than the wall on a shared machine) and wall seconds, sorted, one line each.
"""
from __future__ import annotations

import sys
import time

import numpy as np

from diffuser_lab.backends.records import step_stats
from diffuser_lab.backends.stats import StatsRequest
from diffuser_lab.method.diffusion import diffuse, normalise
from diffuser_lab.method.graph import build_graph
from diffuser_lab.runs.workloads import room_workload


def main(argv: list[str]) -> int:
    n = int(argv[0]) if argv else 50_000
    rounds = int(argv[1]) if len(argv) > 1 else 3
    w = room_workload(n, n_views=30)
    system = normalise(build_graph(w.points, 24, w.normals), w.mass, 1e-4)
    gt = np.random.default_rng(0).integers(-1, w.mass.shape[1], system.n).astype(np.int16)

    class InStep:  # what run.rrd's plots ask for now
        def statistics(self):
            return StatsRequest(gt, None)

        def on_statistics(self, table):
            pass

        def wants(self, iteration):
            return False

        def __call__(self, *args):
            pass

    class SecondPass:  # before issue 50: Z in the paper's units every iteration, then its statistics
        def __init__(self):
            self.prev = np.full(system.n, -1, np.int16)

        def wants(self, iteration):
            return True

        def __call__(self, iteration, Z, stats):
            self.prev = step_stats(Z, self.prev, gt).labels

    diffuse(system, max_iter=5, tol=0.0, backend="numba", observer=InStep())  # numba's cache loaded
    out: dict[str, list[tuple[float, float]]] = {}
    for _ in range(rounds):  # side by side, so a noisy neighbour hits all three
        for name, make in (("no observer", lambda: None), ("statistics in the step", InStep),
                           ("second pass (before)", SecondPass)):
            t, c = time.perf_counter(), time.process_time()
            diffuse(system, max_iter=200, tol=0.0, backend="numba", observer=make())
            out.setdefault(name, []).append((time.process_time() - c, time.perf_counter() - t))
    for name, v in out.items():
        print(f"{name:24s} CPU s {[round(x[0], 3) for x in sorted(v)]}  wall s {sorted(round(x[1], 3) for x in v)}"
              f"  ({system.n:,} x {system.num_classes}, 200 iterations)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
