"""Thread synchronisation inside compiled code (numba intrinsics; imported only with numba).

The Jacobi workers of :mod:`diffuser_lab.backends.numba.jacobi` run many steps in one compiled call per
thread, so the diffusion does not need the GIL between steps (a recorder thread holding it for
Python work would otherwise stall every step). Between steps they meet at a barrier built on
two atomics: a fetch-and-add and an acquiring load of an int64 array element. A waiting thread
spins briefly (``pause``), then yields its core, then sleeps in 20 us naps, so a thread of the
same process that the OS parked (two cores, a recorder busy) gets a core back instead of
watching another spin.
"""
from __future__ import annotations

import platform

import numpy as np

from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

_I64_ARRAY = types.Array(types.int64, 1, "C")


def _element_pointer(context, builder, aryty, ary, idx):
    arr = context.make_array(aryty)(context, builder, ary)
    return cgutils.get_item_pointer(context, builder, aryty, arr, [idx])


@intrinsic
def atomic_add(typingctx, arr, idx, val):
    """``old = arr[idx]; arr[idx] += val`` atomically (sequentially consistent); returns old."""
    def codegen(context, builder, sig, args):
        ptr = _element_pointer(context, builder, sig.args[0], args[0], args[1])
        return builder.atomic_rmw("add", ptr, args[2], "seq_cst")

    return types.int64(_I64_ARRAY, types.intp, types.int64), codegen


@intrinsic
def atomic_load(typingctx, arr, idx):
    """``arr[idx]`` read with acquire ordering (sees every write made before a matching add)."""
    def codegen(context, builder, sig, args):
        ptr = _element_pointer(context, builder, sig.args[0], args[0], args[1])
        return builder.load_atomic(ptr, "acquire", 8)

    return types.int64(_I64_ARRAY, types.intp), codegen


def _call_void(name: str, ret: ir.Type, argtypes=(), convert=None):
    def codegen(context, builder, sig, args):
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ret, list(argtypes)), name)
        builder.call(fn, [convert(builder, a) for a in args] if convert else [])
        return context.get_dummy_value()

    return codegen


_X86 = platform.machine().lower() in ("x86_64", "amd64", "i386", "i686")


@intrinsic
def cpu_pause(typingctx):
    """x86 ``pause`` (a spin-wait hint); nothing on other processors."""
    if _X86:
        return types.void(), _call_void("llvm.x86.sse2.pause", ir.VoidType())
    return types.void(), lambda context, builder, sig, args: context.get_dummy_value()


@intrinsic
def os_yield(typingctx):
    """libc ``sched_yield()``."""
    return types.void(), _call_void("sched_yield", ir.IntType(32))


@intrinsic
def os_usleep(typingctx, us):
    """libc ``usleep(us)``."""
    return types.void(types.int64), _call_void("usleep", ir.IntType(32), [ir.IntType(32)],
                                               lambda b, a: b.trunc(a, ir.IntType(32)))


SPIN_PAUSES = 2000
"""Pauses before a waiting thread starts yielding (~20-40 us on current x86 cores)."""


@njit(cache=True, nogil=True)
def wait_until(ctrl, idx, target):
    """Block until ``ctrl[idx] >= target``: spin, then yield, then nap 20 us at a time."""
    spins = 0
    while atomic_load(ctrl, idx) < target:
        spins += 1
        if spins < SPIN_PAUSES:
            cpu_pause()
        elif spins < SPIN_PAUSES + 100:
            os_yield()
        else:
            os_usleep(20)


@njit(cache=True, nogil=True, boundscheck=False)
def all_converged(res, s, nthreads, tol):
    """After step ``s``'s barrier: the stopping rule of every compiled run of steps, seen alike by
    every thread. ``res[s, t, 0:2]`` is thread t's (max |Zn - Z|, max Zn); True when the global
    relative change max|Zn - Z| / max Zn is <= ``tol``."""
    gch = np.float32(0.0)
    gtp = np.float32(0.0)
    for t in range(nthreads):
        gch = max(gch, res[s, t, 0])
        gtp = max(gtp, res[s, t, 1])
    return (np.float64(gch) / np.float64(gtp) if gtp > 0 else 0.0) <= tol
