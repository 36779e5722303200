"""A reader's bounds in the fuzz tests (tests/data/test_fuzz_formats.py, test_fuzz_readers.py): a case
that runs over its time is a failure (an alarm, not a deadline checked after the call returns; a hang
inside C code, which no Python handler interrupts, ends the process with its stack 2 s later:
tests/hangs.py's watchdog), and one that asks for more than its share of address space gets a
MemoryError. The test's own timer (pytest-timeout's SIGALRM) is set again after the case."""
from __future__ import annotations

import contextlib
import resource
import signal
import time
from pathlib import Path

from hangs import watchdog

LIMIT_S = 5.0  # per case
SPARE_BYTES = 2 << 30  # address space a case may add
HARD_S = 2.0  # after the alarm, the watchdog's time to end a case stuck in C code


class Hung(BaseException):
    """A reader ran over its time: a BaseException, so that no reader's ``except Exception`` turns it into a line."""


@contextlib.contextmanager
def bounded(seconds: float = LIMIT_S, spare: int = SPARE_BYTES):
    """Raise :class:`Hung` after ``seconds``; MemoryError beyond ``spare`` more bytes of address space."""
    def _alarm(*_):
        raise Hung(f"a reader ran over {seconds} s")

    vm = next(int(line.split()[1]) * 1024 for line in Path("/proc/self/status").read_text().splitlines()
              if line.startswith("VmSize:"))
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    with watchdog(seconds + HARD_S):  # its thread started before the address space is capped
        old = signal.signal(signal.SIGALRM, _alarm)
        outer, start = signal.getitimer(signal.ITIMER_REAL)[0], time.monotonic()  # pytest-timeout's, if set
        signal.setitimer(signal.ITIMER_REAL, seconds)
        resource.setrlimit(resource.RLIMIT_AS, (vm + spare if hard == resource.RLIM_INFINITY else min(hard, vm + spare),
                                                hard))
        try:
            yield
        finally:
            resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)
            if outer:  # the outer timer, less the time spent here (due already: at once)
                signal.setitimer(signal.ITIMER_REAL, max(outer - (time.monotonic() - start), 1e-3))
