"""Records of a run: run.rrd (Rerun) and run.mcap (MCAP), written as the diffusion goes.

Both recorders are observers (:class:`~diffuser_lab.hooks.RunHooks`): they read the arrays the
pipeline hands them and never change the result. Per recorded iteration (:mod:`.schedule`:
1, 2, 5, 10, 20, 50, ... or every ``record.interval``-th, plus the first and the last) the derived quantities (labels,
confidence, changes, mIoU so far) are computed once (:mod:`.steps`) and given to both.

All recording work runs on one background thread, in the order the hooks were called: the
pipeline's thread only queues it (a recorded Z is copied into one of :data:`Z_BUFFERS` reused
buffers first, ~0.2 ms on the demo), so the diffusion goes on while an iteration is being
written, and static logging (cameras, images) overlaps the frames' predictions. The queue is
bounded: a recorder that falls behind slows the run down instead of filling the memory.
:meth:`RecordingHooks.close` waits for the queued work.

A recorder that fails (disk full, a bug) is switched off with a warning and the run goes on;
the failure is reported in ``files()["errors"]`` (and so in summary.json's ``records``).

An online run (protocol=online) is recorded per frame instead (:mod:`.online`): each
``on_online_frame`` becomes a :class:`~.online.FrameRecord` in the run's thread (copies of the
labels, the new map points, Z only on the kept frames), written on the recording thread.

Usage (the CLI does this when ``record != off``)::

    hooks = make_hooks(conf, run_dir, overrides=[])
    try:
        result = run(conf, hooks=hooks)
    finally:
        hooks.close()
    hooks.files()   # {"rrd": "run.rrd", "mcap": "run.mcap"}
"""
from __future__ import annotations

import dataclasses
import logging
import queue
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from diffuser_lab.hooks import RunHooks

from .schedule import recorded
from .serial import SerialThread
from .steps import Step, StepTracker, original_to_work

log = logging.getLogger("diffuser_lab.recording")

RRD_NAME = "run.rrd"
MCAP_NAME = "run.mcap"


def _value(x: Any) -> Any:
    return getattr(x, "value", x)


ASYNC = True
"""Record on a background thread (False: in the pipeline's thread, as the hooks are called)."""
Z_BUFFERS = 3
"""Recorded Z states that may wait for the recording thread at once (each M x C float32)."""
QUEUE_SIZE = 64
"""Calls that may wait for the recording thread (frames keep their images alive until logged)."""


class RecordingHooks(RunHooks):
    """Feeds a run to a Rerun and/or an MCAP recorder (either may be None)."""

    def __init__(self, conf: Any, run_dir: Path, *, rerun: bool, mcap: bool, overrides: Sequence[str] = ()):
        self.conf = conf
        self.run_dir = Path(run_dir)
        self.interval = None if conf.record.interval is None else int(conf.record.interval)
        self.max_iter = int(conf.solver.max_iter)
        self.method = str(_value(conf.method.name))
        self.errors: dict[str, str] = {}
        self._files: dict[str, str] = {}
        self.recorded: list[int] = []  # iterations recorded, in order
        self._last_step = None
        self.rerun = self.mcap = None  # set on the recording thread, which opens them
        self._wanted = [w for w, on in (("rerun", rerun), ("mcap", mcap)) if on]
        self.scene = None
        self.tracker: Optional[StepTracker] = None
        self._z_free: queue.SimpleQueue = queue.SimpleQueue()  # recorded-Z buffers back from the worker
        self._z_made = 0
        self._worker = SerialThread("diffuser-lab-record", QUEUE_SIZE, stop_on_error=False) if ASYNC else None
        from .online import is_online

        self.online = is_online(conf)  # protocol=online: per-frame records (on_online_frame)
        self.frames_recorded: list[int] = []  # online: frame indices recorded, in order
        self._online = None  # online: the run's side of the per-frame records (.online.OnlineFrames)
        self._mirror = None
        if rerun:
            self._later(self._guard, "rerun", self._open_rerun)
        if mcap:
            self._later(self._guard, "mcap", self._open_mcap, overrides)

    # -- plumbing --------------------------------------------------------------------------------
    def _open_rerun(self) -> None:
        from .rerun_log import RerunRecorder

        self.rerun = RerunRecorder(self.run_dir / RRD_NAME, max_image_side=self.conf.record.max_image_side,
                                   max_depth_side=int(getattr(self.conf.record, "max_depth_side", 160)),
                                   live=getattr(self.conf.record, "live", None), online=self.online)
        self._files["rrd"] = RRD_NAME

    def _open_mcap(self, overrides: Sequence[str]) -> None:
        from diffuser_lab.runs.records import config_yaml

        from .mcap_write import McapRecorder

        try:
            yaml = config_yaml(self.conf)
        except Exception:  # noqa: BLE001 - a library caller may pass a plain object
            yaml = repr(self.conf)
        # on the recording thread already: the MCAP recorder compresses and writes in it too
        self.mcap = McapRecorder(self.run_dir / MCAP_NAME, z_dtype=str(_value(self.conf.record.z_precision)),
                                 config_yaml=yaml, overrides=overrides, interval=self.interval,
                                 max_iter=self.max_iter, compression=str(_value(getattr(self.conf.record, "compression", "zstd"))),
                                 clouds=str(_value(getattr(self.conf.record, "clouds", "decades"))),
                                 writer_thread=self._worker is None, max_image_side=self.conf.record.max_image_side)
        self._files["mcap"] = MCAP_NAME

    def _guard(self, which: str, fn, *args) -> None:
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

    def _later(self, fn, *args) -> None:
        """Run ``fn(*args)`` on the recording thread (now, without one), after what is queued."""
        if self._worker is None:
            fn(*args)
        else:
            self._worker.submit(fn, *args)

    def _each(self, rerun_fn, mcap_fn) -> None:
        """Queue the Rerun and the MCAP part of one hook call (each guarded)."""
        def both():
            if self.rerun is not None and rerun_fn is not None:
                self._guard("rerun", rerun_fn)
            if self.mcap is not None and mcap_fn is not None:
                self._guard("mcap", mcap_fn)

        self._later(both)

    # -- RunHooks ----------------------------------------------------------------------------------
    def on_scene(self, scene: Any) -> None:
        self.scene = scene
        tax = scene.taxonomy

        def rr_scene():
            self.rerun.log_taxonomy(tax.names, tax.colors)
            self.rerun.log_scene(scene.points, scene.colors, scene.gt_labels)

        self._each(rr_scene, lambda: self.mcap.log_scene(scene))
        if self.online:
            self._online_scene(scene)

    def _online_scene(self, scene: Any) -> None:
        from .online import MapMirror, OnlineFrames, online_meta

        growing = str(_value(self.conf.online.map)) == "growing"
        self._online = OnlineFrames(self.conf, len(scene.frames))
        meta = online_meta(self.conf, scene)

        def mirror():
            self._mirror = MapMirror(growing, scene.points, scene.gt_labels)

        self._later(mirror)
        self._each(lambda: self.rerun.log_online_start(scene.gt_labels is not None, growing),
                   lambda: self.mcap.log_online_start(meta))

    def on_online_frame(self, frame: Any, update: Any) -> None:
        if self._online is None:  # online() called with a config whose protocol is not online
            self.online = True
            self._online_scene(self.scene)
        if all(w in self.errors for w in self._wanted):
            return
        rec = self._online.record(frame, update, want_z="mcap" in self._wanted and "mcap" not in self.errors)
        if rec is not None:
            self.online_record(rec)

    def online_record(self, rec: Any) -> None:
        """Record one :class:`~.online.FrameRecord` (queued; what the recording process calls)."""
        if self._online is None:  # online() called with a config whose protocol is not online
            self.online = True
            self._online_scene(self.scene)

        def record():
            changed = self._mirror.update(rec)
            pts = self._mirror.points
            if self.rerun is not None:
                self._guard("rerun", lambda: self.rerun.log_online_frame(rec, self._mirror, changed))
            if self.mcap is not None:
                self._guard("mcap", lambda: self.mcap.log_online_frame(rec, pts))
            self.frames_recorded.append(rec.index)
            if rec.Z is not None:
                self.recorded.append(rec.index)

        self._later(record)

    def online_final(self, index: int, Z: np.ndarray, labels: np.ndarray, cloud: bool) -> None:
        """The last frame taken was not the sequence's last: keep its Z exactly (see on_result)."""
        def final():
            if self.mcap is not None:
                pts = self._mirror.points
                self._guard("mcap", lambda: self.mcap.log_online_final(index, Z, labels, pts, cloud))
            if not self.recorded or self.recorded[-1] != index:
                self.recorded.append(index)

        self._later(final)

    def online_result(self, summary: dict) -> None:
        """The run's summary (:func:`diffuser_lab.runs.online.summary`) into run.mcap."""
        def finish():
            if self.mcap is not None:
                s = {**summary, "records": self.files(), "recorded_frames": list(self.recorded)}
                self._guard("mcap", lambda: self.mcap.log_summary(s))

        self._later(finish)

    def on_frame(self, index: int, frame: Any) -> None:
        if self.online:  # the frame comes again with its update (on_online_frame)
            return
        def rr_frame():
            h, w = frame.shape
            labels = frame.labels if frame.labels is not None else (
                np.argmax(frame.probs, axis=2) if frame.probs is not None else None)
            self.rerun.log_camera(index, frame.name, frame.K, frame.T_cw, w, h, depth=frame.depth,
                                  labels=labels, rgb=frame.rgb)

        self._each(rr_frame, lambda: self.mcap.log_camera(index, frame))

    def on_evidence(self, points: np.ndarray, grid: Optional[Any], evidence: Any, bayesian: np.ndarray) -> None:
        scene = self.scene
        seen = evidence.seen
        def tracker():  # on the recording thread: the k-d tree query is not the run's business
            to_work = None
            if grid is not None or len(points) != scene.n_points:
                to_work = original_to_work(points, scene.points)
            self.tracker = StepTracker(len(points), scene.taxonomy.names, scene.gt_labels, to_work)

        self._later(tracker)
        self._each(lambda: self.rerun.log_evidence(points, seen, bayesian),
                   lambda: self.mcap.log_evidence(scene, self.method, points, self.tracker.to_work, seen, bayesian))

    def wants(self, iteration: int) -> bool:
        # what was asked for and has not failed: the recorders may still be opening on the
        # recording thread, and what is queued now is written once they are
        return any(w not in self.errors for w in self._wanted) and recorded(iteration, self.interval, self.max_iter)

    def _record(self, iteration: int, Z: np.ndarray, residual: float, final: bool = False) -> None:
        """On the recording thread: one recorded iteration to both recorders (``final``: the
        run's last, whose Z run.mcap keeps exact)."""
        if self.tracker is None or (self.rerun is None and self.mcap is None):
            return
        step = self.tracker.step(iteration, Z, residual)
        self._last_step = step
        pts = self.scene.points
        if self.rerun is not None:
            self._guard("rerun", lambda: self.rerun.log_step(step, pts))
        if self.mcap is not None:
            self._guard("mcap", lambda: self.mcap.log_step(step, final=final))
        self.recorded.append(step.iteration)

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

    def observe(self, iteration: int, Z: np.ndarray, stats: dict) -> None:
        residual = float(stats.get("residual", float("nan")))
        final = iteration == self.max_iter
        if self._worker is None:
            self._record(iteration, Z, residual, final)
            return
        buf = self._z_buffer(Z)  # Z is the solver's, valid during this call only

        def record():
            try:
                self._record(iteration, buf, residual, final)
            finally:
                self._z_free.put(buf)

        self._later(record)

    def on_result(self, result: Any) -> None:
        if self.online or not hasattr(result, "diffusion"):
            if self._online is not None:
                self._online.finish(result, self.online_final, self.online_result)
            return

        def finish():
            d = result.diffusion
            if d is not None and (not self.recorded or self.recorded[-1] != d.iterations):
                # the last iteration was not observed (early convergence, or a solver without
                # per-iteration observers): record it from the returned Z, exactly
                self._record(d.iterations, d.Z, float(d.residual), final=True)
            elif d is not None and d.iterations != self.max_iter and self.mcap is not None:
                # converged on a recorded iteration, stored in z_precision: keep its Z exact too
                step = self._last_step
                exact = dataclasses.replace(step, Z=np.asarray(d.Z, np.float32))
                self._guard("mcap", lambda: self.mcap.log_final(exact))
            if self.mcap is not None:
                def summary():
                    self.mcap.log_summary(_summary(result, self.files(), self.recorded))

                self._guard("mcap", summary)

        self._later(finish)

    def close(self) -> None:
        from diffuser_lab import progress

        with progress.stage(f"finishing records ({', '.join(self._wanted) or 'none'})"):
            if self._worker is not None:
                self._worker.close()  # what is queued is written first
            for which in ("rerun", "mcap"):
                rec = getattr(self, which)
                if rec is not None:
                    self._guard(which, rec.close)

    def files(self) -> dict:
        out = {k: v for k, v in self._files.items() if (k == "rrd" and "rerun" not in self.errors)
               or (k == "mcap" and "mcap" not in self.errors)}
        errors = dict(self.errors)
        if self._online is not None:  # not self.errors: the recorders must still close their files
            errors = {**self._online.errors(self._wanted), **errors}
        if errors:
            out["errors"] = errors
        return out


def _summary(res: Any, files: dict, recorded: list) -> dict:
    """The result part of summary.json (see :func:`diffuser_lab.runs.report.summary`; built here
    from the plain fields so that nothing lazy of the result is computed twice)."""
    scene = res.scene
    d = res.diffusion
    return {
        "method": res.method, "scene": scene.name, "n_points": scene.n_points,
        "n_points_diffused": int(res.work_points.shape[0]), "n_frames": len(res.frames),
        "n_classes": scene.taxonomy.num_classes, "taxonomy": scene.taxonomy.name,
        "metrics": res.metrics, "baseline": {"bayesian": res.baseline.get("bayesian")},
        "predictions_2d": res.predictions_2d,
        "diffusion": ({"iterations": d.iterations, "converged": d.converged, "residual": d.residual}
                      if d is not None else {"iterations": 0, "converged": None, "residual": None}),
        "timings_s": {k: round(float(v), 4) for k, v in res.timings_s.items()},
        "records": files, "recorded_iterations": list(recorded),
    }


class _Off(RunHooks):
    """record=off: records nothing."""

    def files(self) -> dict:
        return {}


def make_hooks(conf: Any, run_dir: Path | str, overrides: Sequence[str] = (), *, process: bool = False) -> RunHooks:
    """The run's recorders as configured by ``conf.record.mode`` (off | rerun | mcap | both).
    The returned object has the :class:`RunHooks` methods and ``files() -> {"rrd": .., "mcap": ..}``
    (names relative to ``run_dir``). ``process``: record in a forked child process
    (:mod:`.process`; what the ``diffuser-lab`` command does where ``fork`` exists), else on a
    thread of this one."""
    mode = str(_value(conf.record.mode))
    if mode == "off":
        return _Off()
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    kinds = dict(rerun=mode in ("rerun", "both"), mcap=mode in ("mcap", "both"), overrides=overrides)
    if process:
        from . import process as proc

        if proc.available():
            return proc.ProcessHooks(conf, run_dir, **kinds)
    return RecordingHooks(conf, run_dir, **kinds)


__all__ = ["make_hooks", "RecordingHooks", "Step", "StepTracker", "RRD_NAME", "MCAP_NAME"]
