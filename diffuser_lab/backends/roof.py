"""This machine's roof, measured in the process that is timed, and what a Jacobi step asks of it.

A timing alone says little across noisy, different machines; a fraction of this machine's own
limits, measured in the same run, does: ``floor_s / measured_s`` (the ``efficiency`` of
``diffuser-lab-bench``). Two limits:

- copy bandwidth: a large float32 array copied with ``np.copyto`` (read + write counted), best of
  several; the bytes a diffusion step must move over it give the memory floor;
- float32 multiply-add rate: a BLAS matmul (2048 x 2048 float32; one multiply-add = 2 flops), best
  of several; the step's multiply-adds over it give the compute floor.

The step model (dense Z, float32, the compiled Jacobi kernel's layout; corrected 2026-12-07, issue
53): what one step moves between the core and the last-level cache or memory,

- P: the K neighbour indices (int32) and weights (float32) of every row, ``N K (4 + 4)``;
- B: read once, ``N C 4``;
- Z written: ``N C 4`` stored, and as many read first (write-allocate: a store to a line not in
  cache loads it, the kernel's stores are not streaming), ``2 N C 4``;
- Z read: ``N C 4`` (a neighbour's row gathered once: a row's neighbours lie close in the Morton
  order, so the other gathers come from cache), not counted when the step's working set (P, B and
  both states of Z) fits in the last-level cache (its size read from Linux's sysfs).

and ``N K C`` multiply-adds. With sparse classes (M per point) C is M. The floor is the larger of
the two; the bound is the limit that sets it. Before 2026-12-07 B's reads and the write-allocate
reads were not counted (``N K 8 + 2 N C 4``, Z's reads dropped when Z and P fitted the cache): 300k
x 21 was 108 MB a step (82.8 MB with a large cache), now 158.4 MB (133.2 MB).
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from diffuser_lab import seeding

__all__ = ["Roof", "measure_roof", "step_cost", "efficiency"]


@dataclass(frozen=True)
class Roof:
    copy_gbps: float  # GB/s (1e9 bytes), read + write of a large copy
    fma_gflops: float  # GFLOP/s float32 (a multiply-add = 2 flops), a BLAS matmul
    copy_mb: int  # the copied array's size, MB
    matmul_n: int
    llc_mb: float = 0.0  # last-level cache, MB (0 = unknown)

    def asdict(self) -> dict:
        return {k: round(v, 2) if isinstance(v, float) else v for k, v in asdict(self).items()}


def measure_roof(copy_mb: int = 256, matmul_n: int = 2048, repeat: int = 5) -> Roof:
    """Best of ``repeat`` (after one untimed run each): a ``copy_mb`` MB float32 copy and an
    ``matmul_n``-square float32 matmul, in this process with its threads as they are."""
    n = copy_mb * 2**20 // 4
    src, dst = np.ones(n, np.float32), np.empty(n, np.float32)
    a = seeding.rng(0, "bench.roof_matmul").random((matmul_n, matmul_n), dtype=np.float32)
    b = a.T.copy()

    def best(fn) -> float:
        fn()
        ts = []
        for _ in range(repeat):  # loop over repeats (a handful)
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
        return min(ts)

    t_copy = best(lambda: np.copyto(dst, src))
    t_mm = best(lambda: a @ b)
    return Roof(copy_gbps=2 * src.nbytes / t_copy / 1e9, fma_gflops=2 * matmul_n**3 / t_mm / 1e9,
                copy_mb=copy_mb, matmul_n=matmul_n, llc_mb=last_level_cache_mb())


def last_level_cache_mb() -> float:
    """The largest CPU cache of cpu0 (Linux sysfs), MB; 0 where it cannot be read."""
    sizes = []
    for f in Path("/sys/devices/system/cpu/cpu0/cache").glob("index*/size"):  # a handful of levels
        try:
            t = f.read_text().strip().upper()
            sizes.append(float(t[:-1]) * {"K": 1 / 1024, "M": 1.0, "G": 1024.0}[t[-1]] if t[-1] in "KMG" else float(t) / 2**20)
        except (OSError, ValueError):
            continue
    return max(sizes, default=0.0)


def step_cost(n: int, k: int, classes: int, llc_mb: float = 0.0) -> dict:
    """One dense Jacobi step on ``n`` rows, ``k`` neighbours, ``classes`` columns of float32 Z:
    ``bytes`` moved to and from memory and ``multiply_adds`` (the module's model; ``llc_mb``: the
    last-level cache: Z's reads not counted when P, B and both states of Z fit in it)."""
    z = n * classes * 4
    p = n * k * 8
    in_cache = 0 < p + 3 * z <= llc_mb * 2**20
    return {"bytes": int(p + z + 2 * z + (0 if in_cache else z)), "multiply_adds": int(n * k * classes),
            "z_in_cache": bool(in_cache)}


def efficiency(roof: Roof, cost: dict, steps: int, measured_s: float) -> dict:
    """The floor of ``steps`` such steps on ``roof`` and the fraction of it ``measured_s`` reaches."""
    mem = steps * cost["bytes"] / (roof.copy_gbps * 1e9)
    comp = steps * 2 * cost["multiply_adds"] / (roof.fma_gflops * 1e9)
    floor = max(mem, comp)
    return {"floor_s": round(floor, 4), "memory_floor_s": round(mem, 4), "compute_floor_s": round(comp, 4),
            "bound": "memory" if mem >= comp else "compute",
            "efficiency": round(floor / measured_s, 4) if measured_s > 0 else None}
