"""The records written in this process: the lane (see :mod:`.hooks`) of library calls, and of the
``diffuser-lab`` command where ``fork`` is missing.

All recording work runs on one background thread, in the order the hooks were called: the
run's thread only queues it (a recorded Z is copied into one of :data:`Z_BUFFERS` reused buffers
first, ~0.2 ms on the demo), so the diffusion goes on while an iteration is being written, and
static logging (cameras, images) overlaps the frames' predictions. The queue is bounded: a
recorder that falls behind slows the run down instead of filling the memory. Without the
thread (``background=False``) each message is written in-line, as the hooks are called.
"""
from __future__ import annotations

import queue
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np

from .recorders import Recorders
from .serial import SerialThread

Z_BUFFERS = 3
"""Recorded Z states that may wait for the recording thread at once (each M x C float32)."""
QUEUE_SIZE = 64
"""Calls that may wait for the recording thread (frames keep their images alive until logged)."""


class ThreadLane:
    """:class:`~.recorders.Recorders` in this process, on a background thread (``background``)
    or in-line."""

    def __init__(self, conf: Any, run_dir: Path, *, rerun: bool, mcap: bool, overrides: Sequence[str] = (),
                 background: bool = True):
        self._worker = SerialThread("diffuser-lab-record", QUEUE_SIZE, stop_on_error=False) if background else None
        # on the recording thread already: the MCAP recorder compresses and writes in it too
        self.side = Recorders(conf, run_dir, rerun=rerun, mcap=mcap, writer_thread=self._worker is None)
        self.wanted = self.side.wanted
        self.dead: Optional[str] = None
        self._z_free: queue.SimpleQueue = queue.SimpleQueue()  # recorded-Z buffers back from the worker
        self._z_made = 0
        self._later(self.side.open, overrides)  # opened on the recording thread

    def _later(self, fn: Callable, *args) -> None:
        """Run ``fn(*args)`` on the recording thread (now, without one), after what is queued."""
        if self._worker is None:
            fn(*args)
        else:
            self._worker.submit(fn, *args)

    def send(self, name: str, *args) -> None:
        self._later(self.side.call, name, args)

    def send_z(self, name: str, iteration: int, Z: np.ndarray, *args) -> None:
        if self._worker is None:
            self.side.call(name, (iteration, Z, *args))
            return
        buf = self._z_buffer(Z)  # Z is the solver's, valid during this call only

        def call():
            try:
                self.side.call(name, (iteration, buf, *args))
            finally:
                self._z_free.put(buf)

        self._worker.submit(call)

    def _z_buffer(self, Z: np.ndarray) -> np.ndarray:
        """A copy of Z in a reused buffer (waits for one when Z_BUFFERS are queued already)."""
        try:
            buf = self._z_free.get_nowait()
        except queue.Empty:
            if self._z_made < Z_BUFFERS:
                self._z_made += 1
                buf = np.empty_like(Z)
            else:
                buf = self._z_free.get()
        if buf.shape != Z.shape or buf.dtype != Z.dtype:
            buf = np.empty_like(Z)
        np.copyto(buf, Z)
        return buf

    def live(self, which: str) -> bool:
        return which in self.wanted and which not in self.side.errors

    @property
    def recorded(self) -> list[int]:
        return self.side.recorded

    def close(self) -> Optional[str]:
        if self._worker is not None:
            self._worker.close()  # what is queued is written first
        self.side.close()
        return None  # the side is this process's: its report is files()

    def files(self) -> dict:
        return self.side.files()


__all__ = ["ThreadLane", "Z_BUFFERS", "QUEUE_SIZE"]
