"""Records of a run: run.rrd (Rerun) and run.mcap (MCAP), written as the run goes.

The recorders are observers (:class:`~diffuser_lab.hooks.RunHooks`): they read the arrays the
run hands them and never change the result. The folder, by role:

- :mod:`.hooks`: the run's side, common part (:class:`~.hooks.RecordingHooks`); the hooks of a
  batch run (:mod:`.batch`: cameras, evidence, the recorded iterations, whose labels,
  confidence, changes and mIoU so far are computed once, :mod:`.steps`, and given to both
  recorders), of an online run (:mod:`.online`: one record per frame taken) and of a
  single-frame run (:mod:`.single_frame`: each target frame's diffusion, Table II as it grows);
- :mod:`.recorders`: the writing side (:class:`~.recorders.Recorders`: run.rrd and run.mcap,
  opened, guarded, closed), fed the run's side's messages; :mod:`.rerun_log` and
  :mod:`.mcap_write` write the two files (:mod:`.mcap_encode` the MCAP messages,
  :mod:`.mcap_read` reads them back);
- the lanes that carry the messages: :mod:`.thread` (a background thread of this process) and
  :mod:`.process` (a forked recording process: what the ``diffuser-lab`` command uses).

A recorder that fails (disk full, a bug) is switched off with a warning and the run goes on;
the failure is reported in ``files()["errors"]`` (and so in summary.json's ``records``); the
``diffuser-lab`` command then ends with one error line and exit status 1, after the labels.

Usage (the CLI does this when ``record != off``)::

    hooks = make_hooks(conf, run_dir, overrides=[])
    try:
        result = run(conf, hooks=hooks)
    finally:
        hooks.close()
    hooks.files()   # {"rrd": "run.rrd", "mcap": "run.mcap"}
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Optional, Sequence

from diffuser_lab.config import RecordMode
from diffuser_lab.hooks import RunHooks

from . import process as proc
from .batch import BatchHooks
from .hooks import RecordingHooks
from .online import OnlineHooks, is_online
from .recorders import MCAP_NAME, RRD_NAME
from .single_frame import SingleFrameHooks, is_single_frame
from .steps import Step, StepTracker
from .thread import ThreadLane
from .tiled import record_tiled

ASYNC = True
"""Record on a background thread (False: in the run's thread, as the hooks are called)."""


class _Off(RunHooks):
    """record=off: records nothing."""

    reads_rgb = False

    def files(self) -> dict:
        return {}


def make_hooks(conf: Any, run_dir: Path | str, overrides: Sequence[str] = (), *, process: bool = False) -> RunHooks:
    """The run's recorders as configured by ``conf.record.mode`` (off | rerun | mcap | both).
    The returned object has the :class:`RunHooks` methods and ``files() -> {"rrd": .., "mcap": ..}``
    (names relative to ``run_dir``). ``process``: record in a forked child process
    (:mod:`.process`; what the ``diffuser-lab`` command does where ``fork`` exists), else on a
    thread of this one. ``conf``: a validated :class:`~diffuser_lab.config.Config` (its choices
    are enums)."""
    mode = conf.record.mode
    if mode == RecordMode.off:
        return _Off()
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    kinds = dict(rerun=mode in (RecordMode.rerun, RecordMode.both), mcap=mode in (RecordMode.mcap, RecordMode.both),
                 overrides=list(overrides))
    if process and proc.available():
        lane = proc.ProcessLane(conf, run_dir, **kinds)
    else:
        lane = ThreadLane(conf, run_dir, background=ASYNC, **kinds)
    if is_single_frame(conf):
        return SingleFrameHooks(conf, lane)
    return (OnlineHooks if is_online(conf) else BatchHooks)(conf, lane)


def record_result(conf: Any, run_dir: Path | str, result: Any, overrides: Sequence[str] = (),
                  provenance: Optional[dict] = None) -> dict:
    """The records of a run whose protocol writes them from its result once it is done
    (``Protocol.result_records``: a tiled run, :func:`.tiled.record_tiled`), with what made it
    (``provenance``: as :meth:`~diffuser_lab.hooks.RunHooks.on_provenance` gets it); ``{}`` for
    record=off. Returns ``{"rrd": .., "mcap": ..}`` as :meth:`RecordingHooks.files` does."""
    if conf.record.mode == RecordMode.off:
        return {}
    Path(run_dir).mkdir(parents=True, exist_ok=True)
    return record_tiled(conf, run_dir, result, overrides, provenance)


__all__ = ["make_hooks", "record_result", "RecordingHooks", "BatchHooks", "OnlineHooks", "Step", "StepTracker", "RRD_NAME",
           "MCAP_NAME"]
