"""``diffuser-lab-bench``: time the core (graph + diffusion) on your own data.

    diffuser-lab-bench --input FILE.npz [--iters T] [--k K] [--solver S] [--backend B] [--out labels.npy]
    diffuser-lab-bench --write-demo-input FILE.npz [--points N]    # an input to try it on

FILE.npz holds ``points`` (N, 3), ``normals`` (N, 3) (optional: without them the distance-only
graph is used) and ``evidence`` (N, C), the pixel-to-point mass already summed per class, before
lambda. The command builds the graph (Eqs. 3-4), normalises (Eqs. 14-15) and diffuses ``--iters``
Jacobi steps (no early stop; ``--solver exact`` solves the fixed point instead; ``--solver
reference`` runs the straightforward scipy float64 implementation of
:mod:`diffuser_lab.method.reference`), then prints one JSON line with ``n_points``, ``graph_s``,
``diffusion_s``, ``total_s``, ``iterations`` (and ``solver``, ``backend``) and writes the (N,)
int16 labels (-1 = unlabeled) if ``--out`` is given. ``--repeat R`` times R runs and reports the
median of each figure. ``--write-demo-input FILE.npz`` writes such a file for the benchmarks'
demo-room workload (``--points`` points, 30 rendered 640x480 views of simulated 2D-network
evidence, 21 classes or ``--classes C`` split by space; :mod:`diffuser_lab.runs.workloads`) and exits.
``--sparse-classes auto|on|off`` and ``--classes-per-point M``: solver.sparse_classes (docs/many-classes.md).

Beside the timings (Jacobi), the line holds this machine's roof measured in the same process
(``roof``: copy bandwidth and float32 multiply-add rate, :mod:`diffuser_lab.backends.roof`), what
one step moves and computes (``per_step``: bytes, multiply-adds), the floor of the iterations on
that roof (``floor_s``, ``bound``) and ``efficiency`` = floor_s / total_s (graph included) and
``efficiency_diffusion`` = floor_s / diffusion_s: ratios comparable across machines. ``--no-roof`` skips it.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import numpy as np

from diffuser_lab import progress
from diffuser_lab.backends import roof as roofline
from diffuser_lab.data.arrays import open_npz
from diffuser_lab.method import reference as ref
from diffuser_lab.method.diffusion import diffuse, labels_from_scores, normalise
from diffuser_lab.method.exact import solve_exact
from diffuser_lab.method.graph import build_graph
from diffuser_lab.runs.workloads import room_workload


def _load(path: str):
    with open_npz(path, "a .npz of points, normals, evidence", role=None) as f:
        missing = [k for k in ("points", "evidence") if k not in f]
        if missing:
            raise ValueError(f"{path}: missing array(s) {', '.join(missing)} (expected points, normals, evidence)")
        pts = np.asarray(f.read("points", kinds="fiu"), np.float32)
        nrm = np.asarray(f.read("normals", kinds="fiu"), np.float32) if "normals" in f else None
        ev = np.asarray(f.read("evidence", kinds="fiu"), np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{path}: points has shape {pts.shape}, expected (N, 3)")
    if nrm is not None and nrm.shape != pts.shape:
        raise ValueError(f"{path}: normals has shape {nrm.shape}, expected {pts.shape}")
    if ev.ndim != 2 or ev.shape[0] != pts.shape[0]:
        raise ValueError(f"{path}: evidence has shape {ev.shape}, expected ({pts.shape[0]}, C)")
    return pts, nrm, ev


def run_once(pts, nrm, ev, *, iters: int, k: int, solver: str, backend: str, pixel_weight: float,
             sigma_s: float, sigma_d_factor: float, sparse_classes: str = "auto", classes_per_point: int = 16):
    """One timed run: returns (labels, figures dict). No progress lines (they would be timed too)."""
    with progress.quiet():
        return _run_once(pts, nrm, ev, iters=iters, k=k, solver=solver, backend=backend, pixel_weight=pixel_weight,
                         sigma_s=sigma_s, sigma_d_factor=sigma_d_factor, sparse_classes=sparse_classes,
                         classes_per_point=classes_per_point)


def _run_once(pts, nrm, ev, *, iters: int, k: int, solver: str, backend: str, pixel_weight: float,
              sigma_s: float, sigma_d_factor: float, sparse_classes: str = "auto", classes_per_point: int = 16):
    t0 = time.perf_counter()
    if solver == "reference":
        G = ref.reference_graph(pts, k, nrm, sigma_s=sigma_s, sigma_d_factor=sigma_d_factor)
        P, B = ref.reference_system(G, ev, pixel_weight)
        t1 = time.perf_counter()
        Z = ref.reference_diffuse(P, B, iters)
        lab = Z.argmax(1).astype(np.int16)
        lab[Z.max(1) <= 0] = -1
        t2 = time.perf_counter()
        return lab, dict(graph_s=t1 - t0, diffusion_s=t2 - t1, total_s=t2 - t0, iterations=iters,
                         solver="reference", backend="scipy-float64")
    gb = "scipy" if backend == "scipy" else "auto"
    g = build_graph(pts, k, nrm, sigma_s=sigma_s, sigma_d_factor=sigma_d_factor, backend=gb)
    system = normalise(g, ev, pixel_weight)
    t1 = time.perf_counter()
    if solver == "exact":
        res = solve_exact(system, backend=backend)
    else:
        res = diffuse(system, max_iter=iters, tol=0.0, backend=backend, sparse_classes=sparse_classes,
                      classes_per_point=classes_per_point)
    lab = labels_from_scores(res.Z)
    t2 = time.perf_counter()
    return lab, dict(graph_s=t1 - t0, diffusion_s=t2 - t1, total_s=t2 - t0, iterations=res.iterations,
                     solver=solver, backend=res.info.get("backend", backend), residual=res.residual,
                     **{key: res.info[key] for key in ("sparse_classes", "certified") if key in res.info})


def _write_demo_input(path: str, n_points: int, num_classes: int = 21) -> int:
    if n_points < 1000:
        print(f"diffuser-lab-bench: error: --points {n_points}: expected >= 1000", file=sys.stderr)
        return 2
    if num_classes < 21:
        print(f"diffuser-lab-bench: error: --classes {num_classes}: expected >= 21", file=sys.stderr)
        return 2
    w = room_workload(n_points, num_classes=num_classes)
    np.savez(path, points=w.points, normals=w.normals, evidence=w.mass)
    print(f"wrote {path}: {w.points.shape[0]:,} points, {w.mass.shape[1]} classes "
          f"({w.mass.any(1).mean():.1%} of the points with evidence)")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="diffuser-lab-bench", description=__doc__.split("\n\n")[0])
    ap.add_argument("--input", help=".npz with points (N,3), normals (N,3), evidence (N,C)")
    ap.add_argument("--write-demo-input", metavar="FILE.npz",
                    help="write the demo-room benchmark workload as such a file, then exit")
    ap.add_argument("--points", type=int, default=30_000, help="with --write-demo-input: about this many points")
    ap.add_argument("--classes", type=int, default=21,
                    help="with --write-demo-input: classes (default 21; more split the 21 by space, see "
                         "diffuser_lab.runs.workloads)")
    ap.add_argument("--sparse-classes", default="auto", choices=["auto", "on", "off"],
                    help="jacobi: the sparse per-point class set (docs/many-classes.md; default auto)")
    ap.add_argument("--classes-per-point", type=int, default=16, help="with --sparse-classes: M (default 16)")
    ap.add_argument("--iters", type=int, default=100, help="Jacobi iterations (default 100)")
    ap.add_argument("--k", type=int, default=24, help="neighbours per point (default 24)")
    ap.add_argument("--solver", default="jacobi", choices=["jacobi", "exact", "reference"])
    ap.add_argument("--backend", default="auto", choices=["auto", "numba", "scipy", "torch"])
    ap.add_argument("--pixel-weight", type=float, default=1e-4, help="lambda (default 1e-4)")
    ap.add_argument("--sigma-s", type=float, default=0.2)
    ap.add_argument("--sigma-d-factor", type=float, default=2.0)
    ap.add_argument("--repeat", type=int, default=1, help="runs; medians are reported (default 1)")
    ap.add_argument("--warmup", action="store_true", help="one untimed run first (compiles the kernels)")
    ap.add_argument("--out", help="write the (N,) int16 labels here (.npy)")
    ap.add_argument("--no-roof", action="store_true", help="skip measuring the copy bandwidth and matmul rate")
    a = ap.parse_args(argv)
    if a.write_demo_input:
        return _write_demo_input(a.write_demo_input, a.points, a.classes)
    if not a.input:
        ap.error("--input FILE.npz is required (make one with --write-demo-input FILE.npz)")
    try:
        if a.iters < 1 or a.k < 1 or a.repeat < 1:
            raise ValueError("--iters, --k and --repeat must be >= 1")
        pts, nrm, ev = _load(a.input)
        kw = dict(iters=a.iters, k=a.k, solver=a.solver, backend=a.backend, pixel_weight=a.pixel_weight,
                  sigma_s=a.sigma_s, sigma_d_factor=a.sigma_d_factor, sparse_classes=a.sparse_classes,
                  classes_per_point=a.classes_per_point)
        if a.warmup:
            run_once(pts, nrm, ev, **kw)
        runs = [run_once(pts, nrm, ev, **kw) for _ in range(a.repeat)]
        roof = None if a.no_roof or a.solver != "jacobi" else roofline.measure_roof()
    except (ValueError, RuntimeError, OSError) as e:
        print(f"diffuser-lab-bench: error: {e}", file=sys.stderr)
        return 2
    lab = runs[-1][0]
    figs = {key: statistics.median(r[1][key] for r in runs) for key in ("graph_s", "diffusion_s", "total_s")}
    out = {"n_points": int(pts.shape[0]), **{k: round(v, 6) for k, v in figs.items()},
           "iterations": runs[-1][1]["iterations"], "solver": runs[-1][1]["solver"],
           "backend": runs[-1][1]["backend"], "repeat": a.repeat}
    for key in ("sparse_classes", "certified"):
        if key in runs[-1][1]:
            out[key] = runs[-1][1][key]
    if "residual" in runs[-1][1]:
        out["residual"] = float(runs[-1][1]["residual"])
    if roof is not None:
        m = runs[-1][1].get("sparse_classes")
        cost = roofline.step_cost(pts.shape[0], a.k, int(m) if m else ev.shape[1], roof.llc_mb)
        eff = roofline.efficiency(roof, cost, out["iterations"], figs["total_s"])
        out.update(roof=roof.asdict(), per_step=cost, **eff,
                   efficiency_diffusion=roofline.efficiency(roof, cost, out["iterations"], figs["diffusion_s"])["efficiency"])
    print(json.dumps(out))
    if a.out:
        np.save(a.out, lab)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
