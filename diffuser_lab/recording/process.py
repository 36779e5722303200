"""Recording in a process of its own: what the ``diffuser-lab`` command uses.

On a thread, recording shares the interpreter's lock with the run: importing the Rerun SDK
(~0.4 s of Python) and the per-iteration Python work then stall the run's own Python between
its numpy calls (a background import made the demo's loading 0.5 s slower, twice the import's
own time). A forked child has its own interpreter: it imports, encodes, compresses and writes on
the second core while the run loads, and only the diffusion, which keeps both cores busy,
shares the CPU with it.

The child runs :class:`~diffuser_lab.recording.RecordingHooks` in-line, fed by the hook calls
this side sends it through a pipe, in order, from a sender thread (a recorded Z is copied
first: the solver reuses its buffer; at most :data:`Z_IN_FLIGHT_MB` wait). The child ignores
SIGINT and, if the run dies, finishes the files with what it received (EOF on the pipe), so an
interrupted or killed run leaves complete, readable records of the iterations sent. A child
that dies costs a warning and ``files()["errors"]``, never the run.

An online run's frames go as :class:`~.online.FrameRecord` s built on this side (plain arrays:
the update's views and its Z callable do not cross a pipe; Z is computed here, on the kept
frames only, and pickled: a few states per run).

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
from types import SimpleNamespace
from typing import Any, Optional, Sequence

import numpy as np

from diffuser_lab.hooks import RunHooks

from .schedule import recorded
from .serial import SerialThread

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


def available() -> bool:
    return "fork" in mp.get_all_start_methods()


def _value(x: Any) -> Any:
    return getattr(x, "value", x)


def _child(conn, conf, run_dir: Path, rerun: bool, mcap: bool, overrides: Sequence[str], shm, done,
           run_end=None) -> None:
    """The recording process: hook calls from ``conn`` into in-line RecordingHooks; recorded Z
    states arrive in ``shm`` slots, each handed back (``done.release()``) once recorded.
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
    from diffuser_lab import recording

    recording.ASYNC = False
    hooks = recording.RecordingHooks(conf, run_dir, rerun=rerun, mcap=mcap, overrides=overrides)
    _warm_kernels(conf)
    try:
        while True:
            try:
                name, args = conn.recv()
            except (EOFError, OSError):  # the run died: finish the files with what came
                break
            if name == "close":
                break
            if name == "observe_shm":  # (iteration, byte offset, shape, stats): Z in the shared slot
                it, offset, shape, stats = args
                Z = np.frombuffer(shm, np.float32, int(np.prod(shape)), offset).reshape(shape)
                try:
                    hooks.observe(it, Z, stats)  # in-line: done with Z when it returns
                finally:
                    del Z
                    done.release()
                continue
            getattr(hooks, name)(*args)
    finally:
        hooks.close()
        try:
            conn.send(("report", hooks.files(), list(hooks.recorded)))
        except (OSError, ValueError):
            pass
        conn.close()


def _warm_kernels(conf: Any) -> None:
    """Load the recorders' compiled kernels now, while the run loads its scene (~0.3 s from
    numba's cache), rather than at the first recorded iteration, inside the diffusion."""
    from diffuser_lab.backends import numba as nb

    if not nb.available():
        return
    from .mcap_encode import z_state_bytes
    from .steps import StepTracker

    Z = np.ones((4, 3), np.float32)
    StepTracker(4, ["a", "b", "c"], np.zeros(4, np.int16)).step(1, Z, 0.0)
    for dtype in {str(_value(conf.record.z_precision)), "float32"}:
        z_state_bytes(1, Z, dtype, labels=np.zeros(4, np.int16))


def _slim_scene(scene: Any) -> SimpleNamespace:
    """What the recorders read of a Scene (no frames: they come one by one)."""
    return SimpleNamespace(name=scene.name, n_points=scene.n_points, points=scene.points, colors=scene.colors,
                           gt_labels=scene.gt_labels, taxonomy=scene.taxonomy,
                           frames=[None] * len(getattr(scene, "frames", ())))  # online: the schedule's length


def _slim_result(res: Any) -> SimpleNamespace:
    """What the recorders read of a RunResult (see recording._summary)."""
    d = res.diffusion
    diff = None if d is None else SimpleNamespace(iterations=d.iterations, converged=d.converged,
                                                  residual=d.residual, Z=d.Z)
    return SimpleNamespace(method=res.method, scene=_slim_scene(res.scene), work_points=np.empty((len(res.work_points), 0)),
                           frames=[None] * len(res.frames), metrics=res.metrics,
                           baseline={"bayesian": res.baseline.get("bayesian")}, predictions_2d=res.predictions_2d,
                           diffusion=diff, timings_s=dict(res.timings_s))


class ProcessHooks(RunHooks):
    """RecordingHooks in a forked child (see the module doc); the same interface."""

    def __init__(self, conf: Any, run_dir: Path, *, rerun: bool, mcap: bool, overrides: Sequence[str] = ()):
        self.interval = None if conf.record.interval is None else int(conf.record.interval)
        self.max_iter = int(conf.solver.max_iter)
        self._wanted = [w for w, on in (("rerun", rerun), ("mcap", mcap)) if on]
        self.recorded: list[int] = []
        self.errors: dict[str, str] = {}
        self._files: dict[str, str] = {}
        self._dead: Optional[str] = None
        self._closed = False
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
        from .online import is_online

        self.conf = conf
        self.online = is_online(conf)
        self._online = None  # online: the run's side of the per-frame records (.online.OnlineFrames)
        self._scene = None

    # -- plumbing --------------------------------------------------------------------------------
    def _send_now(self, name: str, args: tuple) -> None:
        if self._dead is not None:
            return
        try:
            self._conn.send((name, args))
        except (OSError, ValueError) as exc:  # BrokenPipe: the child is gone
            self._dead = f"the recording process ended early ({type(exc).__name__}: {exc})"
            log.warning("recording switched off: %s", self._dead)

    def _send(self, name: str, *args) -> None:
        self._sender.submit(self._send_now, name, args)

    # -- RunHooks ----------------------------------------------------------------------------------
    def on_scene(self, scene: Any) -> None:
        self._scene = scene
        if self.online:
            self._online_schedule()
        self._send("on_scene", _slim_scene(scene))

    def _online_schedule(self) -> None:
        from .online import OnlineFrames

        self._online = OnlineFrames(self.conf, len(self._scene.frames))

    def on_frame(self, index: int, frame: Any) -> None:
        if self.online:  # the frame comes again with its update (on_online_frame)
            return
        self._send("on_frame", index, frame)

    def on_online_frame(self, frame: Any, update: Any) -> None:
        if self._dead is not None:
            return
        if self._online is None:  # online() called with a config whose protocol is not online
            self.online = True
            self._online_schedule()
        rec = self._online.record(frame, update, want_z="mcap" in self._wanted)
        if rec is not None:
            self._send("online_record", rec)

    def on_evidence(self, points: np.ndarray, grid: Optional[Any], evidence: Any, bayesian: np.ndarray) -> None:
        self._send("on_evidence", points, True if grid is not None else None, SimpleNamespace(seen=evidence.seen),
                   bayesian)

    def wants(self, iteration: int) -> bool:
        return self._dead is None and bool(self._wanted) and recorded(iteration, self.interval, self.max_iter)

    def observe(self, iteration: int, Z: np.ndarray, stats: dict) -> None:
        if self._n_slots == 0:
            self._n_slots = min(8, len(self._shm) // max(Z.nbytes, 1))
            if self._n_slots < 3 or Z.dtype != np.float32:
                self._n_slots = -1
        if self._n_slots > 0:
            self._observe_shared(iteration, Z, stats)
            return
        if self._z_slots is None:
            self._z_slots = threading.Semaphore(max(3, int(Z_IN_FLIGHT_MB * 2**20 // max(Z.nbytes, 1))))
        self._z_slots.acquire()  # a recorder far behind makes the run wait instead of filling the memory
        z = np.array(Z)  # the solver's buffer, valid during this call only

        def send():
            try:
                self._send_now("observe", (iteration, z, {"residual": float(stats.get("residual", float("nan")))}))
            finally:
                self._z_slots.release()

        self._sender.submit(send)

    def _observe_shared(self, iteration: int, Z: np.ndarray, stats: dict) -> None:
        """Z into the next shared slot (waiting while the child is all slots behind), then the
        message saying where it is, after everything queued before it."""
        while self._written - self._accounted >= self._n_slots:
            if self._done.acquire(timeout=1.0):
                self._accounted += 1
            elif not self._proc.is_alive():
                self._dead = f"the recording process ended early (exit code {self._proc.exitcode})"
                log.warning("recording switched off: %s", self._dead)
                return
        offset = (self._written % self._n_slots) * Z.nbytes
        np.frombuffer(self._shm, np.float32, Z.size, offset).reshape(Z.shape)[...] = Z
        self._written += 1
        self._send("observe_shm", iteration, offset, Z.shape,
                   {"residual": float(stats.get("residual", float("nan")))})

    def on_result(self, result: Any) -> None:
        if self.online or not hasattr(result, "diffusion"):
            if self._dead is None and self._online is not None:
                self._online.finish(result, lambda *fin: self._send("online_final", *fin),
                                    lambda summary: self._send("online_result", summary))
            return
        self._send("on_result", _slim_result(result))

    def close(self) -> None:
        from diffuser_lab import progress

        if self._closed:
            return
        self._closed = True
        with progress.stage(f"finishing records ({', '.join(self._wanted) or 'none'})"):
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
            if self._online is not None:  # this side stopped sending (an online frame failed)
                self.errors = {**self._online.errors(self._wanted), **self.errors}
        else:
            why = self._dead or f"the recording process ended without a report (exit code {self._proc.exitcode})"
            self.errors = {w: why for w in self._wanted}
            log.warning("recording: %s", why)

    def files(self) -> dict:
        out = dict(self._files)
        if self.errors:
            out["errors"] = dict(self.errors)
        return out


__all__ = ["ProcessHooks", "available"]
