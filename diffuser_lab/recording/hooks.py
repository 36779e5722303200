"""The run's side of the records: hooks (:class:`~diffuser_lab.hooks.RunHooks`) that turn each
call of the run into messages for the writing side (:class:`~.recorders.Recorders`), sent
through a lane.

:class:`RecordingHooks` is the common part; :class:`~.batch.BatchHooks` (a batch run: frames,
evidence, recorded iterations, result) and :class:`~.online.OnlineHooks` (protocol=online: one
record per frame) are the two kinds of run. A lane carries the messages to where the records
are written, in the order they were sent:

- :class:`~.thread.ThreadLane`: a background thread of this process (or in-line);
- :class:`~.process.ProcessLane`: a forked recording process, through a pipe.

A lane has ``wanted`` (the recorders asked for), ``send(name, *args)``,
``send_z(name, iteration, Z, *args)`` (Z valid during the call only: the lane copies it),
``live(which)`` (the recorder was asked for and, as far as this side knows, still writes),
``dead`` (why the writing side is gone, else None), ``recorded``, ``close()`` (returns why no
report came, else None) and ``files()``.
"""
from __future__ import annotations

import logging
from types import SimpleNamespace
from typing import Any, Sequence

from diffuser_lab import progress
from diffuser_lab.hooks import RunHooks

log = logging.getLogger("diffuser_lab.recording")


def finishing(wanted: Sequence[str]):
    """The progress stage of closing the records (:func:`diffuser_lab.progress.stage`)."""
    return progress.stage(f"finishing records ({', '.join(wanted) or 'none'})")


def slim_scene(scene: Any) -> SimpleNamespace:
    """What the recorders read of a Scene (no frames: they come one by one)."""
    return SimpleNamespace(name=scene.name, n_points=scene.n_points, points=scene.points, colors=scene.colors,
                           gt_labels=scene.gt_labels, taxonomy=scene.taxonomy,
                           frames=[None] * len(getattr(scene, "frames", ())))  # online: the schedule's length


class RecordingHooks(RunHooks):
    """The part both kinds of run share: the scene, closing, the files (see the module doc)."""

    def __init__(self, conf: Any, lane: Any):
        self.conf = conf
        self.lane = lane
        self.scene: Any = None
        self._closed = False

    def on_scene(self, scene: Any) -> None:
        self.scene = scene
        self.lane.send("log_scene", slim_scene(scene))

    def on_provenance(self, block: dict) -> None:
        self.lane.send("log_provenance", block)

    def recording(self) -> bool:
        """Whether any recorder asked for still writes."""
        return any(self.lane.live(w) for w in self.lane.wanted)

    @property
    def recorded(self) -> list[int]:
        """Iterations (an online run: frame indices) whose Z was recorded, in order (the
        recording process reports them when it closes)."""
        return self.lane.recorded

    def close(self) -> None:
        """Write what is queued and close the files (once)."""
        if self._closed:
            return
        self._closed = True
        with finishing(self.lane.wanted):
            why = self.lane.close()
        if why is not None:
            log.warning("recording: %s", why)

    def files(self) -> dict:
        """``{"rrd": "run.rrd", "mcap": "run.mcap"}`` (names relative to the run folder) of the
        records written, and ``errors`` {recorder: why} where one failed."""
        return self.lane.files()


__all__ = ["RecordingHooks", "slim_scene", "finishing"]
