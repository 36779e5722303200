"""Reading run.mcap back (also a truncated one: every complete iteration): the one reader that
``diffuser-lab-inspect``, its MCAP -> .rrd conversion and the analysis scripts use."""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Optional

from . import schema
from .mcap_encode import (
    MAGIC,
    TOPIC_METRICS,
    TOPIC_ONLINE_FRAME,
    TOPIC_RUN,
    TOPIC_SCENE,
    TOPIC_TARGET,
    TOPIC_TARGET_ROWS,
    TOPIC_Z,
    decode_point_cloud,
    decode_z,
)


@dataclass
class RunLog:
    """What :func:`read_run` found in a run.mcap.

    Attributes:
        metadata: {record name: {key: value}} (config, run, summary when the run finished).
        info: the RunInfo message, or None.
        metrics: per recorded iteration, dicts with the IterationMetrics fields (None for NaN).
        z_iterations: iterations whose Z state was read completely, in order.
        z: {iteration: (M, C) float32 Z} for the iterations asked for.
        z_dtype: {iteration: how its Z is stored} ("q8", "q16", "float16", "float32"; see
            :func:`~.mcap_encode.z_precision_text`). A state written twice (the last one, kept
            exact after the run converged on a recorded iteration) is read as its later copy.
        scene: {field: array} of the /scene/points cloud (x y z red green blue alpha label), or None.
        frames: protocol=online: per frame taken, dicts with the OnlineFrame fields (None for NaN);
            the Z states (``z``, ``z_iterations``) are then keyed by frame index.
        targets: protocol=single_frame: per target frame, a dict of its TargetFrame's plain fields
            (index, name, count, start, window, n_points, width, height, method, views) and, once
            scored, ``rows`` (Table II so far), ``end`` (the step of its rows), ``iterations``;
            its Z states are keyed by the run's step (iteration t of a target is step start + t).
        truncated: the file ended before its footer (killed run or cut copy).
        error: what stopped the reading early, or None.
    """

    path: Path
    metadata: dict = field(default_factory=dict)
    info: Any = None
    metrics: list = field(default_factory=list)
    z_iterations: list = field(default_factory=list)
    z: dict = field(default_factory=dict)
    z_dtype: dict = field(default_factory=dict)
    scene: Optional[dict] = None
    frames: list = field(default_factory=list)
    targets: list = field(default_factory=list)
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
    def provenance(self) -> Optional[dict]:
        """What made the run (``diffuser_lab.provenance``, the last record: ``provenance``, ``inputs``,
        ``outputs`` decoded), None in a record without it."""
        m = self.metadata.get("diffuser_lab.provenance")
        return {k: json.loads(v) for k, v in m.items()} if m else None

    @property
    def online(self) -> Optional[dict]:
        """The ``diffuser_lab.online`` metadata of an online run (map, n_frames, ...), else None."""
        return self.metadata.get("diffuser_lab.online")

    @property
    def single_frame(self) -> Optional[dict]:
        """The ``diffuser_lab.single_frame`` metadata of a single-frame run (window, ...), else None."""
        m = self.metadata.get("diffuser_lab.single_frame")
        return json.loads(m["json"]) if m else None

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


def online_frame_dict(data: bytes) -> dict:
    """OnlineFrame bytes -> dict (NaN metrics -> None, ``extra`` JSON merged in)."""
    m = schema.OnlineFrame.FromString(data)
    d = {f.name: getattr(m, f.name) for f in m.DESCRIPTOR.fields if f.name != "extra"}
    for k in ("diffuser_miou", "diffuser_accuracy", "bayesian_miou", "bayesian_accuracy", "coverage"):
        if d[k] != d[k]:
            d[k] = None
    d["skipped"] = d["skipped"] or None
    if m.extra:
        d.update(json.loads(m.extra))
    return d


_TARGET_FIELDS = ("index", "name", "count", "start", "n_points", "width", "height", "method", "views")


def target_dict(data: bytes) -> dict:
    """TargetFrame bytes -> dict of its plain fields and its window (no arrays)."""
    m = schema.TargetFrame.FromString(data)
    return {**{f: getattr(m, f) for f in _TARGET_FIELDS}, "window": list(m.window)}


def relog_scene(rec: Any, data: bytes, run: dict, mcap_path: Path | str) -> tuple[Any, list, Any, Any]:
    """A run.mcap's scene message (``TOPIC_SCENE``: the original points) logged again to ``rec``
    (a Rerun recorder of ``diffuser-lab-inspect --to-rrd``: its taxonomy, the recording's name, the
    cloud with colours and ground truth where the run had them; ``run``: the run's metadata).
    Returns (points (N, 3) float32 world m, class names, class colours (C, 3) uint8, ground truth
    (N,) int16 or None)."""
    import numpy as np
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

    cloud = decode_point_cloud(PointCloud.FromString(data))
    points = np.stack([cloud["x"], cloud["y"], cloud["z"]], 1)
    names = json.loads(run.get("class_names", "[]"))
    colors = np.asarray(json.loads(run.get("class_colors", "[]")), np.uint8).reshape(-1, 3)
    gt = cloud["label"].astype(np.int16) if json.loads(run.get("has_gt", "true")) and "label" in cloud else None
    rgb = (np.stack([cloud["red"], cloud["green"], cloud["blue"]], 1)
           if json.loads(run.get("has_colors", "true")) else None)
    rec.log_taxonomy(names, colors)
    rec.rec.send_recording_name(f"{run.get('scene', '?')} (re-logged from {Path(mcap_path).name})")
    rec.log_scene(points, rgb, gt)
    return points, names, colors, gt


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
        elif topic == TOPIC_ONLINE_FRAME:
            out.frames.append(online_frame_dict(data))
        elif topic == TOPIC_Z:
            msg = schema.ZState.FromString(data)
            if not out.z_iterations or out.z_iterations[-1] != int(msg.iteration):
                out.z_iterations.append(int(msg.iteration))
            out.z_dtype[int(msg.iteration)] = msg.dtype or "float32"
            if want_last:
                out.z = {int(msg.iteration): decode_z(msg)}
            elif want_all or msg.iteration in want:
                out.z[int(msg.iteration)] = decode_z(msg)
        elif topic == TOPIC_RUN:
            out.info = schema.RunInfo.FromString(data)
        elif topic == TOPIC_TARGET:
            out.targets.append(target_dict(data))
        elif topic == TOPIC_TARGET_ROWS:
            rows = json.loads(data)
            for t in out.targets:
                if t["index"] == rows["index"] and t["start"] == rows["start"]:
                    t.update(rows=rows["rows"], end=rows["step"], iterations=rows["iterations"])
        elif topic == TOPIC_SCENE and scene:
            out.scene = decode_point_cloud(PointCloud.FromString(data))
    done = set(out.z_iterations)
    out.metrics = [m for m in out.metrics if m["iteration"] in done]
    return out


def work_points(info: Any, scene_points: Optional[Any] = None):
    """(M, 3) float32 points the diffusion ran on: RunInfo.work_points, or the /scene/points
    positions when the run diffused the original cloud itself (left out of RunInfo then)."""
    import numpy as np

    m = int(info.n_work_points)
    if info.work_points:
        return np.frombuffer(info.work_points, "<f4").reshape(m, 3)
    if scene_points is None or len(scene_points) != m:
        raise ValueError("run.mcap: the diffused points are the scene's, but /scene/points was not read")
    return np.asarray(scene_points, np.float32)


__all__ = ["RunLog", "read_run", "iter_run", "metrics_dict", "online_frame_dict", "target_dict", "work_points"]
