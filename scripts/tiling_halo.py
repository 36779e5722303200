"""Labels of protocol=tiled equal to the untiled run's, % of points, per halo width (docs/tiling.md).

    PYTHONPATH=$PWD python scripts/tiling_halo.py demo 0.25,0.5,0.75,1.0 [key=value ...]
    PYTHONPATH=$PWD python scripts/tiling_halo.py demo x5,x10,x15 [key=value ...]   # tiling.halo_factor (x sigma_d)
    PYTHONPATH=$PWD python scripts/tiling_halo.py bench FILE.npz SIZE 0,0.1,0.25,0.5,0.75,1

demo: the configured scene (default: the demo room) untiled, then tiled (tiling.size, default 2 m)
per halo. bench: a diffuser-lab-bench input (points, normals, evidence; e.g.
../shared/bench/make_bench_input.py 300000 FILE.npz): the bench's graph + Eqs. 14-15 + 100 Jacobi
steps on all points, then per x-y tile of SIZE metres plus halo (tiled.tile_points).
"""
import sys
import tempfile
import time

import numpy as np

from diffuser_lab.cli.bench import _load, _run_once
from diffuser_lab.config import default_config
from diffuser_lab.progress import quiet
from diffuser_lab.runs import pipeline, tiled


def _value(v: str):
    try:
        return float(v) if "." in v else int(v)
    except ValueError:
        return v


def _halo(h: str) -> dict:
    """``0.75``: tiling.halo in metres; ``x10``: tiling.halo=null, tiling.halo_factor=10."""
    return {"tiling.halo": None, "tiling.halo_factor": float(h[1:])} if h.startswith("x") else {"tiling.halo": float(h)}


def demo(halos: list[str], overrides: dict) -> None:
    with quiet():
        t = time.perf_counter()
        ref = pipeline.run(default_config(**overrides))
        tu = time.perf_counter() - t
        print(f"untiled: {ref.scene.n_points:,} points, {tu:.1f} s", flush=True)
        print("| size (m) | grid | halo (m) | halo / sigma_d | labels equal, % | Bayesian equal, % | time / untiled |")
        for h in halos:  # loop over halo widths
            cfg = default_config(**overrides, **{"protocol.name": "tiled", **_halo(h)})
            t = time.perf_counter()
            r = tiled.tiled(cfg, scene=ref.scene, run_dir=tempfile.mkdtemp())
            tt = time.perf_counter() - t
            sd = cfg.graph.sigma_d_factor * r.rho
            print(f"| {cfg.tiling.size:g} | {r.grid[0]}x{r.grid[1]} | {r.halo:.3g} | {r.halo / sd:.1f} | {100 * (r.labels == ref.labels).mean():.4f} "
                  f"| {100 * (r.bayesian_labels == ref.bayesian_labels).mean():.3f} | {tt / tu:.2f} |", flush=True)


def bench(path: str, size: float, halos: list[float]) -> None:
    pts, nrm, ev = _load(path)
    kw = dict(iters=100, k=24, solver="jacobi", backend="auto", pixel_weight=1e-4, sigma_s=0.2, sigma_d_factor=2.0)
    ref, _ = _run_once(pts, nrm, ev, **kw)
    origin, shape, cell = tiled.tile_grid(pts, size)
    size = tiled.fitted_edge(pts, size)  # the grid's cells' edge (tile_grid's)
    print(f"{len(pts):,} points, extent {np.ptp(pts, 0).round(2)} m")
    print("| size (m) | grid | halo (m) | labels equal, % |")
    for halo in halos:  # loop over halo widths
        lab = np.full(len(pts), -2, np.int16)
        for ix, iy in sorted({tuple(c) for c in np.unique(cell, axis=0).tolist()}):  # loop over tiles
            own, rows = tiled.tile_points(pts, tiled.TileSpec(ix, iy, origin, size, halo))
            out, _ = _run_once(pts[rows], nrm[rows], ev[rows], **kw)
            lab[own] = out[np.searchsorted(rows, own)]
        print(f"| {size:g} | {shape[0]}x{shape[1]} | {halo:g} | {100 * (lab == ref).mean():.3f} |", flush=True)


if __name__ == "__main__":
    if len(sys.argv) < 3 or sys.argv[1] not in ("demo", "bench"):
        sys.exit(__doc__)
    if sys.argv[1] == "demo":
        demo(sys.argv[2].split(","), {k: _value(v) for k, v in (a.split("=", 1) for a in sys.argv[3:])})
    else:
        bench(sys.argv[2], float(sys.argv[3]), [float(h) for h in sys.argv[4].split(",")])
