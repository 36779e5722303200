"""The writing side of a run's records: run.rrd (Rerun) and run.mcap (MCAP), as asked, with the
batch recorder (:class:`~.batch.BatchRecorder`) and the online recorder
(:class:`~.online.OnlineRecorder`) that write through them.

One :class:`Recorders` lives where the records are written: on the recording thread
(:class:`~.thread.ThreadLane`) or in the recording process (:mod:`.process`), where it runs
in-line. The run's side (:class:`~.hooks.RecordingHooks`) reaches it only through messages,
``(name, args)`` of plain, picklable values, each one :meth:`Recorders.call`: ``open``,
``log_scene``, ``batch.<method>``, ``online.<method>``, ``single.<method>`` (a single-frame run:
:class:`~.single_frame.SingleFrameRecorder`). So neither lane restates a hook, and a
recorder is written once for both.

A recorder that fails (disk full, a bug) is switched off with a warning and the run goes on;
the failure is reported in ``files()["errors"]`` (and so in summary.json's ``records``).
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

from diffuser_lab.backends import provenance
from diffuser_lab.runs.records import config_sha256, config_yaml

from .batch import BatchRecorder
from .mcap_write import McapRecorder
from .online import OnlineRecorder, is_online
from .rerun_log import RerunRecorder
from .single_frame import SingleFrameRecorder, SingleFrameRerun, is_single_frame

log = logging.getLogger("diffuser_lab.recording")

RRD_NAME = "run.rrd"
MCAP_NAME = "run.mcap"


class Recorders:
    """run.rrd and/or run.mcap of one run (see the module doc), opened by :meth:`open`.

    Attributes:
        wanted: the recorders asked for, of ("rerun", "mcap").
        rerun, mcap: the open recorders (None: not asked for, not open yet, or failed).
        errors: {"rerun" | "mcap": why it was switched off}.
        scene: the run's scene as the recorders read it (:func:`~.hooks.slim_scene`).
        recorded: iterations (an online run: frame indices) whose Z was recorded, in order.
        batch, online: the recorders of a batch run and of an online run.
    """

    def __init__(self, conf: Any, run_dir: Path, *, rerun: bool, mcap: bool, writer_thread: bool):
        self.conf = conf
        self.run_dir = Path(run_dir)
        self.wanted = [w for w, on in (("rerun", rerun), ("mcap", mcap)) if on]
        self.writer_thread = writer_thread  # run.mcap compresses and writes on a thread of its own
        self.errors: dict[str, str] = {}
        self._files: dict[str, str] = {}
        self.rerun: Optional[RerunRecorder] = None
        self.mcap: Optional[McapRecorder] = None
        self.scene: Any = None
        self.recorded: list[int] = []
        self.batch = BatchRecorder(self)
        self.online = OnlineRecorder(self)
        self.single = SingleFrameRecorder(self)

    def call(self, name: str, args: tuple) -> None:
        """One message of the run's side: ``name`` a method of this object (``log_scene``) or of
        its batch / online recorder (``batch.step``, ``online.frame``)."""
        owner, _, method = name.rpartition(".")
        getattr(getattr(self, owner) if owner else self, method)(*args)

    # -- the files ---------------------------------------------------------------------------------
    def open(self, overrides: Sequence[str] = ()) -> None:
        if "rerun" in self.wanted:
            self.guard("rerun", self._open_rerun)
        if "mcap" in self.wanted:
            self.guard("mcap", self._open_mcap, overrides)
        try:  # where and with what it runs, from the start: a killed run's records still say it
            block = {"provenance": provenance.collect(), "inputs": {"config_sha256": config_sha256(self.conf)}}
        except Exception:  # noqa: BLE001 - a library caller's plain config object
            block = {"provenance": provenance.collect()}
        self.log_provenance(block)

    def log_provenance(self, block: dict) -> None:
        """What made the run (:meth:`~diffuser_lab.hooks.RunHooks.on_provenance`): run.rrd's recording
        property and run.mcap's metadata ``diffuser_lab.provenance``, each a later one replacing the first."""
        self.each(lambda: self.rerun.log_provenance(block), lambda: self.mcap.log_provenance(block))

    def _open_rerun(self) -> None:
        rc = self.conf.record
        kw = dict(max_image_side=rc.max_image_side, max_depth_side=int(rc.max_depth_side), live=rc.live)
        if is_single_frame(self.conf):
            self.rerun = SingleFrameRerun(self.run_dir / RRD_NAME, **kw)
        else:
            self.rerun = RerunRecorder(self.run_dir / RRD_NAME, online=is_online(self.conf),
                                       confidence=bool(getattr(self.conf.output, "scores", False)), **kw)
        self._files["rrd"] = RRD_NAME

    def _open_mcap(self, overrides: Sequence[str]) -> None:
        rc = self.conf.record
        try:
            yaml = config_yaml(self.conf)
        except Exception:  # noqa: BLE001 - a library caller may pass a plain object
            yaml = repr(self.conf)
        self.mcap = McapRecorder(self.run_dir / MCAP_NAME, z_dtype=rc.z_precision.value, config_yaml=yaml,
                                 overrides=overrides, interval=None if rc.interval is None else int(rc.interval),
                                 max_iter=int(self.conf.solver.max_iter), compression=rc.compression.value,
                                 clouds=rc.clouds.value, writer_thread=self.writer_thread,
                                 max_image_side=rc.max_image_side)
        self._files["mcap"] = MCAP_NAME

    def guard(self, which: str, fn: Callable, *args) -> None:
        """Run ``fn``; on failure switch the recorder ``which`` off, warn, remember the error."""
        if which in self.errors:
            return
        try:
            fn(*args)
        except Exception as exc:  # noqa: BLE001 - a record must never stop the run
            self.errors[which] = f"{type(exc).__name__}: {exc}"
            log.warning("recording %s failed, switched off: %s", which, self.errors[which])
            rec = getattr(self, which, None)
            setattr(self, which, None)
            if rec is not None:
                try:
                    rec.close()
                except Exception:  # noqa: BLE001
                    pass

    def each(self, rerun_fn: Optional[Callable], mcap_fn: Optional[Callable]) -> None:
        """The Rerun and the MCAP part of one message, each guarded, each only while its recorder is on."""
        if self.rerun is not None and rerun_fn is not None:
            self.guard("rerun", rerun_fn)
        if self.mcap is not None and mcap_fn is not None:
            self.guard("mcap", mcap_fn)

    def log_scene(self, scene: Any) -> None:
        self.scene = scene
        tax = scene.taxonomy

        def rr_scene():
            self.rerun.log_taxonomy(tax.names, tax.colors)
            self.rerun.log_scene(scene.points, scene.colors, scene.gt_labels)

        self.each(rr_scene, lambda: self.mcap.log_scene(scene))

    def close(self) -> None:
        for which in ("rerun", "mcap"):
            rec = getattr(self, which)
            if rec is not None:
                self.guard(which, rec.close)

    def files(self) -> dict:
        """{"rrd": "run.rrd", "mcap": "run.mcap"} of the recorders that did not fail, and
        ``errors`` {recorder: why} when one did."""
        out = {k: v for k, v in self._files.items() if (k == "rrd" and "rerun" not in self.errors)
               or (k == "mcap" and "mcap" not in self.errors)}
        if self.errors:
            out["errors"] = dict(self.errors)
        return out


__all__ = ["Recorders", "RRD_NAME", "MCAP_NAME"]
