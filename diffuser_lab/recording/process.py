"""Recording in a process of its own: the lane (see :mod:`.hooks`) the ``diffuser-lab`` command uses.

On a thread, recording shares the interpreter's lock with the run: importing the Rerun SDK
(~0.4 s of Python) and the per-iteration Python work then stall the run's own Python between
its numpy calls (a background import made the demo's loading 0.5 s slower, twice the import's
own time). A forked child has its own interpreter: it imports, encodes, compresses and writes on
the second core while the run loads, and only the diffusion, which keeps both cores busy,
shares the CPU with it.

The child runs :class:`~.recorders.Recorders` in-line, fed the messages of the run's hooks
(:class:`~.batch.BatchHooks`, :class:`~.online.OnlineHooks`) through a pipe, in order, from a
sender thread; whatever the message, it is one :meth:`~.recorders.Recorders.call`, so nothing
here restates a hook. A recorded Z goes through a shared mapping instead (the solver reuses its
buffer; at most :data:`Z_IN_FLIGHT_MB` wait). The child ignores SIGINT and, if the run dies,
finishes the files with what it received (EOF on the pipe), so an interrupted or killed run
leaves complete, readable records of the iterations sent. A child that dies costs a warning and
``files()["errors"]``, never the run.

An online run's frames go as :class:`~.online.FrameRecord` s built on the run's side (plain
arrays: the update's views and its Z callable do not cross a pipe; Z is computed there, on the
kept frames only, and pickled: a few states per run).

Without ``fork`` (not Linux) :func:`~diffuser_lab.recording.make_hooks` keeps the thread.
"""
from __future__ import annotations

import logging
import mmap
import multiprocessing as mp
import os
import signal
import threading
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from .hooks import finishing
from .mcap_encode import z_state_bytes
from .recorders import Recorders
from .serial import SerialThread
from .steps import StepTracker

log = logging.getLogger("diffuser_lab.recording")

Z_IN_FLIGHT_MB = 384
"""Recorded Z copies that may wait for the recording process at once, in MB (at least 3
states): the run only waits when the child is this far behind (the first states come within
milliseconds, while the child may still be logging the cameras). They lie in an anonymous
shared mapping made before the fork (pages are only used once written): one copy of Z instead
of five through a pipe (copy, pickle, pipe, read, unpickle), which on a 566k-point scene cost
the diffusion more than the recording itself."""
QUEUE_SIZE = 64
NICE = 19
"""The recording process runs under SCHED_IDLE (a core the run leaves idle), else this niceness:
a parallel kernel whose thread loses its core for a time slice stalls at its barrier, so a
recorder that merely shares the cores costs the diffusion more than its own CPU time."""
CLOSE_TIMEOUT_S = 600.0
SHARED_Z = "@z"
"""The message of a recorded Z in a shared slot: (message name, iteration, byte offset, shape, args)."""


def available() -> bool:
    return "fork" in mp.get_all_start_methods()


def _child(conn, conf, run_dir: Path, rerun: bool, mcap: bool, overrides: Sequence[str], shm, done,
           run_end=None) -> None:
    """The recording process: messages from ``conn`` into in-line Recorders; recorded Z states
    arrive in ``shm`` slots, each handed back (``done.release()``) once recorded.
    ``run_end``: the run's end of the pipe, inherited by the fork: closed here, else the run's
    death would never read as EOF (this process would hold the pipe open itself)."""
    if run_end is not None:
        run_end.close()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the run's: it closes us in order
    try:  # below the run: its parallel kernels keep both cores busy; the records can wait for a free one
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        try:
            os.nice(NICE)
        except OSError:
            pass
    side = Recorders(conf, run_dir, rerun=rerun, mcap=mcap, writer_thread=True)
    side.open(overrides)
    _warm_kernels(conf, rerun)
    try:
        while True:
            try:
                name, args = conn.recv()
            except (EOFError, OSError):  # the run died: finish the files with what came
                break
            if name == "close":
                break
            if name == SHARED_Z:  # Z in the shared slot
                name, it, offset, shape, rest = args
                Z = np.frombuffer(shm, np.float32, int(np.prod(shape)), offset).reshape(shape)
                try:
                    side.call(name, (it, Z, *rest))  # in-line: done with Z when it returns
                finally:
                    del Z
                    done.release()
                continue
            side.call(name, args)
    finally:
        with finishing(side.wanted):
            side.close()
        try:
            conn.send(("report", side.files(), list(side.recorded)))
        except (OSError, ValueError):
            pass
        conn.close()


def _warm_kernels(conf: Any, rerun: bool = False) -> None:
    """Load the recorders' compiled kernels now, while the run loads its scene (~0.3 s from
    numba's cache), rather than at the first recorded iteration, inside the diffusion (without
    them: a few microseconds of numpy); and matplotlib's canvas, which the legend's picture needs
    with the evidence, when the run's graph keeps both cores busy (its import: ~0.5 s of CPU)."""
    if rerun:
        from matplotlib.backends import backend_agg  # noqa: F401
        from matplotlib import figure  # noqa: F401
    Z = np.ones((4, 3), np.float32)
    StepTracker(4, ["a", "b", "c"], np.zeros(4, np.int16)).step(1, Z, 0.0)
    for dtype in {conf.record.z_precision.value, "float32"}:
        z_state_bytes(1, Z, dtype, labels=np.zeros(4, np.int16))


class ProcessLane:
    """:class:`~.recorders.Recorders` in a forked child (see the module doc)."""

    def __init__(self, conf: Any, run_dir: Path, *, rerun: bool, mcap: bool, overrides: Sequence[str] = ()):
        self.wanted = [w for w, on in (("rerun", rerun), ("mcap", mcap)) if on]
        self.recorded: list[int] = []
        self.errors: dict[str, str] = {}
        self._files: dict[str, str] = {}
        self.dead: Optional[str] = None
        self._z_slots: Optional[threading.Semaphore] = None  # the pickled path (a Z too large for the slots)
        ctx = mp.get_context("fork")
        self._conn, child_conn = ctx.Pipe()
        self._shm = mmap.mmap(-1, Z_IN_FLIGHT_MB * 2**20)  # MAP_SHARED | MAP_ANONYMOUS: the child sees it
        self._done = ctx.Semaphore(0)  # one release per shared slot the child has recorded
        self._n_slots = 0  # set at the first recorded Z
        self._written = self._accounted = 0
        self._proc = ctx.Process(target=_child, args=(child_conn, conf, Path(run_dir), rerun, mcap, list(overrides),
                                                      self._shm, self._done, self._conn),
                                 name="diffuser-lab-record", daemon=True)
        self._proc.start()
        child_conn.close()
        self._sender = SerialThread("diffuser-lab-record-send", QUEUE_SIZE, stop_on_error=False)

    def _send_now(self, name: str, args: tuple) -> None:
        if self.dead is not None:
            return
        try:
            self._conn.send((name, args))
        except (OSError, ValueError) as exc:  # BrokenPipe: the child is gone
            self.dead = f"the recording process ended early ({type(exc).__name__}: {exc})"
            log.warning("recording switched off: %s", self.dead)

    def send(self, name: str, *args) -> None:
        self._sender.submit(self._send_now, name, args)

    def send_z(self, name: str, iteration: int, Z: np.ndarray, *args) -> None:
        if self._n_slots == 0:
            self._n_slots = min(8, len(self._shm) // max(Z.nbytes, 1))
            if self._n_slots < 3 or Z.dtype != np.float32:
                self._n_slots = -1
        if self._n_slots > 0:
            self._send_shared(name, iteration, Z, args)
            return
        if self._z_slots is None:
            self._z_slots = threading.Semaphore(max(3, int(Z_IN_FLIGHT_MB * 2**20 // max(Z.nbytes, 1))))
        self._z_slots.acquire()  # a recorder far behind makes the run wait instead of filling the memory
        z = np.array(Z)  # the solver's buffer, valid during this call only

        def send():
            try:
                self._send_now(name, (iteration, z, *args))
            finally:
                self._z_slots.release()

        self._sender.submit(send)

    def _send_shared(self, name: str, iteration: int, Z: np.ndarray, args: tuple) -> None:
        """Z into the next shared slot (waiting while the child is all slots behind), then the
        message saying where it is, after everything queued before it."""
        while self._written - self._accounted >= self._n_slots:
            if self._done.acquire(timeout=1.0):
                self._accounted += 1
            elif not self._proc.is_alive():
                self.dead = f"the recording process ended early (exit code {self._proc.exitcode})"
                log.warning("recording switched off: %s", self.dead)
                return
        offset = (self._written % self._n_slots) * Z.nbytes
        np.frombuffer(self._shm, np.float32, Z.size, offset).reshape(Z.shape)[...] = Z
        self._written += 1
        self.send(SHARED_Z, name, iteration, offset, Z.shape, args)

    def live(self, which: str) -> bool:
        return which in self.wanted and self.dead is None

    def close(self) -> Optional[str]:
        """Wait for the child's report; why there is none, else None."""
        self._sender.submit(self._send_now, "close", ())
        self._sender.close()
        report = None
        try:
            if self._conn.poll(CLOSE_TIMEOUT_S):
                report = self._conn.recv()
        except (EOFError, OSError):
            pass
        self._proc.join(timeout=30)
        if self._proc.is_alive():
            self._proc.kill()
        self._conn.close()
        self._shm.close()
        if report is not None and report[0] == "report":
            files, self.recorded = report[1], report[2]
            self.errors = dict(files.pop("errors", {}))
            self._files = files
            return None
        why = self.dead or f"the recording process ended without a report (exit code {self._proc.exitcode})"
        self.errors = {w: why for w in self.wanted}
        return why

    def files(self) -> dict:
        out = dict(self._files)
        if self.errors:
            out["errors"] = dict(self.errors)
        return out


__all__ = ["ProcessLane", "available"]
