"""run.mcap: the diffusion as MCAP (zstd chunks, protobuf messages with their schemas inside).

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

Metadata records: ``diffuser_lab.config`` (``yaml``: the resolved config, ``overrides``: JSON list),
``diffuser_lab.run`` (scene, method, sizes, taxonomy as JSON) and, once the run has finished,
``diffuser_lab.summary`` (``json``: the summary.json content).

Each recorded iteration ends its chunk and flushes the file, so a run that is killed leaves
every completed iteration readable (:func:`read_run` reads such a truncated file).
Compression and writing happen on one background thread (in order, a short bounded queue), so
the diffusion does not wait for zstd; :meth:`McapRecorder.close` drains it. The file is written
with ``O_DIRECT`` where the file system allows (:mod:`.direct_file`): no page-cache copies.
Message ``sequence`` is the diffusion iteration; ``log_time`` is the wall clock (ns).
"""
from __future__ import annotations

import functools
import json
import queue
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Optional, Sequence

import numpy as np

from . import schema
from .direct_file import open_direct
from .serial import SerialThread
from .steps import Step

TOPIC_SCENE = "/scene/points"
TOPIC_EVIDENCE = "/evidence/bayesian"
TOPIC_RUN = "/diffuser_lab/run"
TOPIC_LABELS = "/diffusion/labels"
TOPIC_METRICS = "/diffuser_lab/metrics"
TOPIC_Z = "/diffuser_lab/z"
FRAME_ID = "world"
MAGIC = b"\x89MCAP0\r\n"


def _cloud_dtype() -> np.dtype:
    return np.dtype({"names": ["x", "y", "z", "red", "green", "blue", "alpha", "label"],
                     "formats": ["<f4", "<f4", "<f4", "u1", "u1", "u1", "u1", "<i2"]})


def _cloud(points: np.ndarray) -> np.ndarray:
    """(P, 3) points -> a packed cloud (:func:`_cloud_dtype`) with x y z set, opaque, label -1."""
    buf = np.zeros(len(points), _cloud_dtype())
    for i, ax in enumerate("xyz"):
        buf[ax] = points[:, i]
    buf["alpha"] = 255
    buf["label"] = -1
    return buf


def _point_cloud(buf: np.ndarray, stamp_ns: int, with_data: bool = True) -> Any:
    """A foxglove.PointCloud of the packed structured array ``buf`` (without its ``data``
    field when not ``with_data``)."""
    from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

    kinds = {"<f4": PackedElementField.FLOAT32, "|u1": PackedElementField.UINT8, "<i2": PackedElementField.INT16}
    msg = PointCloud(frame_id=FRAME_ID, point_stride=buf.dtype.itemsize)
    msg.timestamp.FromNanoseconds(stamp_ns)
    msg.pose.orientation.w = 1.0
    for name in buf.dtype.names:
        dt, off = buf.dtype.fields[name][:2]
        msg.fields.add(name=name, offset=off, type=kinds[dt.str])
    if with_data:
        msg.data = buf.tobytes()
    return msg


def point_cloud_bytes(buf: np.ndarray, stamp_ns: int, out: Optional[bytearray] = None) -> memoryview:
    """``_point_cloud(buf, stamp_ns).SerializeToString()`` with ``buf`` copied once, into ``out``
    (see :func:`_with_bytes_field`); ``data`` is PointCloud's last field (6)."""
    head = _point_cloud(buf, stamp_ns, with_data=False).SerializeToString()
    mv, at = _with_bytes_field(head, 6, buf.nbytes, b"", out)
    np.frombuffer(mv, np.uint8, buf.nbytes, at)[:] = buf.reshape(-1).view(np.uint8)
    return mv


def decode_point_cloud(msg: Any) -> dict[str, np.ndarray]:
    """foxglove.PointCloud -> {field name: (P,) array} (FLOAT32, UINT8, INT16, INT32 fields)."""
    from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField as F

    codes = {F.FLOAT32: "<f4", F.UINT8: "u1", F.INT16: "<i2", F.INT32: "<i4", F.UINT16: "<u2",
             F.FLOAT64: "<f8", F.INT8: "i1", F.UINT32: "<u4"}
    dt = np.dtype({"names": [f.name for f in msg.fields], "formats": [codes[f.type] for f in msg.fields],
                   "offsets": [f.offset for f in msg.fields], "itemsize": msg.point_stride})
    arr = np.frombuffer(msg.data, dt)
    return {name: np.ascontiguousarray(arr[name]) for name in dt.names}


def _z_scale(Z: np.ndarray, dtype: str) -> float:
    """The scale of stored Z (Z = stored * scale): 1 for float32 (Z itself, exact); max(Z) for
    float16, which stores Z / max(Z) so that Z's tiny values keep their precision."""
    if dtype != "float16":
        return 1.0
    top = float(Z.max()) if Z.size else 0.0
    return top if top > 0 else 1.0


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        if n:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _with_bytes_field(head: bytes, number: int, nbytes: int, tail: bytes,
                      out: Optional[bytearray]) -> tuple[memoryview, int]:
    """A serialized protobuf message ``head`` + bytes field ``number`` (``nbytes`` long, left for
    the caller to fill) + ``tail``, where head and tail serialize the fields numbered below and
    above it (protobuf writes fields in number order, so this is the message's own encoding).
    Uses ``out`` when it is large enough, else a new buffer. Returns (the message, offset of the
    field's payload)."""
    if nbytes:  # proto3 leaves an empty bytes field out
        head += _varint(number << 3 | 2) + _varint(nbytes)
    size = len(head) + nbytes + len(tail)
    if out is None or len(out) < size:
        out = bytearray(size)
    mv = memoryview(out)[:size]
    mv[:len(head)] = head
    mv[len(head) + nbytes:] = tail
    return mv, len(head)


def z_state_bytes(iteration: int, Z: np.ndarray, dtype: str, out: Optional[bytearray] = None,
                  class_major: bool = True) -> memoryview:
    """``ZState(...).SerializeToString()`` with Z copied once (transposed when ``class_major``)
    into ``out`` (see :func:`_with_bytes_field`); ``data`` is field 5."""
    scale = _z_scale(Z, dtype)
    stored = np.dtype("<f2" if dtype == "float16" else "<f4")
    head = schema.ZState(iteration=int(iteration), n_points=Z.shape[0], n_classes=Z.shape[1],
                         dtype=dtype).SerializeToString()
    tail = schema.ZState(scale=scale, class_major=bool(class_major)).SerializeToString()
    mv, at = _with_bytes_field(head, 5, Z.size * stored.itemsize, tail, out)
    body = np.frombuffer(mv, stored, Z.size, at).reshape(Z.shape[::-1] if class_major else Z.shape)
    from diffuser_lab.backends.numba.float16 import transpose_into  # numba: only where Z is written

    if stored == np.float32:
        if class_major:
            transpose_into(np.asarray(Z, np.float32), body)
        else:
            body[...] = Z
        return mv
    # float16: transpose (compiled, float32) and scale first, then one contiguous conversion
    tmp = np.empty(body.shape, np.float32)
    if class_major:
        transpose_into(np.asarray(Z, np.float32), tmp)
    else:
        tmp[...] = Z
    np.divide(tmp, np.float32(scale), out=tmp)
    body[...] = to_float16(tmp)
    return mv


_F16_MIN_NORMAL = np.float32(2.0**-14)


def to_float16(a: np.ndarray) -> np.ndarray:
    """``a.astype("<f2")`` for finite float32 ``a`` >= 0, bit for bit, fast: numpy converts
    values that become float16 subnormals (below 2^-14; Z has many) in a slow path (~50 ms on a
    1M-value Z state). Compiled where numba is; otherwise those values are rounded here as the
    multiple of 2^-24 nearest (ties to even), which is their float16 bit pattern."""
    from diffuser_lab.backends.numba.float16 import to_float16 as compiled

    out = compiled(a)
    if out is not None:
        return out
    sub = a < _F16_MIN_NORMAL
    with np.errstate(over="ignore"):  # beyond 65504: inf, as numpy
        out = np.where(sub, np.float32(0.0), a).astype("<f2")
    bits = out.view(np.uint16)
    bits[sub] = np.rint(a[sub] * np.float32(2.0**24)).astype(np.uint16)
    return out


class _RawMessage:
    """An already serialized message (what the writer thread calls SerializeToString on);
    ``done`` is called once the writer has copied it (returns a pooled buffer)."""

    __slots__ = ("data", "done")

    def __init__(self, data, done=None):
        self.data, self.done = data, done

    def SerializeToString(self):  # noqa: N802 - protobuf's name
        return self.data


def decode_z(msg: Any) -> np.ndarray:
    """diffuser_lab.ZState -> (M, C) float32 Z in the paper's units."""
    dt = "<f2" if msg.dtype == "float16" else "<f4"
    if msg.class_major:
        Z = np.frombuffer(msg.data, dt).reshape(msg.n_classes, msg.n_points).T.astype(np.float32, order="C")
    else:
        Z = np.frombuffer(msg.data, dt).reshape(msg.n_points, msg.n_classes).astype(np.float32)
    if msg.scale not in (0.0, 1.0):
        Z *= np.float32(msg.scale)
    return Z


WRITER_THREAD = True
"""Compress and write on a background thread (False: in the caller's thread)."""
ZSTD_LEVEL = -20
"""Default zstd level of run.mcap's chunks (``record.zstd_level``). Float32 Z is mostly mantissa
noise and barely compresses, and compressing it is most of the cost of recording. Measured on
one 51k x 20 demo Z state (4 MB): level 3 25 ms -> 0.56x, -3 8.3 ms -> 0.61x, -20 3.2 ms -> 0.78x,
-100 1.3 ms -> 0.95x. -20 keeps a quarter of the bytes off the disk at an eighth of level 3's cost."""


@functools.lru_cache(maxsize=None)
def _writer_class(level: int = ZSTD_LEVEL):
    """mcap's Writer with chunks compressed at zstd ``level``.

    mcap 1.x compresses chunks with ``zstandard.compress(data)`` (level 3) and has no option
    for the level, so the subclass carries a copy of the chunk-finishing method whose global
    ``zstandard`` is a shim with the level set; mcap's own module is not touched. Falls back to
    the stock Writer when mcap's internals differ from what this expects."""
    import types

    import zstandard
    from mcap.writer import Writer

    fn = getattr(Writer, "_Writer__finalize_chunk", None)
    if fn is None or "zstandard" not in fn.__code__.co_names:
        return Writer

    class _Zstd:
        def __getattr__(self, name: str) -> Any:
            return getattr(zstandard, name)

        @staticmethod
        def compress(data: bytes) -> bytes:
            return zstandard.compress(data, level)

    glb = dict(fn.__globals__)
    glb["zstandard"] = _Zstd()

    class FastZstdWriter(Writer):
        pass

    FastZstdWriter._Writer__finalize_chunk = types.FunctionType(  # type: ignore[attr-defined]
        fn.__code__, glb, fn.__name__, fn.__defaults__, fn.__closure__)
    return FastZstdWriter


class McapRecorder:
    """Writes run.mcap as the run goes (see the module doc). ``writer_thread``: compress and
    write on a thread of its own (default :data:`WRITER_THREAD`); False when the caller records
    on a background thread already (:mod:`diffuser_lab.recording`)."""

    file_key = "mcap"

    def __init__(self, path: Path, *, z_dtype: str = "float32", config_yaml: str = "",
                 overrides: Sequence[str] = (), interval: int = 1, max_iter: int = 0,
                 zstd_level: int = ZSTD_LEVEL, writer_thread: bool | None = None):
        from mcap.writer import CompressionType

        from diffuser_lab import __version__

        self.path = Path(path)
        self.z_dtype = z_dtype
        self.interval, self.max_iter = int(interval), int(max_iter)
        self._fh = open_direct(self.path)  # O_DIRECT where possible: no page-cache copies
        # no CRCs: on 4 MB Z chunks crc32 costs half as much as compressing them; records keep
        # their lengths, so a cut file is still read up to its last complete chunk
        self.w = _writer_class(int(zstd_level))(self._fh, compression=CompressionType.ZSTD, enable_crcs=False)
        self.w.start(profile="", library=f"diffuser-lab {__version__}")
        from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

        self._channels: dict[str, int] = {}
        self._schema_ids: dict[str, int] = {}
        for topic, cls in ((TOPIC_SCENE, PointCloud), (TOPIC_EVIDENCE, PointCloud), (TOPIC_RUN, schema.RunInfo),
                           (TOPIC_LABELS, PointCloud), (TOPIC_METRICS, schema.IterationMetrics),
                           (TOPIC_Z, schema.ZState)):
            sid = self._schema(cls)
            self._channels[topic] = self.w.register_channel(topic=topic, message_encoding="protobuf", schema_id=sid)
        self.w.add_metadata("diffuser_lab.config", {"yaml": config_yaml, "overrides": json.dumps(list(overrides))})
        self._cameras: list[Any] = []
        self._labels_buf: Optional[np.ndarray] = None
        self._rgba: Optional[np.ndarray] = None  # (C + 1,) colours packed as the cloud's 4 rgba bytes
        # per-iteration message buffers, reused once the writer has copied them (a fresh 4 MB
        # buffer per recorded iteration costs more in page faults than the copy itself)
        self._free: dict[str, queue.SimpleQueue] = {TOPIC_LABELS: queue.SimpleQueue(), TOPIC_Z: queue.SimpleQueue()}
        self._closed = False
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

    def _write(self, topic: str, msg: Any, sequence: int = 0) -> None:
        """Queue ``msg`` (which must not change afterwards) for the writer thread."""
        self._submit(self._add, topic, msg, int(sequence), time.time_ns())

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
        colors = np.vstack([tax.colors, np.array([[70, 70, 70]], np.uint8)])  # last: unlabeled
        rgba = np.concatenate([colors, np.full((len(colors), 1), 255, np.uint8)], 1)
        self._rgba = np.ascontiguousarray(rgba).view("<u4").ravel()  # index -1 (IGNORE): unlabeled
        gt = scene.gt_labels
        self._submit(self.w.add_metadata, "diffuser_lab.run", {
            "scene": scene.name, "n_points": str(scene.n_points), "taxonomy": tax.name,
            "class_names": json.dumps(list(tax.names)), "class_colors": json.dumps(tax.colors.tolist()),
            "has_colors": json.dumps(scene.colors is not None), "has_gt": json.dumps(gt is not None)})
        buf = _cloud(scene.points)
        if gt is not None:
            self._paint(buf, gt)
        if scene.colors is not None:  # input colours win over the ground truth's
            buf["red"], buf["green"], buf["blue"] = scene.colors[:, 0], scene.colors[:, 1], scene.colors[:, 2]
        elif gt is None:
            buf["red"] = buf["green"] = buf["blue"] = 160
        self._write(TOPIC_SCENE, _point_cloud(buf, time.time_ns()))

    def log_camera(self, index: int, frame: Any) -> None:
        h, w = frame.shape
        self._cameras.append(schema.Camera(name=str(frame.name), width=int(w), height=int(h),
                                           K=np.asarray(frame.K, float).ravel().tolist(),
                                           T_cw=np.asarray(frame.T_cw, float).ravel().tolist()))

    def log_evidence(self, scene: Any, method: str, work_points: np.ndarray, to_work: Optional[np.ndarray],
                     seen: np.ndarray, bayesian: np.ndarray) -> None:
        tax = scene.taxonomy
        m = len(work_points)
        info = schema.RunInfo(scene=scene.name, method=method, taxonomy=tax.name, class_names=list(tax.names),
                              class_colors=np.asarray(tax.colors, np.uint8).tobytes(), n_points=scene.n_points,
                              n_work_points=m, work_points=np.ascontiguousarray(work_points, "<f4").tobytes(),
                              original_to_work=b"" if to_work is None else to_work.astype("<i4").tobytes(),
                              bayesian_labels=np.asarray(bayesian, "<i2").tobytes(),
                              seen=np.asarray(seen, np.uint8).tobytes(), interval=self.interval,
                              max_iter=self.max_iter, z_dtype=self.z_dtype)
        info.cameras.extend(self._cameras)
        self._write(TOPIC_RUN, info)
        buf = _cloud(work_points)
        self._paint(buf, bayesian)
        self._write(TOPIC_EVIDENCE, _point_cloud(buf, time.time_ns()))
        self._labels_buf = _cloud(work_points)  # the per-iteration cloud: positions filled once
        self._flush()

    # -- per iteration ------------------------------------------------------------------------
    def log_step(self, step: Step) -> None:
        nan = float("nan")
        self._write(TOPIC_METRICS, schema.IterationMetrics(
            iteration=step.iteration, residual=step.residual, n_changed=step.n_changed,
            previous_iteration=step.previous, miou=nan if step.miou is None else step.miou,
            accuracy=nan if step.accuracy is None else step.accuracy, coverage=step.coverage,
            mean_confidence=step.mean_confidence), step.iteration)
        if self._labels_buf is not None:
            buf = self._labels_buf
            self._paint(buf, step.labels)
            self._write_pooled(TOPIC_LABELS, point_cloud_bytes(buf, time.time_ns(), self._pooled(TOPIC_LABELS)),
                               step.iteration)
        self._write_pooled(TOPIC_Z, z_state_bytes(step.iteration, step.Z, self.z_dtype, self._pooled(TOPIC_Z)),
                           step.iteration)
        self._flush()  # ends the chunk: a killed run keeps this iteration

    def _pooled(self, topic: str) -> Optional[bytearray]:
        try:
            return self._free[topic].get_nowait()
        except queue.Empty:
            return None

    def _write_pooled(self, topic: str, mv: memoryview, sequence: int) -> None:
        """Queue a serialized message whose buffer returns to ``topic``'s pool once written."""
        self._write(topic, _RawMessage(mv, functools.partial(self._free[topic].put, mv.obj)), sequence)

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


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


# ---------------------------------------------------------------------------------------------
# reading


@dataclass
class RunLog:
    """What :func:`read_run` found in a run.mcap.

    Attributes:
        metadata: {record name: {key: value}} (config, run, summary when the run finished).
        info: the RunInfo message, or None.
        metrics: per recorded iteration, dicts with the IterationMetrics fields (None for NaN).
        z_iterations: iterations whose Z state was read completely, in order.
        z: {iteration: (M, C) float32 Z} for the iterations asked for.
        scene: {field: array} of the /scene/points cloud (x y z red green blue alpha label), or None.
        truncated: the file ended before its footer (killed run or cut copy).
        error: what stopped the reading early, or None.
    """

    path: Path
    metadata: dict = field(default_factory=dict)
    info: Any = None
    metrics: list = field(default_factory=list)
    z_iterations: list = field(default_factory=list)
    z: dict = field(default_factory=dict)
    scene: Optional[dict] = None
    truncated: bool = False
    error: Optional[str] = None
    complete: bool = False

    @property
    def config_yaml(self) -> str:
        return self.metadata.get("diffuser_lab.config", {}).get("yaml", "")

    @property
    def overrides(self) -> list:
        return json.loads(self.metadata.get("diffuser_lab.config", {}).get("overrides", "[]"))

    @property
    def summary(self) -> Optional[dict]:
        s = self.metadata.get("diffuser_lab.summary")
        return json.loads(s["json"]) if s else None

    @property
    def run(self) -> dict:
        return self.metadata.get("diffuser_lab.run", {})

    @property
    def class_names(self) -> list:
        if self.info is not None:
            return list(self.info.class_names)
        return json.loads(self.run.get("class_names", "[]"))


def iter_run(path: Path | str, log: "RunLog") -> Iterator[tuple[str, Any]]:
    """Read run.mcap front to back (no summary section needed, so a truncated file works),
    yielding ``(topic, raw message bytes)`` for every message and ``("metadata:<name>", dict)``
    for metadata records. Sets ``log.complete`` / ``log.truncated`` / ``log.error`` at the end;
    only whole records are yielded."""
    from mcap.records import Channel, Footer, Message, Metadata
    from mcap.stream_reader import StreamReader

    topics: dict[int, str] = {}
    with open(path, "rb") as fh:
        if fh.read(8) != MAGIC:
            raise ValueError(f"{path}: not an MCAP file")
        fh.seek(0)
        reader = StreamReader(fh, validate_crcs=True)
        try:
            for rec in reader.records:
                if isinstance(rec, Channel):
                    topics[rec.id] = rec.topic
                elif isinstance(rec, Metadata):
                    log.metadata[rec.name] = dict(rec.metadata)
                    yield f"metadata:{rec.name}", dict(rec.metadata)
                elif isinstance(rec, Message):
                    yield topics.get(rec.channel_id, ""), rec.data
                elif isinstance(rec, Footer):
                    log.complete = True
        except Exception as exc:  # noqa: BLE001 - a cut file ends in any of several ways
            log.truncated = True
            log.error = (f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__)[:300]
    if not log.complete and not log.truncated:
        log.truncated, log.error = True, "the file ends without its footer"


def metrics_dict(data: bytes) -> dict:
    """IterationMetrics bytes -> dict (NaN mIoU / accuracy -> None)."""
    m = schema.IterationMetrics.FromString(data)
    d = {f: getattr(m, f) for f in ("iteration", "residual", "n_changed", "previous_iteration", "miou",
                                    "accuracy", "coverage", "mean_confidence")}
    for k in ("miou", "accuracy"):
        if d[k] != d[k]:
            d[k] = None
    return d


def read_run(path: Path | str, *, z: Optional[Iterable[int]] | str = None, scene: bool = False) -> RunLog:
    """Read a run.mcap, also a truncated one (see :func:`iter_run`).

    Args:
        z: iterations whose Z to decode (``"all"`` for every one, ``"last"`` for the last
            complete one); None: none.
        scene: also decode the /scene/points cloud.
    Returns:
        :class:`RunLog`; ``truncated``/``error`` say whether the file ended early. An iteration
        counts as recorded only when its Z arrived whole.
    """
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

    want_all, want_last = z == "all", z == "last"
    want = set() if (z is None or isinstance(z, str)) else {int(i) for i in z}
    out = RunLog(path=Path(path))
    for topic, data in iter_run(path, out):
        if topic == TOPIC_METRICS:
            out.metrics.append(metrics_dict(data))
        elif topic == TOPIC_Z:
            msg = schema.ZState.FromString(data)
            out.z_iterations.append(int(msg.iteration))
            if want_last:
                out.z = {int(msg.iteration): decode_z(msg)}
            elif want_all or msg.iteration in want:
                out.z[int(msg.iteration)] = decode_z(msg)
        elif topic == TOPIC_RUN:
            out.info = schema.RunInfo.FromString(data)
        elif topic == TOPIC_SCENE and scene:
            out.scene = decode_point_cloud(PointCloud.FromString(data))
    done = set(out.z_iterations)
    out.metrics = [m for m in out.metrics if m["iteration"] in done]
    return out


__all__ = ["McapRecorder", "RunLog", "read_run", "iter_run", "metrics_dict", "decode_z", "z_state_bytes", "point_cloud_bytes", "decode_point_cloud",
           "TOPIC_Z", "TOPIC_METRICS", "TOPIC_RUN", "TOPIC_LABELS", "TOPIC_SCENE", "TOPIC_EVIDENCE"]
