"""Other libraries' thread pools beside the compiled kernels' threads."""
from __future__ import annotations

import contextlib
import sys


@contextlib.contextmanager
def blas_one_thread():
    """BLAS on the calling thread only while this is open (threadpoolctl).

    After every multi-threaded BLAS call OpenBLAS's worker threads busy-wait ~0.1 s for the next
    one (its thread timeout, 2^28 cycles): an online run's frame pipeline (back-projection,
    rendering, the network) calls BLAS between updates, so those spinning workers took the core
    the Jacobi threads were about to use and the update ran at one core's speed (measured on
    scene0470, given map: the steps 16-20 ms a frame with the spinning pool, 9-10 ms without it;
    docs/online.md). The frame pipeline's BLAS calls are small products (N x 3 by 3 x 3)."""
    controller = _controller()
    if controller is None:  # an environment without threadpoolctl: BLAS as it is
        yield
        return
    with controller.limit(limits=1, user_api="blas"):
        yield


_CACHED: list = [None, -1]


def _controller():
    """threadpoolctl's controller of the loaded libraries, made again only when modules were imported
    since (a new extension may have loaded a BLAS): finding the libraries costs ~3 ms, a limit with
    a kept controller ~20 us (the callers enter this once per frame or per chunk of rows)."""
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:
        return None
    if _CACHED[0] is None or _CACHED[1] != len(sys.modules):
        _CACHED[0], _CACHED[1] = ThreadpoolController(), len(sys.modules)
    return _CACHED[0]
