"""Other libraries' thread pools beside the compiled kernels' threads."""
from __future__ import annotations

import contextlib


@contextlib.contextmanager
def blas_one_thread():
    """BLAS on the calling thread only while this is open (threadpoolctl).

    After every multi-threaded BLAS call OpenBLAS's worker threads busy-wait ~0.1 s for the next
    one (its thread timeout, 2^28 cycles): an online run's frame pipeline (back-projection,
    rendering, the network) calls BLAS between updates, so those spinning workers took the core
    the Jacobi threads were about to use and the update ran at one core's speed (measured on
    scene0470, given map: the steps 16-20 ms a frame with the spinning pool, 9-10 ms without it;
    docs/online.md). The frame pipeline's BLAS calls are small products (N x 3 by 3 x 3)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # an environment without it: BLAS as it is
        yield
        return
    with threadpool_limits(limits=1, user_api="blas"):
        yield
