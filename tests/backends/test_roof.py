"""The machine's roof and the Jacobi step model (diffuser_lab/backends/roof.py), and diffuser-lab-bench's
efficiency figures built on them."""
import json

import numpy as np
import pytest

from diffuser_lab.backends import roof
from diffuser_lab.cli import bench


def test_step_model_is_the_issues_arithmetic():
    # 300k points, K = 24, 21 classes: K indices + weights 57.6 MB, B read 25.2 MB, Z written 25.2 MB and
    # read first (write-allocate) 25.2 MB, Z read 25.2 MB (the model since 2026-12-07, issue 53)
    c = roof.step_cost(300_000, 24, 21)
    assert c == {"bytes": 158_400_000, "multiply_adds": 151_200_000, "z_in_cache": False}
    assert roof.step_cost(300_000, 24, 21, llc_mb=32) == c  # P 58 MB + B, Z, Zn 76 MB > 32 MB
    big = roof.step_cost(300_000, 24, 21, llc_mb=260)  # they fit: Z's reads from cache
    assert big["z_in_cache"] and big["bytes"] == 133_200_000
    # 30k x 200 classes x 100 steps: P, B and both Z (78 MB) in a 128 MB cache, Z's reads from it;
    # 14.4 G multiply-adds, 0.374 s at 77 GFLOP/s; 77.8 MB a step, 0.379 s at 20.5 GB/s: with B and
    # write-allocate counted, the two floors are about equal (memory by a hair)
    r = roof.Roof(copy_gbps=20.5, fma_gflops=77.0, copy_mb=256, matmul_n=2048, llc_mb=128)
    many = roof.step_cost(30_000, 24, 200, 128)
    assert many["z_in_cache"] and many["bytes"] == 30_000 * 24 * 8 + 3 * 24_000_000
    assert not roof.step_cost(30_000, 24, 200, 32)["z_in_cache"]
    e = roof.efficiency(r, many, 100, 1.9)
    assert e["bound"] == "memory" and abs(e["compute_floor_s"] - 0.374) < 0.001
    assert abs(e["floor_s"] - 100 * 77.76e6 / 20.5e9) < 1e-4 and abs(e["efficiency"] - e["floor_s"] / 1.9) < 0.001
    e = roof.efficiency(r, c, 200, 2.0)
    assert e["bound"] == "memory" and abs(e["floor_s"] - 200 * 158.4e6 / 20.5e9) < 1e-3


def test_measured_roof_is_bytes_and_flops_over_the_best_time(monkeypatch):
    """The roof is what its two timings say: 2 x the copied bytes (read + write) and 2 n^3 flops over
    the best of the repeats (the clock replaced by one whose every interval is known)."""
    ticks = iter([0.0, 0.50, 1.0, 1.25, 2.0, 2.40,  # copy: 0.5, 0.25, 0.4 s -> best 0.25
                  3.0, 3.1, 4.0, 4.2, 5.0, 5.05])  # matmul: 0.1, 0.2, 0.05 s -> best 0.05
    monkeypatch.setattr(roof.time, "perf_counter", lambda: next(ticks))
    r = roof.measure_roof(copy_mb=4, matmul_n=64, repeat=3)
    assert r.copy_gbps == pytest.approx(2 * 4 * 2**20 / 0.25 / 1e9)
    assert r.fma_gflops == pytest.approx(2 * 64**3 / 0.05 / 1e9)
    assert (r.copy_mb, r.matmul_n) == (4, 64)


def test_bench_reports_efficiency(tmp_path, capsys):
    rng = np.random.default_rng(0)
    pts = rng.random((3000, 3)).astype(np.float32)
    nrm = np.tile(np.float32([0, 0, 1]), (3000, 1))
    ev = np.zeros((3000, 5), np.float32)
    ev[np.arange(0, 3000, 7), rng.integers(0, 5, 429)] = 1.0
    np.savez(tmp_path / "in.npz", points=pts, normals=nrm, evidence=ev)
    assert bench.main(["--input", str(tmp_path / "in.npz"), "--iters", "20"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["per_step"] == roof.step_cost(3000, 24, 5, out["roof"]["llc_mb"]) and out["bound"] in ("memory", "compute")
    assert 0 < out["efficiency"] <= out["efficiency_diffusion"] and out["roof"]["copy_gbps"] > 0
    assert bench.main(["--input", str(tmp_path / "in.npz"), "--iters", "5", "--no-roof"]) == 0
    assert "efficiency" not in json.loads(capsys.readouterr().out.strip().splitlines()[-1])
