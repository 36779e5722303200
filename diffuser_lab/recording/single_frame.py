"""Records of a single-frame run (``protocol=single_frame``, the paper's Table II): each target
frame's diffusion, replayable like a batch run's, and the Table II rows as they accumulate.

:class:`SingleFrameHooks` is the run's side (the hooks :func:`~diffuser_lab.runs.single_frame.single_frame`
calls: ``on_target``, the Diffuser's diffusion with the window's views, ``on_target_done``),
:class:`SingleFrameRecorder` the writing side (in :class:`~.recorders.Recorders`).

**The timeline.** The targets' diffusions follow each other on the ``diffusion_step`` sequence
timeline (run.mcap's ``iteration``): target k starts at step s_k (its cloud, window and images),
its iteration t is step s_k + t, its rows come at s_k + T_k + 1 (T_k: its iterations) and the
next target starts one step later; the ``target`` timeline (sequence = the target frame's index)
is set beside it. Playing ``diffusion_step`` runs through every target's diffusion in turn.

run.rrd (application id ``diffuser_lab_single_frame``)::

    world                          AnnotationContext (taxonomy names + colours; 65535 = unlabeled)
    world/scene/points             Points3D, static: the scene's cloud (context; not what is labelled)
    world/diffusion/labels         Points3D: the target's work points (its back-projected depth,
                                   voxelised) at s_k, class ids per recorded iteration (1-2-5)
    world/diffusion/confidence     Points3D: the same points, max_c Z / sum_c Z in 64 bins (viridis)
    world/diffusion/wrong          Points3D per recorded iteration: work points whose label is not
                                   their pixels' most frequent ground truth
    world/target/ground_truth      Points3D at s_k: the work points in that ground truth's colours
    world/target/camera            Transform3D + Pinhole at s_k: the target's camera (a tab looks through it)
    world/window/<j>               Transform3D + Pinhole + labels (SegmentationImage) at s_k: the
                                   window's j-th view (the frames whose pixels label the target)
    target/diffuser                SegmentationImage per recorded iteration: the Diffuser's labels
                                   projected back into the target frame (strided to record.max_image_side)
    target/ground_truth            SegmentationImage at s_k: the frame's ground-truth labels
    target/prediction              SegmentationImage at s_k: the network's 2D labels of the frame
    target/rows/<method>_<views>   SegmentationImage at s_k + T_k + 1: each Table II row's labels of the frame
    metrics/miou|accuracy          Scalars at every iteration: the frame's 2D mIoU / accuracy so far
                                   (pixels without depth or label count as misses, as Table II)
    metrics/confidence|residual_log10|changed_per_iter_log10   as a batch run's, every iteration
    table                          TextDocument at s_k + T_k + 1: Table II so far (markdown)
    table/miou/<method>_<views>    Scalars at s_k + T_k + 1: each row's pooled 2D mIoU so far
    legend                         Image, static: the classes, unlabeled, wrong label, confidence

run.mcap: ``/scene/points``, the cameras (``/tf``, ``/cameras/calibration``, ``/cameras/labels``,
each frame once, when a window first holds it), and per target ``/diffuser_lab/single_frame/target``
(``diffuser_lab.TargetFrame``: its work points, their ground truth, each pixel's work point,
the ground-truth image, its window, its first step), ``/diffuser_lab/z`` and
``/diffuser_lab/metrics`` per recorded iteration (``iteration`` = the global step; the target's
last iteration float32, exact), ``/diffuser_lab/single_frame/rows`` (JSON: the Table II rows so
far, the frame's mIoU per row) and ``/single_frame/labels`` (a label PNG per row, ``frame_id`` =
``<method>_<views>``); metadata ``diffuser_lab.single_frame`` and ``diffuser_lab.summary``.
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any, Optional, Sequence

import numpy as np

from diffuser_lab.backends.stats import StatsRequest
from diffuser_lab.data.scene import IGNORE

from . import schema
from .eyes import eye_kw, follow_eye, overview_eye, scene_up
from .hooks import RecordingHooks
from .mcap_encode import strided
from .rerun_log import (APP_SINGLE_FRAME, CONFIDENCE_BINS, RIGHT_RGB, TIMELINE, RerunRecorder, class_ids,
                        confidence_context, legend_view, plot, point_radius)
from .schedule import recorded
from .steps import Step, StepTracker, metrics_rows

TARGET_TIMELINE = "target"
"""run.rrd's second timeline of a single-frame run: sequence = the target frame's index."""


@dataclass
class Camera:
    """A window frame's camera as the recorders need it (plain arrays): index, name, K (3, 3) and
    shape (h, w) of the full image, T_cw (4, 4), labels (h, w) int16 the network's 2D labels or None."""

    index: int
    name: str
    K: np.ndarray
    T_cw: np.ndarray
    shape: tuple
    labels: Optional[np.ndarray]


@dataclass
class TargetRecord:
    """A target frame as the recorders need it (plain arrays, picklable): see
    :class:`~diffuser_lab.runs.single_frame.Target`; ``window`` its frame indices and ``poses``
    their (name, K (3, 3), T_cw (4, 4), (h, w)) at full size, ``cameras`` the window's frames not
    handed on before (with their 2D labels); ``pixels`` (H, W) int32, ``gt_image`` (H, W) int16
    at full size; ``method``, ``views``: the row whose diffusion is recorded."""

    index: int
    count: int
    name: str
    window: list
    poses: list
    cameras: list
    work_points: np.ndarray
    work_gt: np.ndarray
    pixels: np.ndarray
    gt_image: np.ndarray
    method: str
    views: int


def _labels_of(frame: Any) -> Optional[np.ndarray]:
    if frame.labels is not None:
        return np.asarray(frame.labels, np.int16)
    if frame.probs is not None:
        return np.argmax(frame.probs, axis=2).astype(np.int16)
    return None


def target_record(target: Any, sent: set) -> TargetRecord:
    """The :class:`TargetRecord` of a :class:`~diffuser_lab.runs.single_frame.Target`; ``sent``:
    the frame indices whose cameras went before (updated)."""
    cams = []
    for j, f in zip(target.window, target.frames):
        if j not in sent:
            sent.add(j)
            cams.append(Camera(int(j), str(f.name), np.asarray(f.K, np.float64), np.asarray(f.T_cw, np.float64),
                               tuple(int(v) for v in f.shape), _labels_of(f)))
    method, views = target.observed
    poses = [(str(f.name), np.asarray(f.K, np.float64), np.asarray(f.T_cw, np.float64), tuple(int(v) for v in f.shape))
             for f in target.frames]
    return TargetRecord(index=int(target.index), count=int(target.count), name=str(target.frame.name),
                        window=[int(j) for j in target.window], poses=poses, cameras=cams,
                        work_points=np.array(target.work_points, np.float32),
                        work_gt=np.array(target.work_gt, np.int16), pixels=np.array(target.pixels, np.int32),
                        gt_image=np.array(target.frame.gt_labels, np.int16), method=str(method), views=int(views))


def is_single_frame(conf: Any) -> bool:
    return conf.protocol.name == "single_frame"


def row_name(method: str, views: int) -> str:
    """A Table II row's name in entity paths and PNG frame ids: ``<method>_<views>``."""
    return f"{method}_{int(views)}"


def single_frame_meta(conf: Any, scene: Any) -> dict:
    """run.mcap's ``diffuser_lab.single_frame`` metadata: the protocol's keys and the schedule."""
    pc, rc = conf.protocol, conf.record
    return {"window": int(pc.window), "target_step": int(pc.target_step), "max_targets": pc.max_targets,
            "n_frames": len(getattr(scene, "frames", ())), "fill_missing_depth": bool(pc.fill_missing_depth),
            "interval": rc.interval, "max_iter": int(conf.solver.max_iter), "z_dtype": rc.z_precision.value,
            "has_gt": True}


def summary_of(res: Any) -> dict:
    """What run.mcap's ``diffuser_lab.summary`` holds of a single-frame result."""
    return {"protocol": "single_frame", "scene": res.scene.name, "window": res.window, "targets": list(res.targets),
            "rows": res.rows, "predictions_2d": res.predictions_2d, "mean_points": res.mean_points,
            "filled": res.filled, "timings_s": {k: round(float(v), 4) for k, v in res.timings_s.items()}}


class SingleFrameHooks(RecordingHooks):
    """A single-frame run's hooks (see the module doc): per target its record, the Diffuser's
    scalars at every iteration (the backend's statistics against the frame's annotated pixels),
    its Z on the schedule, its final Z, the rows scored."""

    def __init__(self, conf: Any, lane: Any):
        super().__init__(conf, lane)
        self.interval = None if conf.record.interval is None else int(conf.record.interval)
        self.max_iter = int(conf.solver.max_iter)
        self.max_image_side = int(conf.record.max_image_side)
        self._request: Optional[StatsRequest] = None
        self._sent: set = set()
        self._observed = 0  # the last iteration whose Z was sent for the current target

    def on_scene(self, scene: Any) -> None:
        super().on_scene(scene)
        self.lane.send("single.start", single_frame_meta(self.conf, scene))

    def on_target(self, target: Any) -> None:
        self._request = StatsRequest(np.asarray(target.frame.gt_labels).ravel(), np.asarray(target.pixels).ravel())
        self._observed = 0
        if self.recording():
            self.lane.send("single.target", target_record(target, self._sent))

    def statistics(self) -> Optional[StatsRequest]:
        return self._request if self._request is not None and self.lane.live("rerun") else None

    def on_statistics(self, table: Any) -> None:
        if self.lane.live("rerun"):
            self.lane.send("single.metrics", metrics_rows(table))

    def wants(self, iteration: int) -> bool:
        return self._request is not None and self.recording() and recorded(iteration, self.interval, self.max_iter)

    def observe(self, iteration: int, Z: np.ndarray, stats: dict) -> None:
        self.lane.send_z("single.step", int(iteration), Z, float(stats.get("residual", float("nan"))))
        self._observed = int(iteration)

    def on_target_done(self, index: int, images: dict, rows: list, diffusion: Any = None) -> None:
        if not self.recording():
            return
        if diffusion is not None and (self._observed != diffusion.iterations or diffusion.iterations != self.max_iter):
            # the last iteration exactly (unobserved after an early stop, or kept in z_precision)
            self.lane.send_z("single.final", int(diffusion.iterations), np.asarray(diffusion.Z, np.float32),
                             float(diffusion.residual))
        small = {}
        for (method, views), img in images.items():
            small[row_name(method, views)] = np.array(strided(np.asarray(img), np.eye(3), self.max_image_side)[0],
                                                      np.int16)
        self.lane.send("single.done", int(index), small, [{k: v for k, v in r.items() if k != "calibration"}
                                                          for r in rows])
        self._request = None

    def on_result(self, result: Any) -> None:
        self.lane.send("single.result", summary_of(result))


class SingleFrameRecorder:
    """The writing side of a single-frame run's records, on the recorders ``recs``."""

    def __init__(self, recs: Any):
        self.recs = recs
        self.max_iter = int(recs.conf.solver.max_iter)
        self.max_image_side = int(recs.conf.record.max_image_side)
        self.next_step = 1  # where the next target starts on the step timeline
        self.labels: dict[int, Optional[np.ndarray]] = {}  # frame index -> its strided 2D labels (run.rrd's windows)
        self.target_rec: Optional[TargetRecord] = None
        self.tracker: Optional[StepTracker] = None
        self.offset = 0  # the current target's start step
        self.last = 0  # its last iteration seen (scalars or Z)
        self.steps: list[int] = []  # its recorded iterations
        self._last_step: Optional[Step] = None
        self._scalars_to = 0  # the last global step whose scalars came from the run's side

    def start(self, meta: dict) -> None:
        r = self.recs
        pts = getattr(r.scene, "points", None)
        r.each(lambda: r.rerun.log_single_frame_start(pts), lambda: r.mcap.log_single_frame_start(meta))

    def target(self, rec: TargetRecord) -> None:
        r = self.recs
        self.target_rec = rec
        self.offset = self.next_step
        self.last = 0
        self.steps = []
        self._last_step = None
        for cam in rec.cameras:  # run.rrd keeps each frame's 2D labels strided, for the windows of later targets
            self.labels[cam.index] = None if cam.labels is None else strided(cam.labels, cam.K, self.max_image_side)[0]
        window = window_cameras(rec, self.labels, self.max_image_side)
        self.tracker = target_tracker(rec, r.scene.taxonomy.names)
        msg = target_message(rec, self.offset)
        r.each(lambda: r.rerun.log_target(rec, self.offset, window, self.max_image_side),
               lambda: r.mcap.log_target(msg, rec.cameras))

    def metrics(self, rows: np.ndarray) -> None:
        """The target's scalars at every iteration ((k, 6) rows as :func:`~.steps.metrics_rows`), moved
        onto the run's step timeline."""
        r = self.recs
        rows = np.array(rows, np.float64)
        self.last = max(self.last, int(rows[-1, 0]))
        rows[:, 0] += self.offset
        self._scalars_to = int(rows[-1, 0])
        r.each(lambda: r.rerun.log_metrics_columns(rows), None)

    def step(self, iteration: int, Z: np.ndarray, residual: float) -> None:
        """A recorded iteration of the target's diffusion (Z valid during the call only)."""
        self._record(iteration, Z, residual, final=iteration == self.max_iter)

    def final(self, iteration: int, Z: np.ndarray, residual: float) -> None:
        """The target's last iteration, exact: recorded again (run.mcap, float32) or for the first time."""
        r = self.recs
        if self.steps and self.steps[-1] == iteration and self._last_step is not None:
            exact = dataclasses.replace(self._last_step, Z=np.asarray(Z, np.float32))
            if r.mcap is not None:
                r.guard("mcap", lambda: r.mcap.log_final(exact))
            return
        self._record(iteration, Z, residual, final=True)

    def _record(self, iteration: int, Z: np.ndarray, residual: float, final: bool) -> None:
        r = self.recs
        if self.tracker is None or (r.rerun is None and r.mcap is None):
            return
        step = self.tracker.step(self.offset + int(iteration), Z, residual)
        self._last_step = step
        self.steps.append(int(iteration))
        self.last = max(self.last, int(iteration))
        scalars = step.iteration > self._scalars_to  # not sent by the run's side
        rec = self.target_rec
        r.each(lambda: r.rerun.log_target_step(step, rec, self.max_image_side, metrics=scalars),
               lambda: r.mcap.log_step(step, final=final))
        r.recorded.append(step.iteration)

    def done(self, index: int, images: dict, rows: list) -> None:
        """The target scored: the rows' label images of the frame (strided) and Table II so far."""
        r = self.recs
        end = self.offset + self.last + 1
        payload = {"index": int(index), "step": end, "start": self.offset, "iterations": self.last,
                   "recorded": [self.offset + t for t in self.steps], "rows": rows}
        r.each(lambda: r.rerun.log_target_rows(end, index, images, rows),
               lambda: r.mcap.log_target_rows(end, payload, images))
        self.next_step = end + 1
        self.tracker = None

    def result(self, summary: dict) -> None:
        r = self.recs
        if r.mcap is not None:
            s = {**summary, "records": r.files(), "recorded_iterations": list(r.recorded)}
            r.guard("mcap", lambda: r.mcap.log_summary(s))


def window_cameras(rec: TargetRecord, labels: dict, max_side: int) -> list:
    """The target's window as run.rrd draws it: per frame its index, name, T_cw and the K, width and
    height of its label image strided to ``max_side`` (``labels`` {frame index: (h, w) strided
    labels or None})."""
    out = []
    for j, (name, K, T, shape) in zip(rec.window, rec.poses):
        lab = labels.get(int(j))
        if lab is None:
            img, K_s = strided(np.empty((shape[0], shape[1], 0), np.uint8), K, max_side)
            h, w = img.shape[:2]
        else:  # the stride the stored image was made with (a replay's max_side may differ)
            k = max(1, int(np.ceil(shape[0] / lab.shape[0])))
            K_s = np.asarray(K, np.float64).copy()
            K_s[:2, :] /= k
            h, w = lab.shape
        out.append(SimpleNamespace(index=int(j), name=name, K=K_s, T_cw=T, width=w, height=h, labels=lab))
    return out


def target_tracker(rec: TargetRecord, names: Sequence[str]) -> StepTracker:
    """The :class:`~.steps.StepTracker` of a target: its pixels are the "original points" (those
    on a work point through ``pixels``, the annotated rest as misses), so a recorded iteration's
    mIoU and accuracy are the frame's 2D ones, as the scalars'."""
    pix, gt = rec.pixels.ravel(), rec.gt_image.ravel()
    on = pix >= 0
    off = gt[~on]
    off = off[(off >= 0) & (off < len(names))]
    return StepTracker(len(rec.work_points), names, gt[on], pix[on].astype(np.int64),
                       misses=np.bincount(off, minlength=len(names)))


def replay(mcap_path: Any, rrd_path: Any, max_image_side: int = 320) -> Any:
    """Re-log a single-frame run into a fresh .rrd from its run.mcap alone: the same entities and
    layout as the live run.rrd, the recorded iterations' labels, confidence, wrong points and
    images, their scalars (at the recorded iterations only: run.mcap keeps no others), the rows'
    images and Table II. Returns the :class:`~.mcap_read.RunLog` (truncation, targets)."""
    from pathlib import Path

    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

    from .mcap_encode import (TOPIC_CAMERA_LABELS, TOPIC_METRICS, TOPIC_SCENE, TOPIC_TARGET, TOPIC_TARGET_IMAGES,
                              TOPIC_TARGET_ROWS, TOPIC_Z, camera_index, decode_label_png, decode_z)
    from .mcap_read import RunLog, iter_run, metrics_dict, relog_scene, target_dict

    log = RunLog(path=Path(mcap_path))
    rec = SingleFrameRerun(Path(rrd_path), max_image_side=max_image_side)
    names: list = []
    colors = np.zeros((0, 3), np.uint8)
    labels: dict = {}  # frame index -> its stored 2D labels
    images: dict = {}  # the current target's rows' images
    target = tracker = None
    residual: dict = {}
    try:
        for topic, data in iter_run(mcap_path, log):
            if topic == TOPIC_SCENE:
                points, names, colors, gt = relog_scene(rec, data, log.run, mcap_path)
            elif topic == TOPIC_CAMERA_LABELS:
                img = CompressedImage.FromString(data)
                labels[camera_index(img.frame_id)] = decode_label_png(img.data, colors)
            elif topic == TOPIC_TARGET:
                msg = schema.TargetFrame.FromString(data)
                target = record_of_message(msg)
                tracker = target_tracker(target, names)
                log.targets.append(target_dict(data))
                rec.log_target(target, int(msg.start), window_cameras(target, labels, max_image_side), max_image_side)
            elif topic == TOPIC_METRICS:
                d = metrics_dict(data)
                log.metrics.append(d)
                residual[d["iteration"]] = d["residual"]
            elif topic == TOPIC_Z and tracker is not None:
                msg = schema.ZState.FromString(data)
                it = int(msg.iteration)
                if log.z_iterations and log.z_iterations[-1] == it:
                    continue  # the target's last state again, exact
                log.z_iterations.append(it)
                exact = np.frombuffer(msg.labels, "<i2") if msg.labels else None
                step = tracker.step(it, decode_z(msg), residual.get(it, float("nan")), labels=exact)
                rec.log_target_step(step, target, max_image_side, metrics=True)
            elif topic == TOPIC_TARGET_IMAGES:
                img = CompressedImage.FromString(data)
                images[img.frame_id] = decode_label_png(img.data, colors)
            elif topic == TOPIC_TARGET_ROWS:
                rows = json.loads(data)
                rec.log_target_rows(int(rows["step"]), int(rows["index"]), images, rows["rows"])
                for t in log.targets:
                    if t["index"] == rows["index"] and t["start"] == rows["start"]:
                        t.update(rows=rows["rows"], end=rows["step"], iterations=rows["iterations"])
                images = {}
    finally:
        rec.close()
    return log


def target_message(rec: TargetRecord, start: int) -> Any:
    """The ``diffuser_lab.TargetFrame`` of a target (``start``: its first step)."""
    h, w = rec.pixels.shape
    cams = [schema.Camera(name=name, width=int(shape[1]), height=int(shape[0]), K=np.ravel(K).tolist(),
                          T_cw=np.ravel(T).tolist()) for name, K, T, shape in rec.poses]
    return schema.TargetFrame(cameras=cams, index=rec.index, name=rec.name, count=rec.count, start=int(start),
                              window=[int(j) for j in rec.window], n_points=len(rec.work_points),
                              work_points=np.ascontiguousarray(rec.work_points, "<f4").tobytes(),
                              work_gt=np.ascontiguousarray(rec.work_gt, "<i2").tobytes(), width=int(w), height=int(h),
                              pixels=np.ascontiguousarray(rec.pixels, "<i4").tobytes(),
                              gt_image=np.ascontiguousarray(rec.gt_image, "<i2").tobytes(), method=rec.method,
                              views=int(rec.views))


def record_of_message(msg: Any) -> TargetRecord:
    """A :class:`TargetRecord` back from its ``diffuser_lab.TargetFrame`` (no cameras: they are on
    their own topics)."""
    h, w = int(msg.height), int(msg.width)
    poses = [(c.name, np.reshape(c.K, (3, 3)), np.reshape(c.T_cw, (4, 4)), (int(c.height), int(c.width)))
             for c in msg.cameras]
    return TargetRecord(index=int(msg.index), count=int(msg.count), name=msg.name, window=list(msg.window),
                        poses=poses, cameras=[], work_points=np.frombuffer(msg.work_points, "<f4").reshape(-1, 3),
                        work_gt=np.frombuffer(msg.work_gt, "<i2"),
                        pixels=np.frombuffer(msg.pixels, "<i4").reshape(h, w),
                        gt_image=np.frombuffer(msg.gt_image, "<i2").reshape(h, w), method=msg.method,
                        views=int(msg.views))


# -- run.rrd ---------------------------------------------------------------------------------------
def table_markdown(rows: Sequence[dict], index: int, count: int) -> str:
    """Table II so far as markdown: a row per method and views, pooled 2D mIoU, accuracy, mean
    frame mIoU and this frame's mIoU."""
    def f(x):
        return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{x:.1f}"

    lines = [f"**Table II so far** ({count} target frame{'s' if count != 1 else ''}, the last: frame {index})", "",
             "| method | views | 2D mIoU | acc | frame mean | this frame |", "| --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(f"| {r['method']} | {r['views']} | {f(r.get('miou'))} | {f(r.get('accuracy'))} | "
                     f"{f(r.get('mean_frame_miou'))} | {f(r.get('frame_miou'))} |")
    return "\n".join(lines)


def blueprint(eye=None, ranges: Optional[dict] = None, rows: Sequence[str] = ()):
    """The layout of a single-frame run: the target's work points (labels, confidence, errors, their
    ground truth, through the target's camera, the scene with the window's cameras) in tabs over
    the legend, beside the target frame's 2D labels (the Diffuser's at the current iteration, each
    Table II row's, the network's) and its ground truth, the frame's mIoU and accuracy per
    iteration with Table II's pooled mIoU so far, the table itself and the residual."""
    import rerun as rr
    import rerun.blueprint as rrb

    def view3d(name: str, contents: list[str], view_eye=eye, **kw):
        return rrb.Spatial3DView(name=name, origin="/world", contents=contents, **eye_kw(view_eye), **kw)

    dim = {"/world/diffusion/labels": rr.Points3D.from_fields(colors=RIGHT_RGB).visualizer()}
    tabs3d = rrb.Tabs(
        view3d("target: labels", ["/world/diffusion/labels", "/world/window/**", "/world/target/camera"]),
        view3d("through the target camera", ["/world/diffusion/labels", "/world/target/camera"],
               view_eye=follow_eye("/world/target/camera")),
        view3d("confidence", ["/world/diffusion/confidence"]),
        view3d("errors", ["/world/diffusion/labels", "/world/diffusion/wrong"], overrides=dim),
        view3d("ground truth", ["/world/target/ground_truth"]),
        view3d("scene + window", ["/world/scene/points", "/world/window/**", "/world/target/camera"]),
        active_tab="target: labels")
    images = rrb.Tabs(rrb.Spatial2DView(name="frame: Diffuser labels", origin="/target/diffuser"),
                      *[rrb.Spatial2DView(name=f"frame: {r}", origin=f"/target/rows/{r}") for r in rows],
                      rrb.Spatial2DView(name="frame: 2D input", origin="/target/prediction"),
                      active_tab="frame: Diffuser labels")
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(tabs3d, legend_view(), row_shares=[4, 1]),
            rrb.Vertical(
                rrb.Horizontal(images, rrb.Spatial2DView(name="frame: ground truth", origin="/target/ground_truth")),
                rrb.Horizontal(plot("this frame: 2D mIoU, accuracy [%]", ["/metrics/miou", "/metrics/accuracy"],
                                    ranges, legend=True),
                               plot("Table II so far: 2D mIoU [%]", ["/table/miou/**"], ranges, legend=True,
                                    origin="/table/miou")),
                rrb.Horizontal(rrb.TextDocumentView(name="Table II", origin="/table", contents=["/table"]),
                               plot("relative residual, log10", ["/metrics/residual_log10"], ranges)),
                row_shares=[3, 2, 2]),
            column_shares=[3, 2]),
        rrb.TimePanel(state="collapsed", timeline=TIMELINE, play_state="following"),
        collapse_panels=True)


class SingleFrameRerun(RerunRecorder):
    """run.rrd of a single-frame run: :class:`~.rerun_log.RerunRecorder` (scene, taxonomy, legend,
    scalars) with the targets' entities and the layout of its own (:func:`blueprint`)."""

    def __init__(self, path, **kw):
        super().__init__(path, application_id=APP_SINGLE_FRAME, **kw)
        self._sf_eye = None
        self._sf_rows: list[str] = []
        self._sf_present: Optional[np.ndarray] = None
        self._sf_count = 0

    def _send_batch_blueprint(self, T_cw: Optional[np.ndarray] = None) -> None:
        """(log_scene sends its kind's layout here) the single-frame layout, its eye over the scene."""
        pts = getattr(self, "_scene_points", None)
        self._sf_eye = overview_eye(pts) if pts is not None and len(pts) else None
        self._eye_up = scene_up(None)
        self.rec.send_blueprint(blueprint(self._sf_eye, rows=self._sf_rows), make_active=True, make_default=True)

    def log_single_frame_start(self, points: Optional[np.ndarray] = None) -> None:
        """The layout (the eye over the scene's ``points``), if the scene did not send it."""
        if self._eye_up is None:
            self._scene_points = points
            self._send_batch_blueprint()

    def close(self) -> None:
        if not self._closed and self._extent:  # the layout again with the plots' y ranges
            self.rec.send_blueprint(blueprint(self._sf_eye, ranges=self._extent, rows=self._sf_rows),
                                    make_active=True, make_default=True)
            self._extent = {}
        if self._eye_up is None:  # never the batch layout
            self._eye_up = scene_up(None)
        super().close()

    def _sf_time(self, step: int, index: int) -> None:
        self.rec.set_time(TIMELINE, sequence=int(step))
        self.rec.set_time(TARGET_TIMELINE, sequence=int(index))

    def log_target(self, rec: TargetRecord, start: int, cameras: Sequence[Any], max_side: int) -> None:
        """A target at its first step ``start``: its work points (unlabeled so far), their ground
        truth, its camera and window, its ground-truth and 2D-input images."""
        rr, log = self.rr, self.rec.log
        self._sf_time(start, rec.index)
        pts = rec.work_points
        r = point_radius(pts)
        self._work_radius, self._work_points = r, pts
        none = class_ids(np.full(len(pts), IGNORE, np.int16))
        log("world/diffusion/labels", rr.Points3D(pts, class_ids=none, radii=r))
        log("world/diffusion/confidence", confidence_context(),
            rr.Points3D(pts, class_ids=np.zeros(len(pts), np.uint16), radii=r))
        log("world/diffusion/wrong", rr.Points3D(np.zeros((0, 3), np.float32)))
        log("world/target/ground_truth", rr.Points3D(pts, class_ids=class_ids(rec.work_gt), radii=r))
        for j, cam in enumerate(cameras):
            T_wc = np.linalg.inv(np.asarray(cam.T_cw, np.float64))
            path = f"world/window/{j}"
            log(path, rr.Transform3D(translation=T_wc[:3, 3], mat3x3=T_wc[:3, :3]),
                rr.Pinhole(image_from_camera=cam.K, resolution=(cam.width, cam.height), image_plane_distance=0.2))
            if cam.labels is not None:
                log(f"{path}/labels", rr.SegmentationImage(class_ids(cam.labels)))
            if cam.index == rec.index:
                log("world/target/camera", rr.Transform3D(translation=T_wc[:3, 3], mat3x3=T_wc[:3, :3]),
                    rr.Pinhole(image_from_camera=cam.K, resolution=(cam.width, cam.height), image_plane_distance=0.2))
                if cam.labels is not None:
                    log("target/prediction", rr.SegmentationImage(class_ids(cam.labels)))
        gt, _ = strided(rec.gt_image, np.eye(3), max_side)
        log("target/ground_truth", rr.SegmentationImage(class_ids(gt)))
        log("target/diffuser", rr.SegmentationImage(class_ids(np.full(gt.shape, IGNORE, np.int16))))
        if self._sf_present is None:  # the legend: the classes of the scene's and the first target's ground truth
            self._sf_present = np.unique(np.concatenate([np.asarray(rec.work_gt).ravel(), gt.ravel()]))
            self.log_legend(self._sf_present)

    def log_target_step(self, step: Step, rec: TargetRecord, max_side: int, metrics: bool = True) -> None:
        """A recorded iteration of the target's diffusion (``step.iteration``: the global step):
        the labels and confidence of its work points, the wrong ones, its labels in the frame."""
        rr, log = self.rr, self.rec.log
        self._sf_time(step.iteration, rec.index)
        log("world/diffusion/labels", rr.Points3D.from_fields(class_ids=class_ids(step.labels)))
        q = np.minimum(np.multiply(step.confidence, CONFIDENCE_BINS, dtype=np.float32), CONFIDENCE_BINS - 1)
        log("world/diffusion/confidence", rr.Points3D.from_fields(class_ids=q.astype(np.uint16)))
        bad = (step.labels != rec.work_gt) & (rec.work_gt != IGNORE)
        log("world/diffusion/wrong", rr.Points3D(rec.work_points[bad], colors=self.wrong_rgb,
                                                 radii=1.2 * self._work_radius))
        pix, _ = strided(rec.pixels, np.eye(3), max_side)
        img = np.where(pix >= 0, step.labels[np.maximum(pix, 0)], IGNORE)
        log("target/diffuser", rr.SegmentationImage(class_ids(img)))
        if metrics:
            self.log_metrics(step.iteration, step.residual, step.n_changed, step.mean_confidence, step.miou,
                             step.accuracy, per=step.iteration - step.previous)

    def log_target_rows(self, step: int, index: int, images: dict, rows: Sequence[dict]) -> None:
        """A target scored, at ``step``: each row's label image of the frame, Table II so far (a
        markdown table and each row's pooled 2D mIoU)."""
        rr, log = self.rr, self.rec.log
        self._sf_time(step, index)
        for name, img in images.items():
            log(f"target/rows/{name}", rr.SegmentationImage(class_ids(img)))
        self._sf_count += 1
        log("table", rr.TextDocument(table_markdown(rows, index, self._sf_count), media_type=rr.MediaType.MARKDOWN))
        for r in rows:
            name = row_name(r["method"], r["views"])
            if r.get("miou") is not None and np.isfinite(r["miou"]):
                self._table_scalar(name, r["miou"])
        names = list(images)
        if names != self._sf_rows:  # the rows' tabs, once their names are known
            self._sf_rows = names
            self.rec.send_blueprint(blueprint(self._sf_eye, rows=names), make_active=True, make_default=True)

    def _table_scalar(self, name: str, value: float) -> None:
        v = float(value)
        self.rec.log(f"table/miou/{name}", self.rr.Scalars(v))
        e = self._extent.setdefault("/table/miou/**", [v, v])
        e[0], e[1] = min(e[0], v), max(e[1], v)



__all__ = ["SingleFrameHooks", "SingleFrameRecorder", "SingleFrameRerun", "TargetRecord", "Camera", "target_record",
           "target_message", "record_of_message", "blueprint", "table_markdown", "row_name", "TARGET_TIMELINE",
           "single_frame_meta", "summary_of", "is_single_frame", "replay", "target_tracker", "window_cameras"]
