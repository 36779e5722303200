"""A reader's bounds in the fuzz tests (tests/data/test_fuzz_formats.py, test_fuzz_readers.py): a case
that runs over its time is a failure (an alarm, not a deadline checked after the call returns), and
one that asks for more than its share of address space gets a MemoryError."""
from __future__ import annotations

import contextlib
import resource
import signal
from pathlib import Path

LIMIT_S = 5.0  # per case
SPARE_BYTES = 2 << 30  # address space a case may add


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
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    resource.setrlimit(resource.RLIMIT_AS, (vm + spare if hard == resource.RLIM_INFINITY else min(hard, vm + spare), hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
