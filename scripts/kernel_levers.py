"""Issue 38's kernel levers, measured side by side on one core (the Jacobi step of Eq. 10 on many columns).

    python scripts/kernel_levers.py BENCH.npz [--columns 64 200 512] [--steps 3]

BENCH.npz: an input of ``diffuser-lab-bench`` (``../shared/bench/make_bench_input.py 30000 b.npz 200``);
its graph (K = 24, Morton order) is built with the package and every variant steps the same rows
single-threaded on random Z of the given width. Variants (all float32 accumulation, rows summed in
neighbour order, so the float32 ones give the package kernel's result bit for bit):

- ``package``: today's kernel (``backends/numba/_unrolled.steps_16``: 16-wide class blocks, LLVM's SLP);
- ``vec64``: explicit 8-lane vectors from numba (a ``f32x8`` type and ``numba.extending.intrinsic``s
  emitting LLVM vector loads and ``llvm.fma.v8f32``), Z row-major, per row column groups of 64:
  8 independent accumulators;
- ``vec16x4`` / ``vec32x2``: the same with 4 / 2 Morton-adjacent rows at a time (register blocking);
- ``vec64+prefetch``: the lines of row i+3's neighbours prefetched;
- ``vec64-B+nt``: no B read and non-temporal stores (the bound of a sparse B and streaming stores);
- ``vec64 f16``: Z stored as float16 (F16C conversion on load, accumulation in float32);
- ``vec64 self``: every neighbour is the row itself: no gather leaves L1 (the kernel's ceiling).

Prints a Markdown table: ms per step and GFLOP/s (a multiply-add = 2 flops), and the fraction of
one core's compute floor (this process's BLAS matmul rate over its threads).
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic, models, register_model

LANES = 8
_F = ir.FloatType()
_V = ir.VectorType(_F, LANES)


class F32x8(types.Type):
    def __init__(self):
        super().__init__(name="f32x8")


f32x8 = F32x8()


@register_model(F32x8)
class _Model(models.PrimitiveModel):
    def __init__(self, dmm, fe_type):
        super().__init__(dmm, fe_type, _V)


def _ptr(context, builder, arrty, arr, idx):
    data = cgutils.create_struct_proxy(arrty)(context, builder, value=arr).data
    p = builder.gep(data, [idx])
    return builder.bitcast(p, _V.as_pointer())


def _splat(builder, s):
    v = builder.insert_element(ir.Constant(_V, ir.Undefined), s, ir.Constant(ir.IntType(32), 0))
    return builder.shuffle_vector(v, ir.Constant(_V, ir.Undefined), ir.Constant(ir.VectorType(ir.IntType(32), LANES), [0] * LANES))


@intrinsic
def vzero(typingctx):
    def codegen(context, builder, sig, args):
        return ir.Constant(_V, [0.0] * LANES)
    return f32x8(), codegen


@intrinsic
def vload(typingctx, arr, idx):
    def codegen(context, builder, sig, args):
        i = context.cast(builder, args[1], sig.args[1], types.intp)
        ld = builder.load(_ptr(context, builder, sig.args[0], args[0], i), align=4)
        return ld
    return f32x8(arr, idx), codegen


@intrinsic
def vstore(typingctx, arr, idx, v):
    def codegen(context, builder, sig, args):
        i = context.cast(builder, args[1], sig.args[1], types.intp)
        builder.store(args[2], _ptr(context, builder, sig.args[0], args[0], i), align=4)
        return context.get_dummy_value()
    return types.none(arr, idx, v), codegen


@intrinsic
def vfma(typingctx, x, s, acc):
    """acc + x * s (s a float32 scalar), one fused multiply-add per lane."""
    def codegen(context, builder, sig, args):
        fma = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_V, [_V, _V, _V]), "llvm.fma.v8f32")
        return builder.call(fma, [args[0], _splat(builder, args[1]), args[2]])
    return f32x8(x, s, acc), codegen


@intrinsic
def vadd(typingctx, a, b):
    def codegen(context, builder, sig, args):
        return builder.fadd(args[0], args[1])
    return f32x8(a, b), codegen


@intrinsic
def vflush(typingctx, v, floor):
    """v where v >= floor, else 0."""
    def codegen(context, builder, sig, args):
        ge = builder.fcmp_ordered(">=", args[0], _splat(builder, args[1]))
        return builder.select(ge, args[0], ir.Constant(_V, [0.0] * LANES))
    return f32x8(v, floor), codegen


@intrinsic
def vmax(typingctx, a, b):
    """a where a > b else b (as the scalar kernel's selects)."""
    def codegen(context, builder, sig, args):
        gt = builder.fcmp_ordered(">", args[0], args[1])
        return builder.select(gt, args[0], args[1])
    return f32x8(a, b), codegen


@intrinsic
def vabsdiff(typingctx, a, b):
    def codegen(context, builder, sig, args):
        d = builder.fsub(args[0], args[1])
        fabs = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_V, [_V]), "llvm.fabs.v8f32")
        return builder.call(fabs, [d])
    return f32x8(a, b), codegen


@intrinsic
def vhmax(typingctx, v):
    """Largest lane (float32)."""
    def codegen(context, builder, sig, args):
        out = builder.extract_element(args[0], ir.Constant(ir.IntType(32), 0))
        for k in range(1, LANES):
            e = builder.extract_element(args[0], ir.Constant(ir.IntType(32), k))
            out = builder.select(builder.fcmp_ordered(">", e, out), e, out)
        return out
    return types.float32(v), codegen


@intrinsic
def vstore_nt(typingctx, arr, idx, v):
    """Non-temporal store (the address must be 32-byte aligned)."""
    def codegen(context, builder, sig, args):
        i = context.cast(builder, args[1], sig.args[1], types.intp)
        st = builder.store(args[2], _ptr(context, builder, sig.args[0], args[0], i), align=32)
        st.set_metadata("nontemporal", builder.module.add_metadata([ir.Constant(ir.IntType(32), 1)]))
        return context.get_dummy_value()
    return types.none(arr, idx, v), codegen


@intrinsic
def prefetch(typingctx, arr, idx):
    """Prefetch arr[idx]'s cache line (read, keep in all levels)."""
    def codegen(context, builder, sig, args):
        i = context.cast(builder, args[1], sig.args[1], types.intp)
        data = cgutils.create_struct_proxy(sig.args[0])(context, builder, value=args[0]).data
        p = builder.bitcast(builder.gep(data, [i]), ir.IntType(8).as_pointer())
        i32 = ir.IntType(32)
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [ir.IntType(8).as_pointer(), i32, i32, i32]), "llvm.prefetch.p0")
        builder.call(fn, [p, ir.Constant(i32, 0), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()
    return types.none(arr, idx), codegen


_H = ir.VectorType(ir.HalfType(), LANES)


def _hptr(context, builder, arrty, arr, idx):
    data = cgutils.create_struct_proxy(arrty)(context, builder, value=arr).data
    return builder.bitcast(builder.gep(data, [idx]), _H.as_pointer())


@intrinsic
def vload_h(typingctx, arr, idx):
    """8 float16 (stored as uint16) -> f32x8."""
    def codegen(context, builder, sig, args):
        i = context.cast(builder, args[1], sig.args[1], types.intp)
        return builder.fpext(builder.load(_hptr(context, builder, sig.args[0], args[0], i), align=2), _V)
    return f32x8(arr, idx), codegen


@intrinsic
def vstore_h(typingctx, arr, idx, v):
    def codegen(context, builder, sig, args):
        i = context.cast(builder, args[1], sig.args[1], types.intp)
        builder.store(builder.fptrunc(args[2], _H), _hptr(context, builder, sig.args[0], args[0], i), align=2)
        return context.get_dummy_value()
    return types.none(arr, idx, v), codegen


def _group(G: int, R: int, half: bool, nt: bool, no_b: bool, pf: bool) -> str:
    M, ld, st = G // 8, "vload_h" if half else "vload", "vstore_h" if half else ("vstore_nt" if nt else "vstore")
    L = ["@njit(boundscheck=False, nogil=True)",
         "def grp(nbr, wts, Zf, Znf, Bf, floor, i, W, g, ch, tp):",
         "    K = nbr.shape[1]"]
    L += [f"    a{r}_{m} = vzero()" for r in range(R) for m in range(M)]
    L += ["    for kk in range(K):"]
    for r in range(R):
        L += [f"        b{r} = np.int64(nbr[i + {r}, kk]) * W + g", f"        w{r} = wts[i + {r}, kk]"]
    if pf:
        L += ["        if i + 3 < nbr.shape[0]:", "            pb = np.int64(nbr[i + 3, kk]) * W + g"]
        L += [f"            prefetch(Zf, pb + {16 * q})" for q in range((M + 1) // 2)]
    L += [f"        a{r}_{m} = vfma({ld}(Zf, b{r} + {8 * m}), w{r}, a{r}_{m})" for r in range(R) for m in range(M)]
    for r in range(R):
        L += [f"    ib = (i + {r}) * W + g"]
        for m in range(M):
            L += [f"    v = vflush(a{r}_{m}, floor)" if no_b else f"    v = vflush(vadd(a{r}_{m}, vload(Bf, ib + {8 * m})), floor)",
                  f"    ch = vmax(vabsdiff(v, {ld}(Zf, ib + {8 * m})), ch)", "    tp = vmax(v, tp)",
                  f"    {st}(Znf, ib + {8 * m}, v)"]
    L += ["    return ch, tp", "", "",
          "@njit(boundscheck=False, nogil=True)",
          "def steps(nbr, wts, Za, Zb, Bf, floor, n_steps, W):",
          "    n = nbr.shape[0]",
          "    for s in range(n_steps):",
          "        src = Za if s % 2 == 0 else Zb",
          "        dst = Zb if s % 2 == 0 else Za",
          "        ch = vzero()",
          "        tp = vzero()",
          f"        for i in range(0, n - {R} + 1, {R}):",
          f"            for g in range(0, W, {G}):",
          "                ch, tp = grp(nbr, wts, src, dst, Bf, floor, i, W, g, ch, tp)",
          "    return vhmax(ch), vhmax(tp)", ""]
    return "\n".join(L)


def _kernel(tmp: Path, name: str, **kw):
    """Compile one variant: its source in a module of its own that imports this script's intrinsics."""
    src = ["import numpy as np", "from numba import njit",
           f"from {__name__ if __name__ != '__main__' else '_levers'} import (vzero, vload, vstore, vstore_nt, vstore_h,"
           " vload_h, vfma, vadd, vflush, vmax, vabsdiff, vhmax, prefetch)", "", _group(**kw)]
    path = tmp / f"lever_{name}.py"
    path.write_text("\n".join(src))
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.steps


def _aligned(n: int) -> np.ndarray:
    """(n,) float32 zeros starting on a 64-byte boundary."""
    buf = np.zeros(n + 16, np.float32)
    off = (-buf.ctypes.data % 64) // 4
    return buf[off:off + n]


VARIANTS = {  # name: (G, R, half, nt, no_b, pf, self_neighbours)
    "vec64": (64, 1, False, False, False, False, False),
    "vec32x2": (32, 2, False, False, False, False, False),
    "vec16x4": (16, 4, False, False, False, False, False),
    "vec64+prefetch": (64, 1, False, False, False, True, False),
    "vec64-B+nt": (64, 1, False, True, True, False, False),
    "vec64 f16": (64, 1, True, False, False, False, False),
    "vec64 self": (64, 1, False, False, False, False, True),
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("input")
    ap.add_argument("--columns", type=int, nargs="+", default=[64, 192, 512])
    ap.add_argument("--steps", type=int, default=3)
    a = ap.parse_args(argv)
    sys.modules.setdefault("_levers", sys.modules[__name__])
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from diffuser_lab.backends import roof
    from diffuser_lab.backends.numba import _unrolled, slp
    from diffuser_lab.method.diffusion import normalise
    from diffuser_lab.method.graph import build_graph

    with np.load(a.input) as f:
        g = build_graph(f["points"].astype(np.float32), 24, f["normals"].astype(np.float32), sigma_s=0.2,
                        sigma_d_factor=2.0)
        system = normalise(g, f["evidence"].astype(np.float32), 1e-4)
    be = system.start(backend="numba", tol=0.0, sparse_classes="off")
    nbr, wts = be.nbr, be.wts
    system.close()
    N, K = nbr.shape
    self_nbr = np.repeat(np.arange(N, dtype=np.int32)[:, None], K, 1)
    rng = np.random.default_rng(0)
    core_gf = roof.measure_roof(copy_mb=64).fma_gflops / max(1, __import__("numba").get_num_threads())
    floor = np.float32(1e-6)

    def timed(fn) -> float:
        fn()
        ts = []
        for _ in range(3):
            t0 = time.perf_counter()
            fn()
            ts.append((time.perf_counter() - t0) / a.steps)
        return min(ts)

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        kernels = {name: _kernel(Path(tmp), name.replace(" ", "_").replace("+", "p").replace("-", "m"),
                                 G=v[0], R=v[1], half=v[2], nt=v[3], no_b=v[4], pf=v[5])
                   for name, v in VARIANTS.items()}
        for C in a.columns:
            W = -(-C // 64) * 64  # every variant's groups divide it
            flops = 2 * N * K * W
            res = {}
            nb = W // 16  # the package's layout: (blocks, N * 16)
            Zb = rng.random((nb, N * 16)).astype(np.float32)
            Bb = (rng.random((nb, N * 16)) * 0.01).astype(np.float32)
            Znb = np.zeros_like(Zb)
            with slp():
                res["package"] = timed(lambda: _unrolled.steps_16(
                    nbr, wts, Zb, Znb, Bb, floor, -1.0, a.steps, 512, 0, 1,
                    np.zeros(1 + a.steps, np.int64), np.zeros((a.steps, 1, 2), np.float32)))  # fresh tickets a call
            Z, B, Zn = _aligned(N * W), _aligned(N * W), _aligned(N * W)  # non-temporal stores need 32-byte rows
            Z[:] = rng.random(N * W)
            B[:] = rng.random(N * W) * 0.01
            for name, v in VARIANTS.items():
                z, zn = (Z.astype(np.float16).view(np.uint16), np.zeros(N * W, np.uint16)) if v[2] else (Z, Zn)
                nb_ = self_nbr if v[6] else nbr
                res[name] = timed(lambda: kernels[name](nb_, wts, z, zn, B, floor, a.steps, W))
            for name, t in res.items():
                rows.append(f"| {N:,} x {W} | {name} | {t * 1e3:.2f} | {flops / t / 1e9:.1f} | {flops / t / 1e9 / core_gf:.2f} |")
    print(f"one core's compute roof: {core_gf:.1f} GFLOP/s (BLAS matmul over its threads)")
    print("| rows x columns | variant | ms / step | GFLOP/s | of the core's roof |")
    print("| --- | --- | --- | --- | --- |")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
