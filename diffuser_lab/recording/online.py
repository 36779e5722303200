"""Records of an online run (protocol=online): :class:`OnlineHooks` is the run's side (the hooks
the online runner calls), :class:`OnlineRecorder` the writing side (in
:class:`~.recorders.Recorders`, on the recording thread or in the recording process).

The run calls ``on_online_frame(frame, update)`` after every frame it takes
(:class:`~diffuser_lab.runs.online.OnlineUpdate`: views valid during the call only and a
callable for Z). :func:`frame_record` turns that, in the caller's thread, into a
:class:`FrameRecord` of plain arrays that can wait in a queue or go through a pipe: the map's
new points only (a map only grows, and a given map never changes), the labels, the frame's
label image already strided to ``record.max_image_side``, and Z only on the frames the schedule
keeps (:func:`~.schedule.recorded` over the 1-based count of frames taken; the sequence's last
frame always, exact). :class:`MapMirror` rebuilds the map on the recorders' side from those.
"""
from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from diffuser_lab.backends.stats import StatsRequest
from diffuser_lab.config import OnlineMap
from diffuser_lab.data.scene import IGNORE
from diffuser_lab.method.diffusion import labels_from_scores
from diffuser_lab.runs.online import summary as online_summary

from .hooks import RecordingHooks
from .mcap_encode import FRAME_STEP_NS, strided
from .schedule import is_log_step, recorded, with_cloud
from .steps import metrics_rows, original_to_work

log = logging.getLogger("diffuser_lab.recording")

TIMELINE = "frame"
"""run.rrd's timeline of an online run: sequence = the frame's index; after the last frame taken
(index L) the finishing pass (``online.finish``): its step s at L + s."""
FINISH_TIMELINE = "finish_step"
"""run.rrd's timeline of an online run's finishing pass alone: sequence = its step."""


@dataclass
class FrameRecord:
    """One taken frame, as the recorders need it (plain arrays, picklable).

    Attributes:
        index: the frame's index in the sequence; count: 1-based count of frames taken so far.
        name: the frame's name. stats: :class:`~diffuser_lab.method.online.FrameStats` as a dict.
        metrics: ``update.metrics`` (mIoU so far etc., {} without ground truth).
        n: map points after the frame. new_points: (m, 3) float32 rows appended to the map
            (the whole map at the first frame), world metres. new_gt: (m,) int16 their ground
            truth (growing map with ground truth), or None.
        labels, bayesian: (n,) int16 online Diffuser / Bayesian labels, map order (IGNORE = none).
        Z: (n, C) float32 scores in the paper's units on the kept frames, else None.
        exact: Z is the run's last (kept float32); cloud: a labelled cloud goes into run.mcap.
        K, T_cw: (3, 3) intrinsics of the stored label image, (4, 4) world -> camera.
        width, height: of the stored label image. image: (h, w) int16 2D labels (strided) or None.
    """

    index: int
    count: int
    name: str
    stats: dict
    metrics: dict
    n: int
    new_points: Optional[np.ndarray]
    new_gt: Optional[np.ndarray]
    labels: np.ndarray
    bayesian: np.ndarray
    Z: Optional[np.ndarray]
    exact: bool
    cloud: bool
    K: np.ndarray
    T_cw: np.ndarray
    width: int
    height: int
    image: Optional[np.ndarray]


class FrameSchedule:
    """Which taken frames keep their Z state and a labelled cloud (``record.interval`` and
    ``record.clouds`` over the 1-based count of frames taken, ``n_frames`` the sequence's
    length: the first and the last always)."""

    def __init__(self, interval: Optional[int], clouds: str, n_frames: int):
        self.interval, self.clouds, self.n_frames = interval, clouds, int(n_frames)
        self.count = 0
        self.kept: list[int] = []  # frame indices whose Z was kept

    def next(self, index: int) -> tuple[int, bool, bool, bool]:
        """Count frame ``index`` as taken: (count, keep Z, Z exact, cloud)."""
        self.count += 1
        last = int(index) == self.n_frames - 1
        keep = last or recorded(self.count, self.interval, self.n_frames)
        cloud = keep and with_cloud(self.count, self.clouds, last)
        if keep:
            self.kept.append(int(index))
        return self.count, keep, last, cloud


def frame_record(frame: Any, update: Any, sched: FrameSchedule, max_image_side: int, n_before: int,
                 want_z: bool = True) -> FrameRecord:
    """A :class:`FrameRecord` of ``update`` (``n_before``: map points the recorders have)."""
    count, keep, last, cloud = sched.next(update.index)
    n = int(update.points.shape[0])
    new = np.array(update.points[n_before:], np.float32) if n > n_before else None
    gt = None
    if new is not None and update.gt is not None and len(update.gt) == n:
        gt = np.array(update.gt[n_before:], np.int16)
    h, w = frame.shape
    s = _stride(h, w, max_image_side)  # as run.rrd and run.mcap store label images (strided)
    K = strided(np.empty((h, w, 0), np.uint8), frame.K, max_image_side)[1]
    img = frame.labels
    if img is None and frame.probs is not None:  # soft labels: the argmax, of the strided probabilities only
        img = np.argmax(frame.probs[::s, ::s], axis=2)
    elif img is not None:
        img = np.asarray(img)[::s, ::s]
    img = None if img is None else np.array(img, np.int16)
    sh, sw = -(-h // s), -(-w // s)
    Z = np.asarray(update.scores(), np.float32) if keep and want_z else None
    return FrameRecord(index=int(update.index), count=count, name=str(frame.name),
                       stats=dataclasses.asdict(update.stats), metrics=dict(update.metrics), n=n,
                       new_points=new, new_gt=gt, labels=np.array(update.labels, np.int16),
                       bayesian=np.array(update.bayesian, np.int16), Z=Z, exact=last, cloud=cloud,
                       K=np.asarray(K, np.float64), T_cw=np.array(frame.T_cw, np.float64), width=int(sw),
                       height=int(sh), image=img)


class OnlineFrames:
    """The run's side of recording an online run (:class:`OnlineHooks`' state, whichever lane
    carries the records): the frame schedule, the map points already handed on, the last frame taken
    and its Z callable (for the final exact Z), and why recording stopped (``off``: the files keep
    what came before and close; ``files()`` reports it)."""

    def __init__(self, conf: Any, n_frames: int):
        rc = conf.record
        self.sched = FrameSchedule(None if rc.interval is None else int(rc.interval), rc.clouds.value, n_frames)
        self.max_image_side = int(rc.max_image_side)
        self.n_sent = 0  # map points already handed to the recorders
        self.last: Optional[tuple] = None  # (frame index, Z kept exactly, cloud) of the last frame taken
        self.last_scores = None  # the last update's Z callable
        self.off: Optional[str] = None

    def record(self, frame: Any, update: Any, want_z: bool) -> Optional[FrameRecord]:
        """The update's :class:`FrameRecord`, or None once recording failed (in the run's thread: a
        record never stops the run)."""
        if self.off is not None:
            return None
        try:
            rec = frame_record(frame, update, self.sched, self.max_image_side, self.n_sent, want_z)
        except Exception as exc:  # noqa: BLE001
            self.failed(exc)
            return None
        self.n_sent = rec.n
        self.last = (rec.index, rec.Z is not None and rec.exact, rec.cloud)
        self.last_scores = update.scores if want_z else None
        return rec

    def failed(self, exc: BaseException) -> None:
        self.off = f"recording the online run failed: {type(exc).__name__}: {exc}"
        log.warning("recording switched off: %s", self.off)

    def final_state(self, result: Any) -> Optional[tuple]:
        """(frame index, Z, labels, cloud) of the run's end where the last frame's record does not
        hold it exactly: its Z was not kept exactly (frames after it were skipped), or the finishing
        pass (``online.finish``) moved Z after it; else None. Z comes from the last update's
        callable (the final state once the run is over): the map does not change after the last frame."""
        if self.last is None or self.last_scores is None:
            return None
        index, exact, cloud = self.last
        finished = bool((getattr(result, "settings", None) or {}).get("finish", {}).get("steps"))
        if exact and not finished:
            return None
        return (index, np.asarray(self.last_scores(), np.float32), np.array(result.labels, np.int16),
                finished or not cloud)

    def finish(self, result: Any, final, summary) -> None:
        """Hand on the final exact Z (``final(index, Z, labels, cloud)``, where needed) and the run's
        summary (``summary(dict)``)."""
        if self.off is not None:
            return
        try:
            fin = self.final_state(result)
            if fin is not None:
                final(*fin)
            summary(online_summary(result))
        except Exception as exc:  # noqa: BLE001 - a record must never stop the run
            self.failed(exc)

    def errors(self, wanted) -> dict:
        """{recorder: why} for ``files()["errors"]`` once recording failed."""
        return {w: self.off for w in wanted} if self.off is not None else {}


class OnlineHooks(RecordingHooks):
    """An online run's hooks (protocol=online): per frame taken a :class:`FrameRecord` (made in
    the run's thread by :class:`OnlineFrames`), at the end the last frame's exact Z and the
    run's summary. A frame's ``on_frame`` call is not recorded: it comes again with its update."""

    def __init__(self, conf: Any, lane: Any):
        super().__init__(conf, lane)
        self.frames: Optional[OnlineFrames] = None
        self._update: Any = None  # the last frame's update: the map the finishing pass runs on

    # -- the finishing pass (online.finish), observed as a diffusion: run.rrd's frame timeline
    # goes on after the last frame, one step a value (OnlineRecorder.finish_*)
    def statistics(self) -> Optional[StatsRequest]:
        """Every finishing step's statistics (run.rrd's plots), against the map's ground truth
        (growing) or the scene's through each point's nearest map point (given), as per frame."""
        u = self._update
        if u is None or not self.lane.live("rerun") or (self.frames is not None and self.frames.off):
            return None
        if u.gt is not None:  # growing map with ground truth: the map's points'
            return StatsRequest(np.asarray(u.gt), None)
        gt = getattr(self.scene, "gt_labels", None)
        if gt is None or self.conf.online.map == OnlineMap.growing:
            return StatsRequest(None, None)
        return StatsRequest(gt, original_to_work(np.asarray(u.points), self.scene.points))

    def on_statistics(self, table: Any) -> None:
        if self.lane.live("rerun"):
            self.lane.send("online.finish_metrics", metrics_rows(table))

    def wants(self, iteration: int) -> bool:
        return self._update is not None and self.lane.live("rerun") and is_log_step(iteration)

    def observe(self, iteration: int, Z: np.ndarray, stats: dict) -> None:
        self.lane.send("online.finish_labels", int(iteration), labels_from_scores(Z))

    def on_scene(self, scene: Any) -> None:
        super().on_scene(scene)
        self.start(scene)

    def start(self, scene: Any) -> None:
        """The per-frame records begin (the scene's frames give the schedule's length)."""
        self.frames = OnlineFrames(self.conf, len(scene.frames))
        self.lane.send("online.start")

    def on_online_frame(self, frame: Any, update: Any) -> None:
        if not self.recording():
            return
        rec = self.frames.record(frame, update, want_z=self.lane.live("mcap"))
        if rec is not None:
            self.lane.send("online.frame", rec)
            self._update = update

    def on_result(self, result: Any) -> None:
        if self.lane.dead is None and self.frames is not None:
            steps = int(((getattr(result, "settings", None) or {}).get("finish") or {}).get("steps") or 0)
            if steps and self.lane.live("rerun") and not self.frames.off:  # the replay ends on labels.npy's
                self.lane.send("online.finish_end", steps, np.array(result.labels, np.int16))
            self.frames.finish(result, lambda *fin: self.lane.send("online.final", *fin),
                               lambda summary: self.lane.send("online.result", summary))
        self._update = None

    def files(self) -> dict:
        out = self.lane.files()
        # the writing side's errors, and this side's when it stopped sending (an online frame failed)
        errors = {**(self.frames.errors(self.lane.wanted) if self.frames is not None else {}), **out.pop("errors", {})}
        if errors:
            out["errors"] = errors
        return out


class OnlineRecorder:
    """The writing side of an online run's records, on the recorders ``recs``
    (:class:`~.recorders.Recorders`): the map rebuilt from the frame records
    (:class:`MapMirror`) and each frame to both recorders."""

    def __init__(self, recs: Any):
        self.recs = recs
        self.mirror: Optional[MapMirror] = None
        self.last_index = -1  # the last frame taken: the finishing pass's steps follow it on the timeline

    def start(self) -> None:
        r = self.recs
        scene = r.scene
        growing = r.conf.online.map == OnlineMap.growing
        meta = online_meta(r.conf, scene)
        self.mirror = MapMirror(growing, scene.points, scene.gt_labels)
        spacing = float(r.conf.online.voxel_size) or None
        budget = 1000.0 / r.conf.online.rate if r.conf.online.rate > 0 else None
        r.each(lambda: r.rerun.log_online_start(scene.gt_labels is not None, growing, scene.points, spacing, budget),
               lambda: r.mcap.log_online_start(meta))

    def frame(self, rec: FrameRecord) -> None:
        r = self.recs
        changed = self.mirror.update(rec)
        pts = self.mirror.points
        r.each(lambda: r.rerun.log_online_frame(rec, self.mirror, changed), lambda: r.mcap.log_online_frame(rec, pts))
        self.last_index = rec.index
        if rec.Z is not None:
            r.recorded.append(rec.index)

    def finish_metrics(self, rows: np.ndarray) -> None:
        """The finishing pass's scalars, (k, 6) rows as :func:`~.steps.metrics_rows` (step of the pass, ...)."""
        r = self.recs
        r.each(lambda: r.rerun.log_online_finish_metrics(self.last_index, rows), None)

    def finish_labels(self, step: int, labels: np.ndarray) -> None:
        """The map's (n,) labels after step ``step`` of the finishing pass (its 1-2-5 steps)."""
        r = self.recs
        r.each(lambda: r.rerun.log_online_labels(self.last_index, step, labels, self.mirror), None)

    def finish_end(self, steps: int, labels: np.ndarray) -> None:
        """The run's final labels (labels.npy's, map order) at the pass's last step ``steps``."""
        self.finish_labels(steps, labels)

    def final(self, index: int, Z: np.ndarray, labels: np.ndarray, cloud: bool) -> None:
        """The run's end (:meth:`OnlineFrames.final_state`): its Z exactly, at the last frame taken."""
        r = self.recs
        if r.mcap is not None:
            pts = self.mirror.points
            r.guard("mcap", lambda: r.mcap.log_online_final(index, Z, labels, pts, cloud))
        if not r.recorded or r.recorded[-1] != index:
            r.recorded.append(index)

    def result(self, summary: dict) -> None:
        """The run's summary (:func:`diffuser_lab.runs.online.summary`) into run.mcap."""
        r = self.recs
        if r.mcap is not None:
            s = {**summary, "records": r.files(), "recorded_frames": list(r.recorded)}
            r.guard("mcap", lambda: r.mcap.log_summary(s))


def _stride(h: int, w: int, max_side: int) -> int:
    return max(1, int(np.ceil(max(h, w) / max_side)))


class MapMirror:
    """The map as the recorders see it, rebuilt from :class:`FrameRecord` s.

    Attributes:
        points: (n, 3) float32 map points (map order); gt: (n,) int16 their ground truth or None.
        to_map: given map with scene ground truth: (N,) index of each scene point's map row
            (nearest map point, as the batch recorder transfers), else None.
    """

    def __init__(self, growing: bool, scene_points: Optional[np.ndarray], scene_gt: Optional[np.ndarray]):
        self.growing = growing
        self.scene_points, self.scene_gt = scene_points, scene_gt
        self.points = np.zeros((0, 3), np.float32)
        self.gt: Optional[np.ndarray] = None
        self.to_map: Optional[np.ndarray] = None

    def update(self, rec: FrameRecord) -> bool:
        """Append the record's new points; True when the map changed."""
        if rec.new_points is None:
            return False
        self.points = rec.new_points if not len(self.points) else np.concatenate([self.points, rec.new_points])
        if rec.new_gt is not None:
            self.gt = rec.new_gt if self.gt is None else np.concatenate([self.gt, rec.new_gt])
        if not self.growing and self.scene_gt is not None and self.scene_points is not None:
            self.to_map = original_to_work(self.points, self.scene_points)
        return True

    def wrong(self, labels: np.ndarray) -> Optional[np.ndarray]:
        """(P, 3) positions of annotated, labelled points whose label is wrong (growing: map
        points; given: the scene's points through :attr:`to_map`), or None without ground truth.
        Points no frame has reached yet are left out: they are not yet wrong (mIoU counts them
        as misses)."""
        if self.to_map is not None:
            lab = labels[self.to_map]
            bad = (lab != self.scene_gt) & (self.scene_gt != IGNORE) & (lab != IGNORE)
            return self.scene_points[bad]
        if self.gt is not None and len(self.gt) == len(labels):
            bad = (labels != self.gt) & (self.gt != IGNORE) & (labels != IGNORE)
            return self.points[bad]
        return None


def online_meta(conf: Any, scene: Any) -> dict:
    """What run.mcap's ``diffuser_lab.online`` metadata record says (strings)."""
    rc = conf.record
    return {"map": conf.online.map.value, "n_frames": str(len(scene.frames)),
            "interval": json.dumps(rc.interval), "z_dtype": rc.z_precision.value, "clouds": rc.clouds.value,
            "has_gt": json.dumps(scene.gt_labels is not None), "frame_step_ns": str(FRAME_STEP_NS)}


def is_online(conf: Any) -> bool:
    return conf.protocol.name == "online"


__all__ = ["OnlineHooks", "OnlineRecorder", "FrameRecord", "FrameSchedule", "OnlineFrames", "MapMirror", "frame_record",
           "online_meta", "is_online", "FRAME_STEP_NS", "TIMELINE"]
