"""glibc heap settings for recording: keep freed memory for reuse instead of returning it.

Each recorded iteration allocates and frees ~12 MB of short-lived buffers (mcap's chunk
buffers, zstd's output). With glibc's defaults the freed top of the heap is handed back to the
kernel after every iteration (trim threshold ~8 MB once large blocks have been freed) and the
next iteration faults every page in again: ~3,000 page faults per recorded iteration, 0.1-0.2 s
of system time per demo run on the VMs we measure on (strace shows the heap break moving
12 MB up and down per iteration). Raising the trim threshold keeps those pages; fixing the mmap
threshold at glibc's own dynamic maximum (32 MiB) keeps blocks of up to that size on the heap,
where they can be reused (setting either option switches glibc's dynamic threshold off).

Process-wide and permanent for the process (glibc has no way to read the settings back); a
no-op where the C library is not glibc.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import logging
import platform

log = logging.getLogger("diffuser_lab.recording")

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 32 << 20
"""Blocks above this still get their own mapping (returned to the kernel when freed)."""

_trim_applied = 0  # bytes; 0: glibc's defaults are in force


def retain_freed_memory(trim_mb: int) -> bool:
    """Let glibc keep up to ``trim_mb`` MiB of freed memory at the top of each heap (0: leave the
    defaults). Returns whether the setting is in force. Applied once per process; a later call
    with a larger value raises it."""
    global _trim_applied
    if trim_mb <= 0 or platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return _trim_applied > 0
    trim = int(trim_mb) << 20
    if _trim_applied >= trim:
        return True
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        ok = libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1 and libc.mallopt(M_TRIM_THRESHOLD, trim) == 1
    except (OSError, AttributeError) as exc:  # no usable libc: nothing to tune
        log.debug("mallopt unavailable: %s", exc)
        return False
    if ok:
        _trim_applied = trim
    return ok


__all__ = ["retain_freed_memory"]
