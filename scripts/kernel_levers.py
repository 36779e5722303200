"""Issues 38 and 53's kernel levers, measured side by side on one core (the Jacobi step of Eq. 10 on many columns).

    python scripts/kernel_levers.py BENCH.npz [--columns 64 200 512 1024] [--tiles 8 16 32 64]
        [--rows 2048 1000000000] [--row-major vec64 ...] [--steps 3] [--rounds 5] [--labels 100]

BENCH.npz: an input of ``diffuser-lab-bench`` (``../shared/bench/make_bench_input.py 30000 b.npz 200``);
its graph (K = 24, Morton order) is built with the package and every variant steps the same rows
single-threaded on random Z of the given width (padded to the variant's width). The variants run
interleaved, ``--rounds`` times each, and the best round is reported (the machine is shared: ratios
of one run, not absolute times, are what to read). Variants (float32 accumulation, rows summed in
neighbour order with fused multiply-adds, so the float32 ones give the package kernel's Z bit for bit):

- ``package``: the generated kernel (``backends/numba/_unrolled.steps_16``: 16-wide class blocks, LLVM's
  SLP), rows claimed 512 at a time and done for every block (as before issue 53), or all rows a block;
  ``package zmm``: the package's kernel of several blocks since issue 53 (``_unrolled.steps_32z``: 32-wide
  blocks, ``backends/numba/_zmm``'s 16-lane row kernel, rows claimed ``jacobi.MULTI_CHUNK`` at a time);
- issue 38's, Z row-major (N, W): ``vec64``: explicit 8-lane vectors from numba (a ``f32x8`` type and
  ``numba.extending.intrinsic``s emitting LLVM vector loads and ``llvm.fma.v8f32``), per row column
  groups of 64: 8 independent accumulators; ``vec32x2`` / ``vec16x4``: 2 / 4 rows at a time;
  ``vec64+prefetch``: the lines of row i+3's neighbours prefetched; ``vec64-B+nt``: no B read and
  non-temporal stores; ``vec64 f16``: Z stored as float16; ``vec64 self``: every neighbour is the row
  itself (no gather leaves L1: the kernel's ceiling);
- issue 53's column tiles: Z, Zn and B tile-major (W / T tiles of (N, T)), ``tileT R=r``: rows r at a
  time done for every tile (``all``: a tile's whole column block before the next), 16-lane (zmm)
  vectors for T >= 16 (the package's intrinsics, ``backends/numba/_zmm.py``; ``ymm``: 8 lanes); ``small-idx``: the index stream as row-relative int16 offsets
  (rows where one does not fit: int32 neighbours) and float16 weights, 4 instead of 8 bytes a
  neighbour; ``f16Z``: Z stored as float16, scaled by 2^14 (B and the floor with it);
  ``tileT self``: the ceiling.

Prints a Markdown table: ms per step, the ratio to the package kernel, the fraction of one core's
compute floor (this process's BLAS matmul rate over its threads: unreliable on a loaded machine) and
of the fastest ``self`` variant of the same run; then with ``--labels`` the labels after that many
steps of the input's own B, with each numerics of the 16-wide tile kernels, against scipy's.
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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from diffuser_lab.backends.numba._zmm import f32x16, prefetch  # noqa: E402,F401 - the package's 16-lane vectors
from diffuser_lab.backends.numba._zmm import vabsdiff as wabsdiff, vadd as wadd, vflush as wflush  # noqa: E402,F401
from diffuser_lab.backends.numba._zmm import vfma as wfma, vhmax as whmax, vload as wload  # noqa: E402,F401
from diffuser_lab.backends.numba._zmm import vmax as wmax, vstore as wstore, vzero as wzero  # noqa: E402,F401

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


# ---- issue 53: 16-lane (zmm) vectors: the package's (backends/numba/_zmm.py); here only their float16
# loads and stores, for the small index stream and float16 Z
_V16 = ir.VectorType(_F, 16)
_H16 = ir.VectorType(ir.HalfType(), 16)


def _p16(context, builder, arrty, arr, idx, vt):
    data = cgutils.create_struct_proxy(arrty)(context, builder, value=arr).data
    return builder.bitcast(builder.gep(data, [idx]), vt.as_pointer())


@intrinsic
def wload_h(typingctx, arr, idx):
    """16 float16 (stored as uint16) -> f32x16."""
    def codegen(context, builder, sig, args):
        i = context.cast(builder, args[1], sig.args[1], types.intp)
        return builder.fpext(builder.load(_p16(context, builder, sig.args[0], args[0], i, _H16), align=2), _V16)
    return f32x16(arr, idx), codegen


@intrinsic
def wstore_h(typingctx, arr, idx, v):
    def codegen(context, builder, sig, args):
        i = context.cast(builder, args[1], sig.args[1], types.intp)
        builder.store(builder.fptrunc(args[2], _H16), _p16(context, builder, sig.args[0], args[0], i, _H16), align=2)
        return context.get_dummy_value()
    return types.none(arr, idx, v), codegen


@intrinsic
def h2f(typingctx, arr, idx):
    """arr[idx] (a float16 stored as uint16) as float32."""
    def codegen(context, builder, sig, args):
        i = context.cast(builder, args[1], sig.args[1], types.intp)
        data = cgutils.create_struct_proxy(sig.args[0])(context, builder, value=args[0]).data
        p = builder.bitcast(builder.gep(data, [i]), ir.HalfType().as_pointer())
        return builder.fpext(builder.load(p, align=2), _F)
    return types.float32(arr, idx), codegen


def _tiled(T: int, L: int, small: bool, half: bool) -> str:
    """Column tiles: Z, Zn and B stored tile-major ((W / T) tiles of (N, T), flat); a step takes
    rows ``R`` at a time (R = N: a tile's whole column block before the next tile) and does them for
    every tile before the next R rows, so the index stream of R rows is read once from memory and
    again from cache for every further tile, and a tile's gathers stay within the window of
    neighbour rows x T columns. ``L``: lanes per vector (8: ymm, 16: zmm); ``small``: the index
    stream as row-relative int16 offsets (rows where one does not fit: ``far[i]``, int32
    neighbours) and float16 weights; ``half``: Z stored as float16 (accumulation in float32)."""
    M = T // L
    p = "w" if L == 16 else "v"
    zero, fma, add, flush, vmx, absd, hmx = (p + x for x in ("zero", "fma", "add", "flush", "max", "absdiff", "hmax"))
    ld = f"{p}load_h" if half else f"{p}load"
    st = f"{p}store_h" if half else f"{p}store"
    bl = f"{p}load"
    L_ = ["@njit(boundscheck=False, nogil=True)",
          "def row(nbr, wts, offs, far, wh, wb, Zf, Znf, Bf, floor, i, base, ch, tp):",
          "    K = nbr.shape[1]"]
    L_ += [f"    a{m} = {zero}()" for m in range(M)]
    body = [f"            a{m} = {fma}({ld}(Zf, b + {L * m}), w, a{m})" for m in range(M)]
    if small:  # the row's float16 weights to float32 8 at a time (K % 8 == 0; a scalar conversion is a libcall)
        L_ += ["    for q in range(0, K, 8):",
               "        vstore(wb, q, vload_h(wh, i * K + q))",
               "    if far[i]:",
               "        for kk in range(K):",
               f"            b = base + np.int64(nbr[i, kk]) * {T}",
               "            w = wb[kk]"] + body
        L_ += ["    else:",
               "        for kk in range(K):",
               f"            b = base + (i + np.int64(offs[i, kk])) * {T}",
               "            w = wb[kk]"] + body
    else:
        L_ += ["    if True:",
               "        for kk in range(K):",
               f"            b = base + np.int64(nbr[i, kk]) * {T}",
               "            w = wts[i, kk]"] + body
    L_ += [f"    ib = base + i * {T}"]
    for m in range(M):
        L_ += [f"    v = {flush}({add}(a{m}, {bl}(Bf, ib + {L * m})), floor)",
               f"    ch = {vmx}({absd}(v, {ld}(Zf, ib + {L * m})), ch)", f"    tp = {vmx}(v, tp)",
               f"    {st}(Znf, ib + {L * m}, v)"]
    L_ += ["    return ch, tp", "", "",
           "@njit(boundscheck=False, nogil=True)",
           "def steps(nbr, wts, offs, far, wh, Za, Zb, Bf, floor, n_steps, R):",
           "    n = nbr.shape[0]",
           f"    nt = Za.shape[0] // (n * {T})",
           "    wb = np.zeros(((nbr.shape[1] + 7) // 8) * 8, np.float32)",
           "    for s in range(n_steps):",
           "        src = Za if s % 2 == 0 else Zb",
           "        dst = Zb if s % 2 == 0 else Za",
           f"        ch = {zero}()",
           f"        tp = {zero}()",
           "        for lo in range(0, n, R):",
           "            hi = min(lo + R, n)",
           "            for t in range(nt):",
           f"                base = t * n * {T}",
           "                for i in range(lo, hi):",
           "                    ch, tp = row(nbr, wts, offs, far, wh, wb, src, dst, Bf, floor, i, base, ch, tp)",
           f"    return {hmx}(ch), {hmx}(tp)", ""]
    return "\n".join(L_)


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


_IMPORTS = ("vzero, vload, vstore, vstore_nt, vstore_h, vload_h, vfma, vadd, vflush, vmax, vabsdiff, vhmax, prefetch,"
            " wzero, wload, wload_h, wstore, wstore_h, wfma, wadd, wflush, wmax, wabsdiff, whmax, h2f")


def _kernel(tmp: Path, name: str, source: str):
    """Compile one variant: its source in a module of its own that imports this script's intrinsics."""
    src = ["import numpy as np", "from numba import njit",
           f"from {__name__ if __name__ != '__main__' else '_levers'} import ({_IMPORTS})", "", source]
    path = tmp / f"lever_{name}.py"
    path.write_text("\n".join(src))
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.steps


def _aligned(n: int, dtype=np.float32) -> np.ndarray:
    """(n,) zeros starting on a 64-byte boundary."""
    it = np.dtype(dtype).itemsize
    buf = np.zeros(n + 64 // it, dtype)
    off = (-buf.ctypes.data % 64) // it
    return buf[off:off + n]


ROW_MAJOR = {  # issue 38's variants, Z row-major (N, W): name: (G, R, half, nt, no_b, pf, self_neighbours)
    "vec64": (64, 1, False, False, False, False, False),
    "vec32x2": (32, 2, False, False, False, False, False),
    "vec16x4": (16, 4, False, False, False, False, False),
    "vec64+prefetch": (64, 1, False, False, False, True, False),
    "vec64-B+nt": (64, 1, False, True, True, False, False),
    "vec64 f16": (64, 1, True, False, False, False, False),
    "vec64 self": (64, 1, False, False, False, False, True),
}
ROW_MAJOR_DEFAULT = ("vec64", "vec64+prefetch", "vec64 f16", "vec64 self")


def tile_variants(tiles, rows_list, n):
    """Column-tile variants: name: (T, L, small, half, R, self_neighbours)."""
    out = {}
    for T in tiles:
        L = 8 if T < 16 else 16
        for R in rows_list:
            r = "all" if R >= n else str(R)
            out[f"tile{T} R={r}"] = (T, L, False, False, min(R, n), False)
            out[f"tile{T} R={r} small-idx"] = (T, L, True, False, min(R, n), False)
            out[f"tile{T} R={r} small-idx f16Z"] = (T, L, True, True, min(R, n), False)
        if T == 16:  # ymm instead of zmm
            out[f"tile16 ymm R={'all' if rows_list[0] >= n else rows_list[0]}"] = (16, 8, False, False, min(rows_list[0], n), False)
    T = max(tiles)
    out[f"tile{T} self"] = (T, 16 if T >= 16 else 8, False, False, n, True)  # every gather in L1
    out[f"tile{min(tiles)} self"] = (min(tiles), 16 if min(tiles) >= 16 else 8, False, False, n, True)
    return out


def tile_major(X: np.ndarray, T: int) -> np.ndarray:
    """(N, W) -> flat (W / T tiles of (N, T))."""
    n, w = X.shape
    return np.ascontiguousarray(X.reshape(n, w // T, T).transpose(1, 0, 2)).ravel()


def from_tiles(f: np.ndarray, n: int, T: int) -> np.ndarray:
    return f.reshape(-1, n, T).transpose(1, 0, 2).reshape(n, -1)


def small_index(nbr: np.ndarray, wts: np.ndarray):
    """Row-relative int16 offsets (0 on rows where one does not fit: ``far``), float16 weights (flat uint16)."""
    n = nbr.shape[0]
    rel = nbr.astype(np.int64) - np.arange(n)[:, None]
    far = (np.abs(rel) > 32767).any(1)
    offs = np.where(far[:, None], 0, rel).astype(np.int16)
    return offs, far.astype(np.uint8), wts.astype(np.float16).view(np.uint16).ravel()


F16_SCALE = np.float32(2.0 ** 14)
"""The scaled float16 Z: the iteration on Z / scale * 2^14 (B and the floor scaled with it; the step is
linear): Z / scale <= ~1 lands below float16's 65,504 and its smallest entries above the subnormals."""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("input")
    ap.add_argument("--columns", type=int, nargs="+", default=[64, 200, 512, 1024])
    ap.add_argument("--tiles", type=int, nargs="+", default=[8, 16, 32, 64])
    ap.add_argument("--rows", type=int, nargs="+", default=[2048, 10**9],
                    help="rows per pass over the tiles (>= N: each tile's whole column block in turn)")
    ap.add_argument("--row-major", nargs="*", default=list(ROW_MAJOR_DEFAULT), help="issue 38's variants to run too")
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=5, help="interleaved rounds; the best of them is reported")
    ap.add_argument("--labels", type=int, default=100, help="steps of the label check on the input's classes (0: none)")
    a = ap.parse_args(argv)
    sys.modules.setdefault("_levers", sys.modules[__name__])
    import os

    from diffuser_lab.backends import roof
    from diffuser_lab.backends.numba import _unrolled, slp
    from diffuser_lab.backends.numba import jacobi as kernels
    from diffuser_lab.method.diffusion import normalise
    from diffuser_lab.method.graph import build_graph

    with np.load(a.input) as f:
        g = build_graph(f["points"].astype(np.float32), 24, f["normals"].astype(np.float32), sigma_s=0.2,
                        sigma_d_factor=2.0)
        system = normalise(g, f["evidence"].astype(np.float32), 1e-4)
    be = system.start(backend="numba", tol=0.0, sparse_classes="off")
    nbr, wts = be.nbr, be.wts
    inp = be.inputs
    N, K = nbr.shape
    self_nbr = np.repeat(np.arange(N, dtype=np.int32)[:, None], K, 1)
    offs, far, wh = small_index(nbr, wts)
    self_offs, self_far, _ = small_index(self_nbr, wts)
    rng = np.random.default_rng(0)
    core_gf = roof.measure_roof(copy_mb=64).fma_gflops / max(1, __import__("numba").get_num_threads())
    floor = np.float32(1e-6)
    load0 = os.getloadavg()[0]
    print(f"{N:,} rows, K = {K}; rows with an offset beyond int16: {int(far.sum())} ({far.mean():.2%}); "
          f"index stream {nbr.nbytes + wts.nbytes} -> {offs.nbytes + wh.nbytes + far.nbytes} bytes; load {load0:.1f}")

    tv = tile_variants(a.tiles, sorted(a.rows), N)
    rows, labels_rows = [], []
    with tempfile.TemporaryDirectory() as tmp:
        kern = {name: _kernel(Path(tmp), f"rm{j}", _group(G=v[0], R=v[1], half=v[2], nt=v[3], no_b=v[4], pf=v[5]))
                for j, (name, v) in enumerate(ROW_MAJOR.items()) if name in a.row_major}
        tk = {}
        for name, (T, L, small, half, R, _) in tv.items():
            key = (T, L, small, half)
            if key not in tk:
                tk[key] = _kernel(Path(tmp), f"t{T}_{L}_{int(small)}{int(half)}", _tiled(T, L, small, half))

        def run_tile(name, Zs, Zns, Bs, flo, n_steps):
            T, L, small, half, R, selfn = tv[name]
            nb_ = self_nbr if selfn else nbr
            of, fa = (self_offs, self_far) if selfn else (offs, far)
            return tk[(T, L, small, half)](nb_, wts, of, fa, wh, Zs, Zns, Bs, flo, n_steps, R)

        for C in a.columns:
            calls = {}
            pad = lambda m: -(-C // m) * m  # noqa: E731
            Z0 = rng.random((N, pad(64))).astype(np.float32)
            B0 = (rng.random((N, pad(64))) * 0.01).astype(np.float32)
            W16 = pad(16)
            Zb, Bb = tile_major(Z0[:, :W16], 16).reshape(-1, N * 16), tile_major(B0[:, :W16], 16).reshape(-1, N * 16)
            Znb = np.zeros_like(Zb)
            widths = {"package (16-wide blocks, SLP), 512 rows": W16, "package, all rows a block": W16}
            for R_, nm in ((512, "package (16-wide blocks, SLP), 512 rows"), (N, "package, all rows a block")):
                calls[nm] = (lambda R_=R_: _unrolled.steps_16(
                    nbr, wts, Zb, Znb, Bb, floor, -1.0, kernels.EVERY_ROW, *kernels.untracked(a.steps, 1), a.steps, R_, 0, 1,
                    np.zeros(1 + a.steps, np.int64), np.zeros((a.steps, 1, 2), np.float32)))
            W32 = pad(32)  # the package's kernel of several blocks: 32-wide blocks, the zmm row kernel
            Zz, Bz = tile_major(Z0[:, :W32], 32).reshape(-1, N * 32), tile_major(B0[:, :W32], 32).reshape(-1, N * 32)
            Znz = np.zeros_like(Zz)
            nm = f"package zmm (32-wide blocks), {kernels.MULTI_CHUNK} rows"
            widths[nm] = W32
            calls[nm] = lambda: _unrolled.steps_32z(
                nbr, wts, Zz, Znz, Bz, floor, -1.0, kernels.EVERY_ROW, a.steps, kernels.MULTI_CHUNK, 0, 1,
                np.zeros(1 + a.steps, np.int64), np.zeros((a.steps, 1, 2), np.float32))
            W64 = pad(64)
            Zr, Br, Znr = _aligned(N * W64), _aligned(N * W64), _aligned(N * W64)
            Zr[:] = Z0[:, :W64].ravel()
            Br[:] = B0[:, :W64].ravel()
            Zrh, Znrh = Zr.astype(np.float16).view(np.uint16), np.zeros(N * W64, np.uint16)
            for name in kern:
                v = ROW_MAJOR[name]
                z, zn = (Zrh, Znrh) if v[2] else (Zr, Znr)
                nb_ = self_nbr if v[6] else nbr
                calls[name] = (lambda name=name, z=z, zn=zn, nb_=nb_: kern[name](nb_, wts, z, zn, Br, floor, a.steps, W64))
                widths[name] = W64
            bufs = {}
            for name, (T, L, small, half, R, selfn) in tv.items():
                W = pad(T)
                if (T, half) not in bufs:
                    zt, bt = tile_major(Z0[:, :W], T), tile_major(B0[:, :W], T)
                    if half:
                        zt = (zt * F16_SCALE).astype(np.float16).view(np.uint16)
                        bt = bt * F16_SCALE
                    bufs[(T, half)] = (zt, np.zeros_like(zt), bt)
                zt, znt, bt = bufs[(T, half)]
                flo = floor * F16_SCALE if half else floor
                calls[name] = (lambda name=name, zt=zt, znt=znt, bt=bt, flo=flo: run_tile(name, zt, znt, bt, flo, a.steps))
                widths[name] = W
            best = {name: float("inf") for name in calls}
            with slp():
                for fn in calls.values():
                    fn()
                loads = []
                for _ in range(a.rounds):  # interleaved: every variant once a round
                    loads.append(os.getloadavg()[0])
                    for name, fn in calls.items():
                        t0 = time.perf_counter()
                        fn()
                        best[name] = min(best[name], (time.perf_counter() - t0) / a.steps)
            ceiling = min(t for name, t in best.items() if "self" in name)
            base = best["package (16-wide blocks, SLP), 512 rows"]
            flops = 2 * N * K * C
            for name, t in best.items():
                rows.append(f"| {C} | {name} | {widths[name]} | {t * 1e3:.2f} | {base / t:.2f} | "
                            f"{flops / t / 1e9 / core_gf:.2f} | {ceiling / t:.2f} |")
            print(f"columns {C}: load during the rounds {min(loads):.1f}-{max(loads):.1f}", flush=True)

        print_table(core_gf, rows)
        if a.labels:
            labels_rows = label_check(system, be, nbr, wts, offs, far, wh, tk, a.labels, inp)
    system.close()
    if labels_rows:
        print()
        print("| labels after the steps (the input's classes) | = scipy |")
        print("| --- | --- |")
        print("\n".join(labels_rows))
    return 0


def print_table(core_gf, rows):
    print(f"one core's compute roof: {core_gf:.1f} GFLOP/s (BLAS matmul over its threads); "
          f"ceiling = the fastest 'self' variant (every gather in L1) of the same width")
    print("| columns | variant | padded width | ms / step (best of rounds) | x today's kernel | of the core's roof | of the L1 ceiling |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    print("\n".join(rows), flush=True)


def label_check(system, be, nbr, wts, offs, far, wh, tk, n_steps, inp):
    """The real iteration (the input's B, Z = 0, ``n_steps`` steps) with each numerics of the tile
    kernels (float32; small index stream; scaled float16 Z; both) against scipy's labels."""
    N = nbr.shape[0]
    A = len(inp.active)
    def lab(Z):
        out = Z.argmax(1)
        return np.where(Z.max(1) > 0, out, -1)

    be.steps(n_steps)
    pkg = lab(np.asarray(be.state()))
    sc = system.start(backend="scipy", tol=0.0, sparse_classes="off")  # closes the numba backend
    sc.steps(n_steps)
    ref = lab(np.asarray(sc.state(), np.float32))
    out = [f"| package kernel (numba, {n_steps} steps) | {(pkg == ref).mean():.4%} |"]
    Bd = np.asarray(inp.B, np.float32)[:, inp.active] / inp.scale
    T = 16
    W = -(-A // T) * T
    B0 = np.zeros((N, W), np.float32)
    B0[:, :A] = Bd
    for (TT, L, small, half), fn in tk.items():
        if TT != T:
            continue
        S = F16_SCALE if half else np.float32(1.0)
        bt = tile_major(B0 * S, T)
        if half:
            za, zb = np.zeros(N * W, np.uint16), np.zeros(N * W, np.uint16)
        else:
            za, zb = np.zeros(N * W, np.float32), np.zeros(N * W, np.float32)
        fn(nbr, wts, offs, far, wh, za, zb, bt, np.float32(inp.floor) * S, n_steps, N)
        z = za if n_steps % 2 == 0 else zb
        if half:
            z = z.view(np.float16).astype(np.float32)
        Z = from_tiles(z, N, T)[:, :A] / S
        name = f"tile{T} {'zmm' if L == 16 else 'ymm'}" + (" small-idx" if small else "") + (" f16Z (scaled 2^14)" if half else "")
        out.append(f"| {name} | {(lab(Z) == ref).mean():.4%} |")
    return out


if __name__ == "__main__":
    raise SystemExit(main())
