"""Issue 6 performance rows, measured with pytest-benchmark against a straightforward scipy float64
implementation of Eqs. 3-15 (diffuser_lab.method.reference) on the same input.

    .venv/bin/python -m pytest tests/benchmarks --benchmark-enable            # the real sizes
    DIFFUSER_BENCH_LARGE=1 .venv/bin/python -m pytest tests/benchmarks --benchmark-enable -k 3m

The default test command runs every benchmark once on tiny inputs with benchmarking disabled
(mechanics and label agreement only). Workloads: diffuser_lab.runs.workloads (voxel-downsampled demo
room, 21 classes, rendered 640x480 views with simulated 2D-network evidence, normals on).
Timings are printed and stored in the benchmark's extra_info; the targets are reported, not
asserted (the machine is shared); label agreement with the reference is asserted.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import tracemalloc
from types import SimpleNamespace

import numpy as np
import pytest

from diffuser_lab.backends import numba as nb
from diffuser_lab.method import reference as ref
from diffuser_lab.method.diffusion import diffuse, labels_from_scores, normalise
from diffuser_lab.method.evidence import Evidence, add_frame
from diffuser_lab.method.graph import build_graph
from diffuser_lab.runs.workloads import cycled_frames, room_workload

pytestmark = pytest.mark.slow  # timing runs (also run once as tests): not the quick loop

LARGE = os.environ.get("DIFFUSER_BENCH_LARGE", "") not in ("", "0")


@pytest.fixture(scope="module")
def enabled(request) -> bool:
    return bool(request.config.getoption("benchmark_enable", default=False))


_CACHE: dict = {}


def workload(n: int, enabled: bool, **kw):
    key = (n if enabled else max(n // 100, 1500), enabled, tuple(sorted(kw.items())))
    if key not in _CACHE:
        small = {} if enabled else dict(n_views=4, width=160, height=120)
        _CACHE[key] = room_workload(key[0], **{**small, **kw})
    return _CACHE[key]


def core(w, iters, backend="auto"):
    g = build_graph(w.points, 24, w.normals, backend="scipy" if backend == "scipy" else "auto")
    return diffuse(normalise(g, w.mass, 1e-4), max_iter=iters, tol=0.0, backend=backend)


def reference_labels(w, iters):
    G = ref.reference_graph(w.points, 24, w.normals)
    P, B = ref.reference_system(G, w.mass, 1e-4)
    Z = ref.reference_diffuse(P, B, iters)
    lab = Z.argmax(1)
    lab[Z.max(1) <= 0] = -1
    return lab


def _report(benchmark, row, **info):
    benchmark.extra_info.update(info)
    print(f"\n[{row}] " + json.dumps(info))


@pytest.mark.parametrize("n,iters", [(30_000, 100), (300_000, 200)], ids=["30k-100it", "300k-200it"])
@pytest.mark.parametrize("impl", ["diffuser-lab", "diffuser-lab-scipy", "reference-float64",
                                  "reference-float64-shuffled"])
def test_graph_and_diffusion(benchmark, enabled, n, iters, impl):
    """Rows 1-2: graph + T iterations; labels agree with the float64 reference on >= 99.9 %.

    ``reference-float64`` gets the workload's points in voxel order (x-major, as a voxelised
    scan leaves them: neighbours are near in memory, its best case); ``-shuffled`` the same
    cloud in a random order, as a cloud of arbitrary provenance comes (diffuser-lab orders
    the points itself, so its time does not depend on the input order)."""
    w = workload(n, enabled)
    if impl.startswith("reference-float64"):
        if impl.endswith("shuffled"):
            perm = np.random.default_rng(0).permutation(w.n)
            w_in = SimpleNamespace(points=w.points[perm], normals=w.normals[perm], mass=w.mass[perm])
        else:
            w_in = w
        if n >= 300_000 and enabled:  # ~20-60 s a run: a single round
            lab = benchmark.pedantic(reference_labels, args=(w_in, iters), rounds=1, iterations=1)
        else:
            lab = benchmark(reference_labels, w_in, iters)
        if impl.endswith("shuffled"):
            back = np.empty_like(lab)
            back[perm] = lab
            agree = float(np.mean(back == reference_labels(w, iters)))
            _report(benchmark, f"{impl} {n}", n_points=w.n, iterations=iters, agreement=agree)
            assert agree >= (0.999 if enabled else 0.99)  # the same graph and sums, in another order
    else:
        backend = "scipy" if impl.endswith("scipy") else "auto"
        core(w, 2, backend)  # compile / warm caches
        res = benchmark(core, w, iters, backend)
        lab = labels_from_scores(res.Z)
        agree = float(np.mean(lab == reference_labels(w, iters)))
        _report(benchmark, f"{impl} {n}", n_points=w.n, iterations=iters, agreement=agree,
                numba=nb.available())
        # a certified point (sparse layout) has the dense label; the rest are near-ties of the top M
        # classes. The ~1.5k-point stand-in of a disabled benchmark: a near-tied point weighs 0.07 %
        # (99.60 % measured on the keyed workload)
        assert agree >= res.info.get("certified", 0.0)
        assert agree >= (0.999 if enabled else 0.98)
    assert lab.shape == (w.n,)


def _evidence(points, frames, num_classes):
    ev = Evidence.empty(len(points), num_classes)
    for f in frames:
        add_frame(ev, points, f)
    return ev


@pytest.mark.parametrize("impl", ["diffuser-lab", "reference-float64"])
def test_evidence_300_frames(benchmark, enabled, impl):
    """Row 3: evidence from 300 frames of 640x480 into 300k points (30 rendered views, cycled)."""
    w = workload(300_000, enabled, with_mass=False)
    n_frames = 300 if enabled else 12
    frames = cycled_frames(w.frames, n_frames)
    if impl == "reference-float64":
        mass = benchmark.pedantic(ref.reference_evidence, args=(w.points, frames, 21), rounds=1, iterations=1)
        assert mass.shape == (w.n, 21)
        return
    ev = benchmark(_evidence, w.points, frames, 21)
    np.testing.assert_array_equal(ev.mass.sum(1), ev.links)
    # memory independent of the number of frames: peak allocations for 10x more frames
    peaks = []
    for m in (n_frames // 10, n_frames):
        tracemalloc.start()
        _evidence(w.points, cycled_frames(w.frames, m), 21)
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    _report(benchmark, "evidence", n_points=w.n, frames=n_frames, peak_bytes=peaks)
    assert peaks[1] <= peaks[0] * 1.05 + 1e6
    if enabled:  # same votes as the authors' dense one-hot path, up to projection round-off
        ref_mass = ref.reference_evidence(w.points, cycled_frames(w.frames, 30), 21)
        ours = _evidence(w.points, cycled_frames(w.frames, 30), 21).mass
        assert np.mean(np.all(ref_mass == ours, axis=1)) >= 0.999


_PIPELINE = textwrap.dedent("""
    import json, resource, sys, time
    from diffuser_lab.config import default_config
    from diffuser_lab.runs.pipeline import run
    from diffuser_lab.runs.workloads import room_workload
    t = time.perf_counter()
    w = room_workload(int(sys.argv[1]), n_views=int(sys.argv[2]), with_mass=False)
    t_make = time.perf_counter() - t
    cfg = default_config(**{"solver.max_iter": 200, "output.quiet": True})
    res = run(cfg, scene=w.scene())
    print(json.dumps({"n_points": w.n, "n_frames": len(w.frames), "make_s": t_make,
                      "timings_s": res.timings_s, "miou": res.metrics["miou"],
                      "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}))
""")


@pytest.mark.skipif(not LARGE, reason="3M-point pipeline: set DIFFUSER_BENCH_LARGE=1")
def test_pipeline_3m(benchmark, enabled):
    """Row 4: the whole pipeline (pipeline.run: evidence, Bayesian baseline, graph, 200 iterations,
    labels, metrics) on 3M points (the room tiled; each tile has its own views: 240 frames of
    640x480), in a fresh process; peak memory < 16 GB."""
    n = 3_000_000 if enabled else 30_000

    def once():
        p = subprocess.run([sys.executable, "-c", _PIPELINE, str(n), "30"], capture_output=True, text=True,
                           timeout=3600)
        assert p.returncode == 0, p.stderr[-2000:]
        return json.loads(p.stdout.strip().splitlines()[-1])

    out = benchmark.pedantic(once, rounds=1, iterations=1)
    _report(benchmark, "pipeline", **out)
    assert out["peak_rss_gb"] < 16.0


def test_first_run_cold_cache(benchmark, enabled, tmp_path):
    """The demo as a new user first runs it (``diffuser-lab``, no overrides) with numba's kernel
    cache empty: target <= 8 s of wall time on a 2-core machine (it takes the numpy/scipy path and
    compiles in the background afterwards; that background process is stopped here)."""
    if not enabled:
        pytest.skip("timing only: the cold-cache path itself is tested in tests/cli/test_first_run.py")
    import shutil
    import time

    env = {k: v for k, v in os.environ.items() if k not in ("DIFFUSER_LAB_NUMBA", "DIFFUSER_LAB_PROGRESS")}
    exe = shutil.which("diffuser-lab", path=os.path.dirname(sys.executable)) or "diffuser-lab"
    rounds = iter(range(100))

    def setup():
        cache = tmp_path / f"cache{next(rounds)}"
        return (cache,), {}

    def once(cache):
        t0 = time.perf_counter()
        p = subprocess.run([exe], cwd=tmp_path, env={**env, "NUMBA_CACHE_DIR": str(cache)},
                           capture_output=True, text=True, timeout=600)
        wall = time.perf_counter() - t0
        subprocess.run(["pkill", "-f", str(cache / "diffuser_lab_warm.lock")], check=False)
        assert p.returncode == 0, p.stderr[-2000:]
        assert "numba kernels are not compiled yet" in p.stderr
        return wall

    wall = benchmark.pedantic(once, setup=setup, rounds=3, iterations=1)
    _report(benchmark, "first run, empty kernel cache", wall_s=wall, target_s=8.0)


@pytest.mark.parametrize("n", [30_000, 300_000], ids=["30k", "300k"])
@pytest.mark.parametrize("classes", [21, 64, 150, 200])
@pytest.mark.parametrize("layout", ["dense", "sparse"])
def test_many_classes(benchmark, enabled, n, classes, layout):
    """Many-classes rows (docs/many-classes.md): graph excluded, 100 Jacobi iterations on the
    C-class workload (runs/workloads.py: the 21 classes split by space), dense numba kernels vs the
    sparse per-point class set (M = 16); labels against the dense scipy path (>= 99.9 %)."""
    w = workload(n, enabled, num_classes=classes)
    system = normalise(build_graph(w.points, 24, w.normals), w.mass, 1e-4)
    mode = "off" if layout == "dense" else "on"
    diffuse(system, max_iter=2, tol=0.0, sparse_classes=mode)  # compile / warm caches
    res = benchmark(diffuse, system, max_iter=100, tol=0.0, sparse_classes=mode)
    lab = labels_from_scores(res.Z)
    dense = labels_from_scores(diffuse(system, max_iter=100, tol=0.0, backend="scipy", sparse_classes="off").Z)
    agree = float(np.mean(lab == dense))
    _report(benchmark, f"many-classes {layout} {classes} {n}", n_points=w.n, classes=classes, agreement=agree,
            **{k: res.info[k] for k in ("backend", "certified", "dropped_fraction") if k in res.info})
    # a certified point (sparse layout) has the dense label; the rest are near-ties of the top M classes
    # (the small 3k-point stand-in of a disabled benchmark: 98.99 % measured on the keyed workload)
    assert agree >= res.info.get("certified", 0.999) and agree >= (0.999 if enabled else 0.98)
