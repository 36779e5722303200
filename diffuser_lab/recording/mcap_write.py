"""Writing run.mcap: the diffusion as MCAP (lz4 chunks by default, protobuf messages with their schemas inside).

Channels (message encoding ``protobuf``; schemas in :mod:`diffuser_lab.recording.schema`)::

    /scene/points        foxglove.PointCloud, once: input cloud (x y z float32, red green blue alpha
                         uint8 = input colours, else ground-truth colours, label int16 = ground truth)
    /evidence/bayesian   foxglove.PointCloud, once: work cloud coloured by Bayesian labels
    /diffuser_lab/run    diffuser_lab.RunInfo, once: taxonomy, work cloud, cameras
    /diffusion/labels    foxglove.PointCloud, per recorded iteration: work cloud coloured by label
                         (fields as above, label = the iteration's class ids)
    /diffuser_lab/metrics  diffuser_lab.IterationMetrics, per recorded iteration
    /diffuser_lab/z      diffuser_lab.ZState, per recorded iteration: the full (M, C) Z, stored
                         class-major (Z transposed: it compresses ~25% better; decode_z undoes it)
    /tf                  foxglove.FrameTransform, per camera: world -> camera_<i> (its pose)
    /cameras/calibration foxglove.CameraCalibration, per camera (frame camera_<i>), of the image stored
    /cameras/labels      foxglove.CompressedImage, per camera: the 2D label image as a palette PNG
                         (pixel = class id, 255 = unlabeled; palette = taxonomy colours), strided
                         to ``record.max_image_side`` like run.rrd's

One topic per kind and one message per camera, at successive times: Foxglove's Image and 3D
panels show one frame at a time and playing the file sweeps through them, while every camera
frame stays in the transform tree.

Metadata records: ``diffuser_lab.config`` (``yaml``: the resolved config, ``overrides``: JSON list),
``diffuser_lab.run`` (scene, method, sizes, taxonomy as JSON), ``diffuser_lab.provenance`` (JSON
texts ``provenance``: machine, versions, commit, and ``inputs``: at the start the config's hash; once
the files are written again with ``inputs`` and ``outputs`` as summary.json has them) and, once the
run has finished, ``diffuser_lab.summary`` (``json``: the summary.json content).

Each recorded iteration ends its chunk and flushes the file, so a run that is killed leaves
every completed iteration readable (:func:`.mcap_read.read_run` reads such a truncated file).
Compression and writing happen on one background thread (in order, a short bounded queue), so
the diffusion does not wait for the compression; :meth:`McapRecorder.close` drains it. The file is written
with ``O_DIRECT`` where the file system allows (:mod:`.direct_file`): no page-cache copies.
An online run (protocol=online, docs/reference/records.md "Online runs") has no /evidence/bayesian,
/diffuser_lab/run, /diffusion/labels or /diffuser_lab/metrics; per frame taken instead:
``/diffuser_lab/online/frame`` (diffuser_lab.OnlineFrame), the camera on /tf,
/cameras/calibration and /cameras/labels, and on the frames the schedule keeps the map's Z on
/diffuser_lab/z (``iteration`` = the frame's index) and ``/online/labels`` (foxglove.PointCloud of
the map, coloured by label); metadata ``diffuser_lab.online``. Frame i is at the run's start +
(i + 1) x 100 ms, each frame flushed as it comes.

Message ``sequence`` is the diffusion iteration; ``log_time`` (= ``publish_time`` = the foxglove
messages' ``timestamp``) is :func:`log_time_ns`, a timeline that orders the messages by camera and
by iteration (Foxglove's playback, Rerun's ``message_log_time``).
"""
from __future__ import annotations

import functools
import json
import queue
import time
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from diffuser_lab import __version__

from . import schema
from .direct_file import open_direct
from .mcap_encode import (
    FRAME_STEP_NS,
    TOPIC_CALIBRATION,
    TOPIC_CAMERA_LABELS,
    TOPIC_EVIDENCE,
    TOPIC_FEATURE_VIEW,
    TOPIC_FEATURES,
    TOPIC_LABELS,
    TOPIC_METRICS,
    TOPIC_ONLINE_FRAME,
    TOPIC_ONLINE_LABELS,
    TOPIC_RUN,
    TOPIC_SCENE,
    TOPIC_TARGET,
    TOPIC_TARGET_IMAGES,
    TOPIC_TARGET_ROWS,
    TOPIC_TF,
    TOPIC_TILED_LABELS,
    TOPIC_TILED_RECORDS,
    TOPIC_TILED_TILES,
    TOPIC_Z,
    RawMessage,
    camera_messages,
    label_png,
    packed_cloud,
    point_cloud,
    point_cloud_bytes,
    z_state_bytes,
)
from .schedule import with_cloud
from .serial import SerialThread
from .steps import Step

WRITER_THREAD = True
"""Compress and write on a background thread (False: in the caller's thread)."""
COMPRESSION = "lz4"
"""Default compression of run.mcap's chunks (``record.compression``): lz4, zstd (mcap's level 3)
or none. Float32 Z is mostly mantissa noise and compresses little; compressing it is most of the
cost of recording. Measured on one 51k x 20 demo Z state (4 MB, 30 iterations): zstd 8.0 ms ->
0.46x, lz4 2.4 ms -> 0.50x (see docs/reference/records.md)."""
FOXGLOVE_LAYOUT = Path(__file__).with_name("foxglove_layout.json")
"""A Foxglove layout for run.mcap (Layouts > Import from file): the labelled cloud and the camera
frames in a 3D panel, the label images in an Image panel, mIoU / labels changed / residual
plotted against the iteration (``diffuser-lab-inspect RUN --foxglove-layout OUT.json`` copies it)."""
_ONLINE_LAYOUT = (  # FOXGLOVE_LAYOUT's topics and fields -> an online run's
    ('"/diffusion/labels"', '"/online/labels"'), ('"diffusion: labels + cameras"', '"online: map labels + camera"'),
    ('"/diffuser_lab/metrics.miou"', '"/diffuser_lab/online/frame.diffuser_miou"'),
    ('"mIoU [%]"', '"online Diffuser mIoU [%]"'),
    ('"/diffuser_lab/metrics.accuracy"', '"/diffuser_lab/online/frame.bayesian_miou"'),
    ('"accuracy [%]"', '"online Bayesian mIoU [%]"'),
    ('"/diffuser_lab/metrics.n_changed"', '"/diffuser_lab/online/frame.changed"'),
    ('"/diffuser_lab/metrics.residual"', '"/diffuser_lab/online/frame.latency_ms"'),
    ('"relative residual |Z_t - Z_t-1|"', '"latency [ms]"'), ('"residual"', '"latency [ms]"'),
    ('"/diffuser_lab/metrics.iteration"', '"/diffuser_lab/online/frame.index"'), ('"iteration"', '"frame"'),
)


def online_foxglove_layout() -> str:
    """FOXGLOVE_LAYOUT for an online run's run.mcap (JSON text): the map cloud (/online/labels,
    on the kept ``record.clouds`` frames), the camera and its label images, and mIoU so far,
    labels changed and latency plotted against the frame index."""
    text = FOXGLOVE_LAYOUT.read_text()
    for old, new in _ONLINE_LAYOUT:
        text = text.replace(old, new)
    return text


CAMERA_STEP_NS = 50_000_000
"""run.mcap's timeline: 50 ms from one camera to the next."""
ITERATION_STEP_NS = 10_000_000
"""run.mcap's timeline: 10 ms per diffusion iteration."""


def log_time_ns(start_ns: int, kind: str, index: int = 0, n_cameras: int = 0) -> int:
    """The log time of a run.mcap message, ns since the epoch (``start_ns``: the run's start,
    a whole second). ``kind``:

    - ``"scene"``: start;
    - ``"camera"``: camera ``index`` at start + (index + 1) x 50 ms;
    - ``"evidence"`` (RunInfo, the evidence cloud): start + (n_cameras + 1) x 50 ms;
    - ``"iteration"``: iteration ``index`` at D + index x 10 ms, D the evidence's time rounded
      up to a whole second (so iteration = 100 x the seconds since D).
    """
    evidence = start_ns + (int(n_cameras) + 1) * CAMERA_STEP_NS
    if kind == "scene":
        return start_ns
    if kind == "camera":
        return start_ns + (int(index) + 1) * CAMERA_STEP_NS
    if kind == "evidence":
        return evidence
    if kind == "iteration":
        return -(-evidence // 10**9) * 10**9 + int(index) * ITERATION_STEP_NS
    raise ValueError(f"log_time_ns: unknown kind {kind!r}")


class McapRecorder:
    """Writes run.mcap as the run goes (see the module doc). ``writer_thread``: compress and
    write on a thread of its own (default :data:`WRITER_THREAD`); False when the caller records
    on a background thread already (:mod:`diffuser_lab.recording`)."""

    file_key = "mcap"

    def __init__(self, path: Path, *, z_dtype: str = "q8", config_yaml: str = "",
                 overrides: Sequence[str] = (), interval: Optional[int] = None, max_iter: int = 0,
                 compression: str = COMPRESSION, writer_thread: bool | None = None, clouds: str = "decades",
                 max_image_side: int = 320):
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)
        self.z_dtype = z_dtype
        self.interval, self.max_iter = interval, int(max_iter)  # interval None: the 1-2-5 log schedule
        self.clouds = clouds
        self.max_image_side = int(max_image_side)  # the label images are strided to this
        self._start = time.time_ns() // 10**9 * 10**9  # the timeline's origin (log_time_ns)
        self._fh = open_direct(self.path)  # O_DIRECT where possible: no page-cache copies
        # no CRCs: on 4 MB Z chunks crc32 costs half as much as compressing them; records keep
        # their lengths, so a cut file is still read up to its last complete chunk
        kinds = {"lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD, "none": CompressionType.NONE}
        if compression not in kinds:
            raise ValueError(f"record.compression={compression}: expected one of {', '.join(kinds)}")
        self.w = Writer(self._fh, compression=kinds[compression], enable_crcs=False)
        self.w.start(profile="", library=f"diffuser-lab {__version__}")
        from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
        from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
        from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
        from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

        self._channels: dict[str, int] = {}
        self._schema_ids: dict[str, int] = {}
        for topic, cls in ((TOPIC_SCENE, PointCloud), (TOPIC_EVIDENCE, PointCloud), (TOPIC_RUN, schema.RunInfo),
                           (TOPIC_LABELS, PointCloud), (TOPIC_METRICS, schema.IterationMetrics),
                           (TOPIC_Z, schema.ZState), (TOPIC_TF, FrameTransform),
                           (TOPIC_CALIBRATION, CameraCalibration), (TOPIC_CAMERA_LABELS, CompressedImage)):
            sid = self._schema(cls)
            self._channels[topic] = self.w.register_channel(topic=topic, message_encoding="protobuf", schema_id=sid)
        self.w.add_metadata("diffuser_lab.config", {"yaml": config_yaml, "overrides": json.dumps(list(overrides))})
        self._cameras: list[Any] = []
        self._camera_slots = 0  # 1 + the largest camera index logged: the evidence comes after
        self._labels_buf: Optional[np.ndarray] = None
        self._rgba: Optional[np.ndarray] = None  # (C + 1,) colours packed as the cloud's 4 rgba bytes
        self._colors: Optional[np.ndarray] = None  # (C, 3) uint8 taxonomy colours (label images)
        # per-iteration message buffers, reused once the writer has copied them (a fresh 4 MB
        # buffer per recorded iteration costs more in page faults than the copy itself)
        self._free: dict[str, queue.SimpleQueue] = {TOPIC_LABELS: queue.SimpleQueue(), TOPIC_Z: queue.SimpleQueue(),
                                                     TOPIC_ONLINE_LABELS: queue.SimpleQueue()}
        self._closed = False
        self._clouded = False  # the last recorded iteration got its labelled cloud
        # the writer thread, when there is one, is the only user of self.w from here on
        self._writer: Optional[SerialThread] = None
        if WRITER_THREAD if writer_thread is None else writer_thread:
            self._writer = SerialThread("diffuser-lab-mcap", 32, stop_on_error=True)  # ~8 iterations queued

    @property
    def _error(self) -> Optional[BaseException]:
        return None if self._writer is None else self._writer.error

    def _submit(self, fn, *args) -> None:
        if self._error is not None:
            raise RuntimeError(f"writing {self.path.name} failed: {self._error}") from self._error
        if self._writer is None:
            fn(*args)
        else:
            self._writer.submit(fn, *args)

    def _add(self, topic: str, msg: Any, sequence: int, t: int) -> None:
        self.w.add_message(self._channels[topic], log_time=t, publish_time=t, sequence=sequence,
                           data=msg.SerializeToString())
        if getattr(msg, "done", None) is not None:
            msg.done()

    def _schema(self, cls) -> int:
        name = cls.DESCRIPTOR.full_name
        if name not in self._schema_ids:
            self._schema_ids[name] = self.w.register_schema(name=name, encoding="protobuf",
                                                            data=schema.file_descriptor_set(cls))
        return self._schema_ids[name]

    def _write(self, topic: str, msg: Any, sequence: int = 0, t: Optional[int] = None) -> None:
        """Queue ``msg`` (which must not change afterwards) for the writer thread, at log time
        ``t`` (default: that of iteration ``sequence``, :meth:`_time`)."""
        t = self._time("iteration", sequence) if t is None else int(t)
        self._submit(self._add, topic, msg, int(sequence), t)

    def _time(self, kind: str, index: int = 0) -> int:
        return log_time_ns(self._start, kind, index, self._camera_slots)

    def _flush(self) -> None:
        self._submit(self.w.flush)

    def _paint(self, buf: np.ndarray, labels: np.ndarray) -> None:
        """Colour the cloud ``buf`` by ``labels`` (taxonomy colours, IGNORE grey) and store them
        as its label field."""
        rgba = buf.view(np.dtype({"names": ["rgba"], "formats": ["<u4"], "offsets": [12],
                                  "itemsize": buf.dtype.itemsize}))
        rgba["rgba"] = self._rgba[labels]  # red green blue alpha at offsets 12-15
        buf["label"] = labels

    # -- static ----------------------------------------------------------------------------
    def log_scene(self, scene: Any) -> None:
        tax = scene.taxonomy
        self._colors = np.asarray(tax.colors, np.uint8)
        colors = np.vstack([tax.colors, np.array([[70, 70, 70]], np.uint8)])  # last: unlabeled
        rgba = np.concatenate([colors, np.full((len(colors), 1), 255, np.uint8)], 1)
        self._rgba = np.ascontiguousarray(rgba).view("<u4").ravel()  # index -1 (IGNORE): unlabeled
        gt = scene.gt_labels
        self._submit(self.w.add_metadata, "diffuser_lab.run", {
            "scene": scene.name, "n_points": str(scene.n_points), "taxonomy": tax.name,
            "class_names": json.dumps(list(tax.names)), "class_colors": json.dumps(tax.colors.tolist()),
            "has_colors": json.dumps(scene.colors is not None), "has_gt": json.dumps(gt is not None)})
        buf = packed_cloud(scene.points)
        if gt is not None:
            self._paint(buf, gt)
        if scene.colors is not None:  # input colours win over the ground truth's
            buf["red"], buf["green"], buf["blue"] = scene.colors[:, 0], scene.colors[:, 1], scene.colors[:, 2]
        elif gt is None:
            buf["red"] = buf["green"] = buf["blue"] = 160
        t = self._time("scene")
        self._write(TOPIC_SCENE, point_cloud(buf, t), t=t)

    def log_camera(self, index: int, frame: Any) -> None:
        """Frame ``index``: its camera in RunInfo (full size) and its foxglove messages (pose,
        calibration, label image: :func:`.mcap_encode.camera_messages`) at the camera's time."""
        h, w = frame.shape
        self._cameras.append(schema.Camera(name=str(frame.name), width=int(w), height=int(h),
                                           K=np.asarray(frame.K, float).ravel().tolist(),
                                           T_cw=np.asarray(frame.T_cw, float).ravel().tolist()))
        labels = frame.labels
        if labels is None and frame.probs is not None:  # soft labels: their argmax, as run.rrd
            labels = np.argmax(frame.probs, axis=2)
        t = self._time("camera", index)
        self._camera_slots = max(self._camera_slots, int(index) + 1)
        for topic, msg in camera_messages(index, frame.K, frame.T_cw, (h, w), labels, self._colors,
                                          self.max_image_side, t):
            self._write(topic, msg, index, t)

    def log_evidence(self, scene: Any, method: str, work_points: np.ndarray, to_work: Optional[np.ndarray],
                     seen: np.ndarray, bayesian: np.ndarray) -> None:
        tax = scene.taxonomy
        m = len(work_points)
        info = schema.RunInfo(scene=scene.name, method=method, taxonomy=tax.name, class_names=list(tax.names),
                              class_colors=np.asarray(tax.colors, np.uint8).tobytes(), n_points=scene.n_points,
                              n_work_points=m,
                              # the scene's own points (no voxel grid): /scene/points holds them already
                              work_points=b"" if to_work is None and m == scene.n_points
                              else np.ascontiguousarray(work_points, "<f4").tobytes(),
                              original_to_work=b"" if to_work is None else to_work.astype("<i4").tobytes(),
                              bayesian_labels=np.asarray(bayesian, "<i2").tobytes(),
                              seen=np.asarray(seen, np.uint8).tobytes(), interval=self.interval or 0,
                              max_iter=self.max_iter, z_dtype=self.z_dtype)
        info.cameras.extend(self._cameras)
        t = self._time("evidence")
        self._write(TOPIC_RUN, info, t=t)
        buf = packed_cloud(work_points)
        self._paint(buf, bayesian)
        self._write(TOPIC_EVIDENCE, point_cloud(buf, t), t=t)
        self._labels_buf = packed_cloud(work_points)  # the per-iteration cloud: positions filled once
        self._flush()

    # -- per iteration ------------------------------------------------------------------------
    def log_step(self, step: Step, final: bool = False) -> None:
        """One recorded iteration: metrics, Z (``final``: float32, exact; else ``z_dtype`` with
        the exact labels beside it) and, on :func:`.schedule.with_cloud` iterations, the
        labelled cloud."""
        nan = float("nan")
        self._write(TOPIC_METRICS, schema.IterationMetrics(
            iteration=step.iteration, residual=step.residual, n_changed=step.n_changed,
            previous_iteration=step.previous, miou=nan if step.miou is None else step.miou,
            accuracy=nan if step.accuracy is None else step.accuracy, coverage=step.coverage,
            mean_confidence=step.mean_confidence), step.iteration)
        self._clouded = self._labels_buf is not None and with_cloud(step.iteration, self.clouds, final)
        if self._clouded:
            self._write_cloud(step)
        self._write_z(step, final)
        self._flush()  # ends the chunk: a killed run keeps this iteration

    def log_final(self, step: Step) -> None:
        """The run ended on an iteration already recorded (converged there): write its Z again,
        exact, and its cloud if it had none. Readers take the later copy."""
        if not self._clouded and self._labels_buf is not None:
            self._write_cloud(step)
        self._write_z(step, True)
        self._flush()

    def _write_cloud(self, step: Step) -> None:
        buf = self._labels_buf
        self._paint(buf, step.labels)
        stamp = self._time("iteration", step.iteration)  # the message's timestamp: its log time
        self._write_pooled(TOPIC_LABELS, point_cloud_bytes(buf, stamp, self._pooled(TOPIC_LABELS)), step.iteration)

    def _write_z(self, step: Step, final: bool) -> None:
        dtype = "float32" if final else self.z_dtype
        self._write_pooled(TOPIC_Z, z_state_bytes(step.iteration, step.Z, dtype, self._pooled(TOPIC_Z),
                                                  labels=step.labels), step.iteration)

    def _pooled(self, topic: str) -> Optional[bytearray]:
        try:
            return self._free[topic].get_nowait()
        except queue.Empty:
            return None

    def _write_pooled(self, topic: str, mv: memoryview, sequence: int) -> None:
        """Queue a serialized message whose buffer returns to ``topic``'s pool once written."""
        self._write(topic, RawMessage(mv, functools.partial(self._free[topic].put, mv.obj)), sequence)

    # -- a features run (predictions=features) ------------------------------------------------------
    def log_feature_view(self, view: Any) -> None:
        """A features run's projection (:class:`~.features.FeatureView`), once, at the evidence's
        time; registers the features topics."""
        msg = schema.FeatureView(dim=view.dim, basis=np.asarray(view.basis, "<f4").tobytes(),
                                 mean=np.asarray(view.mean, "<f4").tobytes(), lo=np.asarray(view.lo, "<f4").tobytes(),
                                 hi=np.asarray(view.hi, "<f4").tobytes(), query=view.query,
                                 embedding=np.asarray(view.embedding, "<f4").tobytes(), sim_lo=float(view.sim_lo),
                                 sim_hi=float(view.sim_hi), n_fit=int(view.n_fit))

        def start():
            for topic, cls in ((TOPIC_FEATURE_VIEW, schema.FeatureView), (TOPIC_FEATURES, schema.FeatureColors)):
                self._channels[topic] = self.w.register_channel(topic=topic, message_encoding="protobuf",
                                                                schema_id=self._schema(cls))

        self._submit(start)
        self._write(TOPIC_FEATURE_VIEW, msg, t=self._time("evidence"))

    def log_features(self, iteration: int, rgb: np.ndarray, sim: np.ndarray) -> None:
        """One recorded iteration's (M, 3) uint8 RGB projection and (M,) uint8 query similarity."""
        msg = schema.FeatureColors(iteration=int(iteration), n_points=len(sim),
                                   rgb=np.ascontiguousarray(rgb, np.uint8).tobytes(),
                                   similarity=np.ascontiguousarray(sim, np.uint8).tobytes())
        self._write(TOPIC_FEATURES, msg, int(iteration))

    # -- protocol=online ------------------------------------------------------------------------
    def log_online_start(self, meta: dict) -> None:
        """An online run: its channels and the ``diffuser_lab.online`` metadata (:func:`.online.online_meta`)."""
        from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

        def start():
            for topic, cls in ((TOPIC_ONLINE_FRAME, schema.OnlineFrame), (TOPIC_ONLINE_LABELS, PointCloud)):
                self._channels[topic] = self.w.register_channel(topic=topic, message_encoding="protobuf",
                                                                schema_id=self._schema(cls))
            self.w.add_metadata("diffuser_lab.online", meta)

        self._submit(start)  # on the writer thread, before the frames' messages

    def _frame_time(self, index: int) -> int:
        return self._start + (int(index) + 1) * FRAME_STEP_NS

    def log_online_frame(self, rec: Any, points: np.ndarray) -> None:
        """One frame taken (:class:`.online.FrameRecord`); ``points`` (n, 3) the map after it."""
        i = rec.index
        t = self._frame_time(i)
        for topic, msg in camera_messages(i, rec.K, rec.T_cw, (rec.height, rec.width), rec.image, self._colors,
                                          self.max_image_side, t):
            self._write(topic, msg, i, t)
        self._write(TOPIC_ONLINE_FRAME, online_frame_message(rec, "" if rec.Z is None else
                                                            ("float32" if rec.exact else self.z_dtype)), i, t)
        if rec.cloud:
            self._online_cloud(i, points, rec.labels, t)
        if rec.Z is not None:
            self._online_z(i, rec.Z, rec.labels, rec.exact, t)
        self._flush()  # ends the chunk: a killed run keeps this frame

    def log_online_final(self, index: int, Z: np.ndarray, labels: np.ndarray, points: np.ndarray,
                         cloud: bool) -> None:
        """The run's end at the last frame taken (frames after it skipped, or the finishing pass
        after it): its Z again, exact (readers take the later copy), and its cloud if asked."""
        t = self._frame_time(index)
        if cloud:
            self._online_cloud(index, points, labels, t)
        self._online_z(index, Z, labels, True, t)
        self._flush()

    def _online_cloud(self, index: int, points: np.ndarray, labels: np.ndarray, t: int) -> None:
        buf = packed_cloud(points)
        self._paint(buf, labels)
        mv = point_cloud_bytes(buf, t, self._pooled(TOPIC_ONLINE_LABELS))
        self._write(TOPIC_ONLINE_LABELS, RawMessage(mv, functools.partial(self._free[TOPIC_ONLINE_LABELS].put, mv.obj)),
                    index, t)

    def _online_z(self, index: int, Z: np.ndarray, labels: np.ndarray, exact: bool, t: int) -> None:
        dtype = "float32" if exact else self.z_dtype
        mv = z_state_bytes(index, Z, dtype, self._pooled(TOPIC_Z), labels=labels)
        self._write(TOPIC_Z, RawMessage(mv, functools.partial(self._free[TOPIC_Z].put, mv.obj)), index, t)

    # -- protocol=single_frame -------------------------------------------------------------------
    def log_single_frame_start(self, meta: dict) -> None:
        """A single-frame run: its channels and the ``diffuser_lab.single_frame`` metadata (JSON)."""
        from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

        def start():
            for topic, cls in ((TOPIC_TARGET, schema.TargetFrame), (TOPIC_TARGET_IMAGES, CompressedImage)):
                self._channels[topic] = self.w.register_channel(topic=topic, message_encoding="protobuf",
                                                                schema_id=self._schema(cls))
            self._channels[TOPIC_TARGET_ROWS] = self.w.register_channel(topic=TOPIC_TARGET_ROWS,
                                                                        message_encoding="json", schema_id=0)
            self.w.add_metadata("diffuser_lab.single_frame", {"json": json.dumps(meta, default=_json_default)})

        self._submit(start)

    def log_target(self, msg: Any, cameras: Sequence[Any]) -> None:
        """A target frame (``msg``: diffuser_lab.TargetFrame) at its first step, with the cameras of
        its window not logged before (``cameras``: objects with index, name, K, T_cw, shape, labels:
        their foxglove messages, frame ``camera_<index>``)."""
        t = self._time("iteration", msg.start)
        for cam in cameras:
            for topic, m in camera_messages(cam.index, cam.K, cam.T_cw, cam.shape, cam.labels, self._colors,
                                            self.max_image_side, t):
                self._write(topic, m, cam.index, t)
        self._write(TOPIC_TARGET, msg, msg.start, t)
        self._flush()

    def log_target_rows(self, step: int, rows: dict, images: dict) -> None:
        """A target frame scored, at ``step`` (after its iterations): ``rows`` (JSON: the Table II rows
        so far and this frame's figures) on /diffuser_lab/single_frame/rows and each row's (H, W)
        label image of the frame ``images`` {name: int16} as a label PNG on /single_frame/labels
        (frame_id = the row's name, ``<method>_<views>``)."""
        from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

        t = self._time("iteration", step)
        for name, img in images.items():  # before the rows: a reader has them when the rows come
            m = CompressedImage(frame_id=str(name), format="png", data=label_png(img, self._colors))
            m.timestamp.FromNanoseconds(t)
            self._write(TOPIC_TARGET_IMAGES, m, step, t)
        self._write(TOPIC_TARGET_ROWS, RawMessage(json.dumps(rows, default=_json_default).encode()), step, t)
        self._flush()

    # -- protocol=tiled ------------------------------------------------------------------------
    def log_tiled(self, points: np.ndarray, labels: np.ndarray, tiles: Sequence[dict], centers: np.ndarray,
                  half_sizes: np.ndarray, colors: np.ndarray, meta: dict) -> None:
        """A tiled run's final records (:mod:`.tiled`): the displayed points coloured by final
        label on /tiled/labels, one cube per tile on /tiled/tiles (foxglove.SceneUpdate), each
        tile's record as JSON on /diffuser_lab/tiles, ``meta`` as ``diffuser_lab.tiled`` metadata."""
        from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
        from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

        t = self._time("evidence")
        upd = SceneUpdate()
        for i, rec in enumerate(tiles):  # loop over tiles
            e = upd.entities.add(frame_id="world", id=f"tile_{rec['id']}", frame_locked=True)
            e.timestamp.FromNanoseconds(t)
            for k in ("id", "status", "points", "frames_read", "iterations", "time_s", "node", "pid", "error"):
                if rec.get(k) is not None:
                    e.metadata.add(key=k, value=str(rec[k]))
            c = e.cubes.add()
            c.pose.position.x, c.pose.position.y, c.pose.position.z = (float(v) for v in centers[i])
            c.pose.orientation.w = 1.0
            c.size.x, c.size.y, c.size.z = (2.0 * float(v) for v in half_sizes[i])
            c.color.r, c.color.g, c.color.b = (float(v) / 255.0 for v in colors[i])
            c.color.a = 0.25

        def start():
            for topic, cls in ((TOPIC_TILED_LABELS, PointCloud), (TOPIC_TILED_TILES, SceneUpdate)):
                self._channels[topic] = self.w.register_channel(topic=topic, message_encoding="protobuf",
                                                                schema_id=self._schema(cls))
            self._channels[TOPIC_TILED_RECORDS] = self.w.register_channel(topic=TOPIC_TILED_RECORDS,
                                                                          message_encoding="json", schema_id=0)
            self.w.add_metadata("diffuser_lab.tiled", {"json": json.dumps(meta, default=_json_default)})

        self._submit(start)
        buf = packed_cloud(points)
        self._paint(buf, labels)
        self._write(TOPIC_TILED_LABELS, point_cloud(buf, t), t=t)
        self._write(TOPIC_TILED_TILES, upd, t=t)
        for i, rec in enumerate(tiles):  # loop over tiles
            raw = json.dumps(rec, default=_json_default).encode()
            self._write(TOPIC_TILED_RECORDS, RawMessage(raw), i, t + i)
        self._flush()

    def log_provenance(self, block: dict) -> None:
        """What made the run (``provenance``, ``inputs``, ``outputs``) as the metadata record
        ``diffuser_lab.provenance``, one JSON text per key; a later record replaces the first for a
        reader (:attr:`.mcap_read.RunLog.provenance`)."""
        self._submit(self.w.add_metadata, "diffuser_lab.provenance",
                     {k: json.dumps(v, sort_keys=True, default=_json_default) for k, v in block.items()})
        self._flush()

    def log_summary(self, summary: dict) -> None:
        self._submit(self.w.add_metadata, "diffuser_lab.summary",
                     {"json": json.dumps(summary, default=_json_default)})
        self._flush()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._submit(self.w.finish)
            if self._writer is not None:
                self._writer.close()
        finally:
            self._fh.close()
        if self._error is not None:
            raise RuntimeError(f"writing {self.path.name} failed: {self._error}") from self._error


_FRAME_FIELDS = ("index", "name", "latency_ms", "map_ms", "evidence_ms", "steps_ms", "points", "new_points", "seen",
                 "graph_rows", "steps", "residual", "changed")
_FRAME_METRICS = ("diffuser_miou", "diffuser_accuracy", "bayesian_miou", "bayesian_accuracy", "coverage")


def online_frame_message(rec: Any, state: str) -> Any:
    """diffuser_lab.OnlineFrame of a :class:`.online.FrameRecord` (metrics absent: NaN; other
    metrics keys and FrameStats fields: JSON in ``extra``)."""
    st = rec.stats
    msg = schema.OnlineFrame(**{k: st[k] for k in _FRAME_FIELDS if st.get(k) is not None},
                             skipped=st.get("skipped") or "", count=int(rec.count), state=state)
    m = rec.metrics or {}
    for k in _FRAME_METRICS:
        v = m.get(k)
        setattr(msg, k, float("nan") if v is None else float(v))
    extra = {k: v for k, v in m.items() if k not in _FRAME_METRICS}
    # FrameStats fields the schema does not name (a newer FrameStats) travel in extra too
    extra.update({k: v for k, v in st.items() if k not in _FRAME_FIELDS and k != "skipped"})
    if extra:
        msg.extra = json.dumps(extra, default=_json_default)
    return msg


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
