"""Records of a run: run.rrd (Rerun) and run.mcap (MCAP), written as the diffusion goes.

Both recorders are observers (:class:`~diffuser_lab.hooks.RunHooks`): they read the arrays the
pipeline hands them and never change the result. Per recorded iteration (every
``record.interval``-th, plus the first and the last) the derived quantities (labels,
confidence, changes, mIoU so far) are computed once (:mod:`.steps`) and given to both.

A recorder that fails (disk full, a bug) is switched off with a warning and the run goes on;
the failure is reported in ``files()["errors"]`` (and so in summary.json's ``records``).

Usage (the CLI does this when ``record != off``)::

    hooks = make_hooks(conf, run_dir, overrides=[])
    try:
        result = run(conf, hooks=hooks)
    finally:
        hooks.close()
    hooks.files()   # {"rrd": "run.rrd", "mcap": "run.mcap"}
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from ..hooks import RunHooks
from .heap import retain_freed_memory
from .steps import Step, StepTracker, original_to_work

log = logging.getLogger("diffuser_lab.recording")

RRD_NAME = "run.rrd"
MCAP_NAME = "run.mcap"


def _value(x: Any) -> Any:
    return getattr(x, "value", x)


class RecordingHooks(RunHooks):
    """Feeds a run to a Rerun and/or an MCAP recorder (either may be None)."""

    def __init__(self, conf: Any, run_dir: Path, *, rerun: bool, mcap: bool, overrides: Sequence[str] = ()):
        self.conf = conf
        self.run_dir = Path(run_dir)
        self.interval = int(conf.record.interval)
        self.max_iter = int(conf.solver.max_iter)
        self.method = str(_value(conf.method.name))
        self.errors: dict[str, str] = {}
        self._files: dict[str, str] = {}
        self.recorded: list[int] = []  # iterations recorded, in order
        self.rerun = self.mcap = None
        self.scene = None
        self.tracker: Optional[StepTracker] = None
        retain_freed_memory(int(getattr(conf.record, "retain_heap_mb", 0)))
        if rerun:
            self._guard("rerun", self._open_rerun)
        if mcap:
            self._guard("mcap", self._open_mcap, overrides)

    # -- plumbing --------------------------------------------------------------------------------
    def _open_rerun(self) -> None:
        from .rerun_log import RerunRecorder

        self.rerun = RerunRecorder(self.run_dir / RRD_NAME, max_image_side=self.conf.record.max_image_side)
        self._files["rrd"] = RRD_NAME

    def _open_mcap(self, overrides: Sequence[str]) -> None:
        from ..config import config_yaml
        from .mcap_log import McapRecorder

        try:
            yaml = config_yaml(self.conf)
        except Exception:  # noqa: BLE001 - a library caller may pass a plain object
            yaml = repr(self.conf)
        self.mcap = McapRecorder(self.run_dir / MCAP_NAME, z_dtype=str(_value(self.conf.record.z_precision)),
                                 config_yaml=yaml, overrides=overrides, interval=self.interval,
                                 max_iter=self.max_iter, zstd_level=int(getattr(self.conf.record, "zstd_level", -20)))
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

    def _each(self, rerun_fn, mcap_fn) -> None:
        if self.rerun is not None and rerun_fn is not None:
            self._guard("rerun", rerun_fn)
        if self.mcap is not None and mcap_fn is not None:
            self._guard("mcap", mcap_fn)

    # -- RunHooks ----------------------------------------------------------------------------------
    def on_scene(self, scene: Any) -> None:
        self.scene = scene
        tax = scene.taxonomy

        def rr_scene():
            self.rerun.log_taxonomy(tax.names, tax.colors)
            self.rerun.log_scene(scene.points, scene.colors, scene.gt_labels)

        self._each(rr_scene, lambda: self.mcap.log_scene(scene))

    def on_frame(self, index: int, frame: Any) -> None:
        def rr_frame():
            h, w = frame.shape
            labels = frame.labels if frame.labels is not None else (
                np.argmax(frame.probs, axis=2) if frame.probs is not None else None)
            self.rerun.log_camera(index, frame.name, frame.K, frame.T_cw, w, h, depth=frame.depth,
                                  labels=labels, rgb=frame.rgb)

        self._each(rr_frame, lambda: self.mcap.log_camera(index, frame))

    def on_evidence(self, points: np.ndarray, grid: Optional[Any], evidence: Any, bayesian: np.ndarray) -> None:
        scene = self.scene
        to_work = None
        if grid is not None or len(points) != scene.n_points:
            to_work = original_to_work(points, scene.points)
        self.tracker = StepTracker(len(points), scene.taxonomy.names, scene.gt_labels, to_work)
        seen = evidence.seen
        self._each(lambda: self.rerun.log_evidence(points, seen, bayesian),
                   lambda: self.mcap.log_evidence(scene, self.method, points, to_work, seen, bayesian))

    def wants(self, iteration: int) -> bool:
        return (self.rerun is not None or self.mcap is not None) and (
            iteration == 1 or iteration % self.interval == 0 or iteration == self.max_iter)

    def _record(self, iteration: int, Z: np.ndarray, residual: float) -> None:
        if self.tracker is None or (self.rerun is None and self.mcap is None):
            return
        step = self.tracker.step(iteration, Z, residual)
        pts = self.scene.points
        self._each(lambda: self.rerun.log_step(step, pts), lambda: self.mcap.log_step(step))
        self.recorded.append(step.iteration)

    def observe(self, iteration: int, Z: np.ndarray, stats: dict) -> None:
        self._record(iteration, Z, float(stats.get("residual", float("nan"))))

    def on_result(self, result: Any) -> None:
        d = result.diffusion
        if d is not None and (not self.recorded or self.recorded[-1] != d.iterations):
            # the last iteration was not observed (early convergence, or a solver without
            # per-iteration observers): record it from the returned Z, exactly
            self._record(d.iterations, d.Z, float(d.residual))
        if self.mcap is not None:
            def summary():
                self.mcap.log_summary(_summary(result, self.files(), self.recorded))

            self._guard("mcap", summary)

    def close(self) -> None:
        for which in ("rerun", "mcap"):
            rec = getattr(self, which)
            if rec is not None:
                self._guard(which, rec.close)

    def files(self) -> dict:
        out = {k: v for k, v in self._files.items() if (k == "rrd" and "rerun" not in self.errors)
               or (k == "mcap" and "mcap" not in self.errors)}
        if self.errors:
            out["errors"] = dict(self.errors)
        return out


def _summary(res: Any, files: dict, recorded: list) -> dict:
    """The result part of summary.json (see :func:`diffuser_lab.report.summary`; built here
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


def make_hooks(conf: Any, run_dir: Path | str, overrides: Sequence[str] = ()) -> RunHooks:
    """The run's recorders as configured by ``conf.record.mode`` (off | rerun | mcap | both).
    The returned object has the :class:`RunHooks` methods and ``files() -> {"rrd": .., "mcap": ..}``
    (names relative to ``run_dir``)."""
    mode = str(_value(conf.record.mode))
    if mode == "off":
        return _Off()
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    return RecordingHooks(conf, run_dir, rerun=mode in ("rerun", "both"), mcap=mode in ("mcap", "both"),
                          overrides=overrides)


__all__ = ["make_hooks", "RecordingHooks", "Step", "StepTracker", "RRD_NAME", "MCAP_NAME"]
