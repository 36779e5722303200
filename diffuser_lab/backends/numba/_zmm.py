"""The Jacobi step of several 16- or 32-wide class blocks with explicit 16-lane vectors (issue 53).

LLVM's SLP vectoriser puts the generated 16-wide row kernel (``_unrolled.rows_16``) in two 8-lane
(ymm) halves; written against ``<16 x float>`` with ``llvm.fma.v16f32`` (a numba type and a few
``numba.extending.intrinsic``s), a neighbour of a block is one 16-lane load and one fused
multiply-add (one zmm instruction each with AVX-512; two ymm ones without it: the same code, as
fast as before). Rows are summed in neighbour order with fused multiply-adds, as ``rows_16``: the
same Z bit for bit. Each row prefetches the lines of row i + :data:`AHEAD`'s neighbours (issue 38's
lever). Measured (``scripts/kernel_levers.py``, 30k points x 200 classes, one core, 2026-12-07):
16 wide 1.3-1.6x, 32 wide 2.0-2.2x the SLP kernel with rows claimed 2,048 at a time, the prefetch
another 1.2x (see docs/results/performance.md).

Here are the vector type and its intrinsics, written by hand. The kernels that use them are generated
into ``_unrolled.py`` (``python -m diffuser_lab.backends.numba.jacobi``): the row kernels ``rows_16z`` /
``rows_32z`` (``jacobi.zmm_rows_source``: the contract of ``rows_16`` / ``rows_32`` with one 16-lane
accumulator per 16 classes, where the SLP 32-wide kernel runs out of registers) and their runs of steps
on threads ``steps_16z`` / ``steps_32z`` (jacobi's one step loop, ``_STEPS_TEMPLATE``, without the statistics).
"""
from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic, models, register_model


_F = ir.FloatType()
_V = ir.VectorType(_F, 16)


class F32x16(types.Type):
    def __init__(self):
        super().__init__(name="diffuser_lab_f32x16")


f32x16 = F32x16()


@register_model(F32x16)
class _Model(models.PrimitiveModel):
    def __init__(self, dmm, fe_type):
        super().__init__(dmm, fe_type, _V)


def _ptr(context, builder, arrty, arr, idx):
    data = cgutils.create_struct_proxy(arrty)(context, builder, value=arr).data
    return builder.bitcast(builder.gep(data, [idx]), _V.as_pointer())


def _splat(builder, s):
    v = builder.insert_element(ir.Constant(_V, ir.Undefined), s, ir.Constant(ir.IntType(32), 0))
    return builder.shuffle_vector(v, ir.Constant(_V, ir.Undefined), ir.Constant(ir.VectorType(ir.IntType(32), 16), [0] * 16))


@intrinsic
def vzero(typingctx):
    def codegen(context, builder, sig, args):
        return ir.Constant(_V, [0.0] * 16)
    return f32x16(), codegen


@intrinsic
def vload(typingctx, arr, idx):
    """arr[idx:idx + 16] (float32, C-contiguous, no bounds check)."""
    def codegen(context, builder, sig, args):
        i = context.cast(builder, args[1], sig.args[1], types.intp)
        return builder.load(_ptr(context, builder, sig.args[0], args[0], i), align=4)
    return f32x16(arr, idx), codegen


@intrinsic
def vstore(typingctx, arr, idx, v):
    def codegen(context, builder, sig, args):
        i = context.cast(builder, args[1], sig.args[1], types.intp)
        builder.store(args[2], _ptr(context, builder, sig.args[0], args[0], i), align=4)
        return context.get_dummy_value()
    return types.none(arr, idx, v), codegen


@intrinsic
def vfma(typingctx, x, s, acc):
    """acc + x * s (s a float32 scalar), fused, per lane."""
    def codegen(context, builder, sig, args):
        fma = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_V, [_V, _V, _V]), "llvm.fma.v16f32")
        return builder.call(fma, [args[0], _splat(builder, args[1]), args[2]])
    return f32x16(x, s, acc), codegen


@intrinsic
def vadd(typingctx, a, b):
    def codegen(context, builder, sig, args):
        return builder.fadd(args[0], args[1])
    return f32x16(a, b), codegen


@intrinsic
def vflush(typingctx, v, floor):
    """v where v >= floor, else 0 (as rows_16's selects)."""
    def codegen(context, builder, sig, args):
        ge = builder.fcmp_ordered(">=", args[0], _splat(builder, args[1]))
        return builder.select(ge, args[0], ir.Constant(_V, [0.0] * 16))
    return f32x16(v, floor), codegen


@intrinsic
def vmax(typingctx, a, b):
    """a where a > b, else b."""
    def codegen(context, builder, sig, args):
        return builder.select(builder.fcmp_ordered(">", args[0], args[1]), args[0], args[1])
    return f32x16(a, b), codegen


@intrinsic
def vabsdiff(typingctx, a, b):
    def codegen(context, builder, sig, args):
        fabs = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_V, [_V]), "llvm.fabs.v16f32")
        return builder.call(fabs, [builder.fsub(args[0], args[1])])
    return f32x16(a, b), codegen


@intrinsic
def vhmax(typingctx, v):
    """The largest lane, as float32."""
    def codegen(context, builder, sig, args):
        out = builder.extract_element(args[0], ir.Constant(ir.IntType(32), 0))
        for k in range(1, 16):
            e = builder.extract_element(args[0], ir.Constant(ir.IntType(32), k))
            out = builder.select(builder.fcmp_ordered(">", e, out), e, out)
        return out
    return types.float32(v), codegen


@intrinsic
def prefetch(typingctx, arr, idx):
    """Prefetch the cache line of arr[idx] (read, keep in all levels)."""
    def codegen(context, builder, sig, args):
        i = context.cast(builder, args[1], sig.args[1], types.intp)
        data = cgutils.create_struct_proxy(sig.args[0])(context, builder, value=args[0]).data
        p = builder.bitcast(builder.gep(data, [i]), ir.IntType(8).as_pointer())
        i32 = ir.IntType(32)
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [ir.IntType(8).as_pointer(), i32, i32, i32]),
                                            "llvm.prefetch.p0")
        builder.call(fn, [p, ir.Constant(i32, 0), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()
    return types.none(arr, idx), codegen


AHEAD = 4
"""Rows ahead whose neighbours' lines the kernels prefetch (30k x 224, one thread, best of 9 under load:
3 / 4 / 6 rows ahead 1.05x / 1.22x / 1.15x the kernel without; medians 1.19x at 4)."""
