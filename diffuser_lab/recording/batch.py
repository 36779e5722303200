"""The records of a batch run (the global and single-frame protocols): its cameras, its evidence
and, per recorded iteration (:mod:`.schedule`: 1, 2, 5, 10, 20, 50, ... or every
``record.interval``-th, plus the first and the last), the derived quantities (labels,
confidence, changes, mIoU so far), computed once (:mod:`.steps`) and given to both recorders.

:class:`BatchHooks` is the run's side (the hooks the pipeline calls), :class:`BatchRecorder`
the writing side (in :class:`~.recorders.Recorders`, wherever the records are written).
"""
from __future__ import annotations

import dataclasses
from types import SimpleNamespace
from typing import Any, Optional

import numpy as np

from diffuser_lab.backends.stats import StatsRequest

from . import features as feature_view
from .hooks import RecordingHooks, slim_scene
from .online import OnlineHooks
from .schedule import recorded
from .steps import StepTracker, metrics_rows, original_to_work


class BatchHooks(RecordingHooks):
    """A batch run's hooks: frames, evidence, the recorded iterations' Z, the result."""

    def __init__(self, conf: Any, lane: Any):
        super().__init__(conf, lane)
        self.interval = None if conf.record.interval is None else int(conf.record.interval)
        self.max_iter = int(conf.solver.max_iter)
        self._online: Optional[OnlineHooks] = None  # online() called with a config whose protocol is not online
        # a features run: its queries (on_queries), the projection fitted on the evidence
        # (:mod:`.features`) and the last iteration projected with it
        self.query = getattr(conf.record, "query", None)
        self._queries: Optional[tuple] = None
        self._basis: Optional[np.ndarray] = None
        self._view: Optional[feature_view.FeatureView] = None
        self._projected = 0
        # run.rrd's scalars at every iteration, computed by the diffusion's backend in its steps
        # (statistics(), on_statistics()): what they are asked against (ground truth, each
        # original point's work point); the Z states stay on the schedule
        self._request: Optional[StatsRequest] = None

    def on_queries(self, names: Any, embeddings: np.ndarray, basis: Optional[np.ndarray] = None) -> None:
        feature_view.pick_query(names, self.query)  # an unknown record.query: an error now, not after the run
        self._queries = (tuple(names), embeddings)
        self._basis = basis  # (D, k): the features are coordinates; the recorded view is lifted to R^D

    def on_frame(self, index: int, frame: Any) -> None:
        if self._online is None:  # an online run's frame comes again with its update
            self.lane.send("batch.frame", index, frame)

    def on_evidence(self, points: np.ndarray, grid: Optional[Any], evidence: Any, bayesian: np.ndarray) -> None:
        self.lane.send("batch.evidence", points, grid is not None, evidence.seen, bayesian)
        if "rerun" in self.lane.wanted and self._queries is None and self.scene is not None:
            # (a features run is left out: its columns are features, not classes)
            gt = self.scene.gt_labels
            to_work = None
            if gt is not None and (grid is not None or len(points) != self.scene.n_points):
                to_work = original_to_work(points, self.scene.points)
            self._request = StatsRequest(gt, to_work)
        mass = getattr(evidence, "mass", None)
        if self._queries is not None and mass is not None and mass.shape[1] == self._queries[1].shape[1] \
                and self.recording():
            self._view = feature_view.fit_view(mass, *self._queries, self.query)
            self.lane.send("batch.feature_view", feature_view.lifted(self._view, self._basis))

    def observe_features(self, iteration: int, F: np.ndarray) -> None:
        if self._view is not None and self._scheduled(iteration):
            self._send_features(iteration, F)

    def _send_features(self, iteration: int, F: np.ndarray) -> None:
        rgb, sim = feature_view.project(self._view, F)
        self.lane.send("batch.features", iteration, rgb, sim)
        self._projected = iteration

    def _scheduled(self, iteration: int) -> bool:
        return recorded(iteration, self.interval, self.max_iter)

    def statistics(self) -> Optional[StatsRequest]:
        """run.rrd's scalars of every iteration, from the backend's statistics (while run.rrd is written)."""
        if self._online is not None:  # an online run's finishing pass
            return self._online.statistics()
        return self._request if self._request is not None and self.lane.live("rerun") else None

    def on_statistics(self, table: Any) -> None:
        if self._online is not None:
            self._online.on_statistics(table)
        elif self.lane.live("rerun"):
            self.lane.send("batch.metrics", metrics_rows(table))

    def wants(self, iteration: int) -> bool:
        # what was asked for and has not failed: the recorders may still be opening where they
        # are written, and what is sent now is written once they are
        if self._online is not None:
            return self._online.wants(iteration)
        return self.recording() and self._scheduled(iteration)

    def observe(self, iteration: int, Z: np.ndarray, stats: dict) -> None:
        if self._online is not None:
            self._online.observe(iteration, Z, stats)
        elif self.recording() and self._scheduled(iteration):
            self.lane.send_z("batch.step", iteration, Z, float(stats.get("residual", float("nan"))))

    def on_online_frame(self, frame: Any, update: Any) -> None:
        if self._online is None:  # the run is online after all: its frames are recorded from here
            self._online = OnlineHooks(self.conf, self.lane)
            self._online.start(self.scene)
        self._online.on_online_frame(frame, update)

    def on_result(self, result: Any) -> None:
        if self._online is not None or not hasattr(result, "diffusion"):
            if self._online is not None:
                self._online.on_result(result)
            return
        d, space = result.diffusion, getattr(result, "space", None)
        if self._view is not None and d is not None and self._projected != d.iterations \
                and getattr(space, "method", None) is not None:
            # the last iteration's features were not observed (early stop, or diffused in blocks)
            self._send_features(d.iterations, space.observed(space.method))
        if getattr(result, "confidence", None) is not None and self.lane.live("rerun"):  # output.scores
            self.lane.send("batch.confidence", result.confidence)
        self.lane.send("batch.result", slim_result(result))

    def files(self) -> dict:
        return self._online.files() if self._online is not None else super().files()


class BatchRecorder:
    """The writing side of a batch run's records, on the recorders ``recs``
    (:class:`~.recorders.Recorders`)."""

    def __init__(self, recs: Any):
        self.recs = recs
        self.method = str(recs.conf.method.name)
        self.max_iter = int(recs.conf.solver.max_iter)
        self.tracker: Optional[StepTracker] = None
        self._last_step = None
        self._dense_last = 0  # the last iteration whose run.rrd scalars the run's side sent (batch.metrics)

    def frame(self, index: int, frame: Any) -> None:
        r = self.recs

        def rr_frame():
            h, w = frame.shape
            labels = frame.labels if frame.labels is not None else (
                np.argmax(frame.probs, axis=2) if frame.probs is not None else None)
            r.rerun.log_camera(index, frame.name, frame.K, frame.T_cw, w, h, depth=frame.depth,
                               labels=labels, rgb=frame.rgb)

        r.each(rr_frame, lambda: r.mcap.log_camera(index, frame))

    def evidence(self, points: np.ndarray, voxels: bool, seen: np.ndarray, bayesian: np.ndarray) -> None:
        """``voxels``: the work cloud is a voxel grid of the scene's points."""
        r = self.recs
        scene = r.scene
        to_work = None  # the k-d tree query happens here: it is not the run's business
        if voxels or len(points) != scene.n_points:
            to_work = original_to_work(points, scene.points)
        self.tracker = StepTracker(len(points), scene.taxonomy.names, scene.gt_labels, to_work)
        r.each(lambda: r.rerun.log_evidence(points, seen, bayesian),
               lambda: r.mcap.log_evidence(scene, self.method, points, self.tracker.to_work, seen, bayesian))

    def feature_view(self, view: Any) -> None:
        """A features run's projection (:class:`~.features.FeatureView`), once, after the evidence."""
        r = self.recs
        r.each(lambda: r.rerun.log_feature_view(view), lambda: r.mcap.log_feature_view(view))

    def features(self, iteration: int, rgb: np.ndarray, sim: np.ndarray) -> None:
        """A recorded iteration's features as (M, 3) uint8 RGB and (M,) uint8 query similarity."""
        r = self.recs
        r.each(lambda: r.rerun.log_features(iteration, rgb, sim), lambda: r.mcap.log_features(iteration, rgb, sim))

    def metrics(self, rows: np.ndarray) -> None:
        """run.rrd's scalars of consecutive iterations, (k, 6) rows of iteration, residual, labels
        changed per iteration since the one before, mean confidence, mIoU, accuracy (NaN: none)
        (:func:`~.steps.metrics_rows` of the backend's statistics, every iteration)."""
        r = self.recs
        self._dense_last = int(rows[-1, 0])
        r.each(lambda: r.rerun.log_metrics_columns(rows), None)

    def confidence(self, values: np.ndarray) -> None:
        """The original points' (N, 3) top score, margin and entropy (``output.scores``): run.rrd's layer."""
        r = self.recs
        r.each(lambda: r.rerun.log_confidence(r.scene.points, values), None)

    def step(self, iteration: int, Z: np.ndarray, residual: float) -> None:
        """A recorded iteration (Z valid during the call only)."""
        self._record(iteration, Z, residual, final=iteration == self.max_iter)

    def _record(self, iteration: int, Z: np.ndarray, residual: float, final: bool) -> None:
        """One recorded iteration to both recorders (``final``: the run's last, whose Z run.mcap
        keeps exact)."""
        r = self.recs
        if self.tracker is None or (r.rerun is None and r.mcap is None):
            return
        step = self.tracker.step(iteration, Z, residual)
        self._last_step = step
        pts = r.scene.points
        scalars = step.iteration > self._dense_last  # not sent by the run's side (a solver that observes none)
        r.each(lambda: r.rerun.log_step(step, pts, metrics=scalars), lambda: r.mcap.log_step(step, final=final))
        r.recorded.append(step.iteration)

    def result(self, result: Any) -> None:
        """The run's end (``result``: :func:`slim_result`)."""
        r = self.recs
        d = result.diffusion
        if d is not None and (not r.recorded or r.recorded[-1] != d.iterations):
            # the last iteration was not observed (early convergence, or a solver without
            # per-iteration observers): record it from the returned Z, exactly
            self._record(d.iterations, d.Z, float(d.residual), final=True)
        elif d is not None and d.iterations != self.max_iter and r.mcap is not None:
            # converged on a recorded iteration, stored in z_precision: keep its Z exact too
            exact = dataclasses.replace(self._last_step, Z=np.asarray(d.Z, np.float32))
            r.guard("mcap", lambda: r.mcap.log_final(exact))
        if r.mcap is not None:
            r.guard("mcap", lambda: r.mcap.log_summary(summary(result, r.files(), r.recorded)))


def slim_result(res: Any) -> SimpleNamespace:
    """What the recorders read of a RunResult (see :func:`summary`)."""
    d = res.diffusion
    diff = None if d is None else SimpleNamespace(iterations=d.iterations, converged=d.converged,
                                                  residual=d.residual, Z=d.Z)
    return SimpleNamespace(method=res.method, scene=slim_scene(res.scene), work_points=np.empty((len(res.work_points), 0)),
                           frames=[None] * len(res.frames), metrics=res.metrics,
                           baseline={"bayesian": res.baseline.get("bayesian")}, predictions_2d=res.predictions_2d,
                           diffusion=diff, timings_s=dict(res.timings_s))


def summary(res: Any, files: dict, recorded: list) -> dict:
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


__all__ = ["BatchHooks", "BatchRecorder", "slim_result", "summary"]
