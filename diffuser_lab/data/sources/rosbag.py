"""ROS 1 and ROS 2 bags (``.bag``; a rosbag2 folder, ``.mcap`` or ``.db3``), read with ``rosbags``
(no ROS installation): ``scene.source=rosbag``.

What is read (message definitions: https://docs.ros.org/en/rolling/p/sensor_msgs/):

- **depth** ``sensor_msgs/Image`` ``16UC1`` (millimetres, ``depth_scale`` units per metre) or ``32FC1``
  (metres; NaN / inf = none), or ``sensor_msgs/CompressedImage`` ``compressedDepth`` (PNG, as
  ``compressed_depth_image_transport`` writes it); 0 = no depth (REP 118);
- **colour** ``Image`` rgb8 / bgr8 / rgba8 / bgra8 / mono8 or ``CompressedImage`` jpeg / png, registered to
  the depth image (one optical frame: e.g. RealSense ``aligned_depth_to_color``), resized to its size;
- **labels** ``Image`` mono8 / mono16 (8UC1, 16UC1, 32SC1) or a PNG ``CompressedImage``: label ids;
- **intrinsics** ``sensor_msgs/CameraInfo`` of the depth topic: ``K`` for ``width x height``; a
  non-zero ``D`` (``plumb_bob``, ``rational_polynomial``, ``equidistant``: e.g. the Azure Kinect's raw
  topics) resamples depth (nearest), colour (bilinear) and labels (nearest) to the pinhole camera of the
  same K with the one undistortion (:mod:`diffuser_lab.data.distortion`); pixels without a source get no
  depth / IGNORE; ``scene.frames.info["undistorted"]`` names the lens;
- **poses** of the camera's optical frame (x right, y down, z forward: OpenCV's camera, REP 103) in the
  world: the tf2 chain ``world_frame`` -> ``camera_frame`` of ``/tf`` + ``/tf_static``
  (``tf2_msgs/TFMessage``; any number of links, static and dynamic), or a pose topic
  (``geometry_msgs/PoseStamped``, ``PoseWithCovarianceStamped``, ``TransformStamped``,
  ``nav_msgs/Odometry``) of a body whose camera sits at ``camera_in_body``.

Stamps are the messages' ``header.stamp`` (``use_header_stamp=false``: the bag's record time). The depth
image is the frame's clock; the nearest colour / label image within ``max_time_diff`` seconds joins it;
the pose at its stamp is interpolated (translation linear, rotation slerp) between the samples around it
that lie within ``pose_max_time_diff``, else the nearest such sample. Frames without colour or pose are
skipped and counted in ``scene.frames.info``; frames are ordered by stamp.

Frames are lazy: the first pass keeps (topic, record time, ordinal) per image message and decodes only
the small messages (CameraInfo, tf, poses); an image is read from the bag when its frame is.

**Followed as it is written** (``follow=true``, protocol=online; docs/online.md, :func:`follow_rosbag`): a
ROS 2 bag in MCAP storage (a rosbag2 folder, or an .mcap file) is polled while the recorder writes it;
only whole records are read (a chunk the writer still fills is not on disk yet), and a depth image becomes
a frame once no later message can change it (:meth:`_Pass.settled`), so the frames are the closed bag's.

The labelled points go out as a PointCloud2 bag through
:func:`diffuser_lab.data.clouds.write_pointcloud2_bag`, beside the other cloud writers.
"""
from __future__ import annotations

import contextlib
import mmap
import os
import re
import struct
import threading
import warnings
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Callable, List, Optional

import numpy as np
from omegaconf import MISSING

from diffuser_lab.config import SceneConfig, above, check, key, rule
from diffuser_lab.data import inputs
from diffuser_lab.data.capture import CaptureOptions, CapturedFrame, FollowOptions, capture_scene, followed_capture
from diffuser_lab.data.frames import first_line
from diffuser_lab.data.distortion import LensModel, ros_lens, undistort_image
from diffuser_lab.data.images import open_image
from diffuser_lab.data.poses import associate, interpolate_poses, pose_matrices, rigid_inverse
from diffuser_lab.data.scene import IGNORE, Scene, Taxonomy
from diffuser_lab.data.sensor import SensorModel
from diffuser_lab.data.validate import check_depth_unit


__all__ = ["RosbagOptions", "load", "load_rosbag", "follow_rosbag", "decode_image"]

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
TF_TYPE = "tf2_msgs/msg/TFMessage"
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped",
              "geometry_msgs/msg/TransformStamped", "nav_msgs/msg/Odometry")
QUAT_TOL = 1e-2  # |norm(q) - 1| above this: not a rotation (as the TUM reader checks)


_SEVEN = rule("[x, y, z, qx, qy, qz, qw] (metres, unit quaternion) or null", null=True, test=lambda v: len(v) == 7
              and abs(float(np.linalg.norm(np.asarray(v[3:], float))) - 1.0) <= QUAT_TOL)


@dataclass
class RosbagOptions(FollowOptions, CaptureOptions):
    """``scene.options`` of ``scene=rosbag`` (docs/layouts.md, "ROS bags")."""

    path: str = MISSING  # the bag: a ROS 1 .bag, a rosbag2 folder (metadata.yaml), or its .mcap / .db3 file
    depth_topic: Optional[str] = None  # sensor_msgs Image / CompressedImage; null = the one image topic named *depth*
    color_topic: Optional[str] = "auto"  # auto = the one image topic named *color* / *rgb* (raw before compressed); null = none
    labels_topic: Optional[str] = None  # label-id images (mono8 / mono16 / PNG); null = none
    camera_info_topic: Optional[str] = None  # the depth's CameraInfo; null = <depth topic's namespace>/camera_info, else the only one
    pose_topic: Optional[str] = None  # PoseStamped / PoseWithCovarianceStamped / TransformStamped / Odometry; null = /tf + /tf_static
    world_frame: Optional[str] = "map"  # tf: the world frame of the poses (null with pose_topic: the poses' header.frame_id)
    camera_frame: Optional[str] = None  # tf: the camera's optical frame; null = the depth images' header.frame_id
    camera_in_body: Optional[List[float]] = key(None, _SEVEN)  # pose_topic: the camera optical frame's pose in the body; null = the pose is the camera's
    max_time_diff: float = key(0.02, above(0, "seconds"))  # colour / label image: nearest within this of the depth stamp
    pose_max_time_diff: float = key(0.05, above(0, "seconds"))  # pose samples used: within this of the depth stamp
    pose_interpolation: bool = True  # interpolate between the pose samples around a stamp; false = the nearest
    use_header_stamp: bool = True  # false = the bag's record (receive) time instead of header.stamp
    depth_scale: float = key(1000.0, above(0))  # 16UC1 depth: units per metre (REP 118: millimetres)

    def _check_keys(self) -> None:
        check(not self.follow or Path(self.path).suffix not in (".bag", ".db3"), "scene.options.path", self.path,
              "a rosbag2 folder of .mcap files or an .mcap file with scene.options.follow=true (a bag is followed "
              "in its MCAP storage: ros2 bag record -s mcap)")


# --------------------------------------------------------------------------- images


def _pil(data: bytes, what: str) -> np.ndarray:
    """A CompressedImage's bytes through the one image reader (declared size checked, one line naming ``what``)."""
    with open_image(bytes(data), "compressed image", name=what) as im:
        return np.asarray(im.convert("RGB") if im.mode in ("P", "CMYK", "YCbCr", "LA", "RGBA") else im).copy()


_RAW = {"rgb8": ("u1", 3), "bgr8": ("u1", 3), "rgba8": ("u1", 4), "bgra8": ("u1", 4), "mono8": ("u1", 1),
        "8UC1": ("u1", 1), "8UC3": ("u1", 3), "mono16": ("u2", 1), "16UC1": ("u2", 1), "16SC1": ("i2", 1),
        "32SC1": ("i4", 1), "32FC1": ("f4", 1)}


def decode_image(msg, what: str) -> tuple[np.ndarray, str]:
    """A ``sensor_msgs`` Image / CompressedImage -> ((H, W) or (H, W, C) array, encoding).

    Raw images honour ``step`` (row padding) and ``is_bigendian``; the encoding returned is the
    message's (``rgb8``, ``16UC1``...). Compressed: ``compressedDepth`` -> (H, W) float32 metres with
    encoding ``depth``, else the PIL-decoded pixels with encoding ``compressed``.
    """
    if hasattr(msg, "format"):
        fmt = str(msg.format)
        data = np.asarray(msg.data, np.uint8)
        if "compresseddepth" in fmt.lower():
            if data.size < 12:
                raise ValueError(f"{what}: compressedDepth message of {data.size} bytes, "
                                 f"expected a 12-byte header + PNG")
            _, qa, qb = struct.unpack("<iff", data[:12].tobytes())
            raw = _pil(data[12:].tobytes(), what)
            if "32FC1" in fmt:  # inverse depth, quantised: depth = qa / (v - qb)
                v = raw.astype(np.float32)
                d = np.where(v > 0, qa / np.maximum(v - qb, 1e-9), 0.0).astype(np.float32)
            else:
                d = raw.astype(np.float32) / 1000.0  # 16UC1 millimetres
            return d, "depth"
        return _pil(data.tobytes(), what), "compressed"
    enc = str(msg.encoding)
    if enc not in _RAW:
        raise ValueError(f"{what}: image encoding {enc!r}, expected one of {', '.join(_RAW)}")
    kind, ch = _RAW[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    dt = np.dtype(kind).newbyteorder(">" if msg.is_bigendian else "<")
    row = w * ch * dt.itemsize
    data = np.asarray(msg.data, np.uint8)
    if step < row or data.size < h * step:
        raise ValueError(f"{what}: {enc} image {w}x{h} with step {step} and {data.size} bytes, "
                         f"expected step >= {row} and {h} x step bytes")
    a = data[: h * step].reshape(h, step)[:, :row].copy().view(dt).reshape(h, w, ch)
    return (a[..., 0] if ch == 1 else a).astype(dt.newbyteorder("=")), enc


def _to_depth(a: np.ndarray, enc: str, scale: float, what: str) -> np.ndarray:
    """Decoded depth -> (H, W) float32 metres, 0 = none."""
    if enc == "depth":
        d = a
    elif enc in ("16UC1", "mono16"):
        d = a.astype(np.float32) / np.float32(scale)
    elif enc == "32FC1":
        d = a.astype(np.float32)
    else:
        raise ValueError(f"{what}: depth image of encoding {enc}, expected 16UC1 (millimetres), 32FC1 (metres) "
                         f"or a compressedDepth image")
    return np.where(np.isfinite(d) & (d > 0), d, 0).astype(np.float32)


def _to_rgb(a: np.ndarray, enc: str, what: str) -> np.ndarray:
    """Decoded colour -> (H, W, 3) uint8 RGB."""
    if a.dtype != np.uint8:
        raise ValueError(f"{what}: colour image of encoding {enc} ({a.dtype}), "
                         f"expected 8-bit rgb8/bgr8/rgba8/bgra8/mono8")
    if a.ndim == 2:
        return np.repeat(a[..., None], 3, axis=2)
    if enc in ("bgr8", "bgra8"):
        return np.ascontiguousarray(a[..., 2::-1])
    return np.ascontiguousarray(a[..., :3])


def _to_labels(a: np.ndarray, enc: str, what: str) -> np.ndarray:
    if a.ndim != 2 or a.dtype.kind not in "ui":
        raise ValueError(f"{what}: label image of encoding {enc} shape {a.shape}, expected one integer channel "
                         f"(mono8 / mono16 / 32SC1 / a PNG)")
    return a.astype(np.int64)


# --------------------------------------------------------------------------- poses


def _rigid(q: np.ndarray, t: np.ndarray, where: str) -> None:
    """One line when a sample's quaternion is not a rotation (or any value is not finite)."""
    n = np.linalg.norm(q, axis=1)
    bad = ~(np.abs(n - 1) <= QUAT_TOL) | ~np.isfinite(t).all(1)
    if bad.any():
        k = int(np.argmax(bad))
        raise ValueError(f"{where}: sample {k} has quaternion norm {n[k]:.4g} (or non-finite values), expected a "
                         f"rigid pose (a unit quaternion x y z w)")


class _Track:
    """One sampled transform (a tf edge parent -> child, or a pose topic): stamps and values."""

    def __init__(self, parent: str, static: bool, where: str):
        self.parent, self.static, self.where = parent, static, where
        self.t: list[int] = []
        self.v: list[tuple] = []

    def arrays(self):
        st = np.asarray(self.t, np.int64)
        v = np.asarray(self.v, np.float64).reshape(-1, 7)
        o = np.argsort(st, kind="stable")
        _rigid(v[o, 3:], v[o, :3], self.where)
        return st[o], v[o, :3], v[o, 3:] / np.linalg.norm(v[o, 3:], axis=1, keepdims=True)

    def at(self, at: np.ndarray, tol: float, interpolate: bool) -> tuple[np.ndarray, np.ndarray]:
        st, tr, q = self.arrays()
        if self.static:  # valid at every time: the latest sample
            return np.repeat(pose_matrices(tr[-1:], q[-1:]), len(at), 0), np.ones(len(at), bool)
        return interpolate_poses(st, tr, q, at, tol * 1e9, interpolate)  # nanoseconds


def _chain(edges: dict[str, _Track], world: str, camera: str, bag: Path) -> tuple[list[str], list[str]]:
    """The tf tree's path world -> camera: (frames from world up to the common ancestor,
    frames from the camera up to it), each edge a child frame of ``edges``."""
    known = sorted(set(edges) | {e.parent for e in edges.values()})
    for name, role in ((world, "world_frame"), (camera, "camera_frame")):
        if name not in known:
            raise ValueError(f"{bag}: frame {name!r} (scene.options.{role}) is not in /tf or /tf_static; "
                             f"frames there: {', '.join(known) or 'none'}")

    def up(f: str) -> list[str]:
        out = [f]
        while out[-1] in edges and len(out) <= len(edges):
            out.append(edges[out[-1]].parent)
        return out

    a, b = up(camera), up(world)
    common = next((f for f in a if f in b), None)
    if common is None:
        raise ValueError(f"{bag}: frames {world!r} and {camera!r} are not connected in /tf + /tf_static "
                         f"(roots {b[-1]!r} and {a[-1]!r})")
    return b[: b.index(common)], a[: a.index(common)]


def _chain_poses(edges, world, camera, at, tol, interpolate, bag) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4, 4) world-from-camera at the (N,) stamps and (N,) bool: every link had a sample."""
    up_world, up_cam = _chain(edges, world, camera, bag)
    ok = np.ones(len(at), bool)

    def root_from(frames: list[str]) -> np.ndarray:  # root-from-frames[0]: the links composed
        nonlocal ok
        T = np.tile(np.eye(4), (len(at), 1, 1))
        for f in frames:  # loop over the few links of a chain
            Tf, okf = edges[f].at(at, tol, interpolate)
            T, ok = Tf @ T, ok & okf
        return T

    Tw, Tc = root_from(up_world), root_from(up_cam)
    return rigid_inverse(Tw) @ Tc, ok


def _tf_values(tr) -> tuple:
    t, r = tr.translation, tr.rotation
    return (t.x, t.y, t.z, r.x, r.y, r.z, r.w)


def _pose_values(msg, msgtype: str) -> tuple:
    if msgtype.endswith("TransformStamped"):
        return _tf_values(msg.transform)
    p = msg.pose.pose if msgtype.endswith(("Odometry", "WithCovarianceStamped")) else msg.pose
    return (p.position.x, p.position.y, p.position.z, p.orientation.x, p.orientation.y, p.orientation.z,
            p.orientation.w)


# --------------------------------------------------------------------------- the bag


def _stamp_ns(t) -> int:
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def _header(raw: memoryview | bytes, ros2: bool, what: str) -> tuple[int, str]:
    """(stamp ns, frame_id) of a serialised message whose first field is a std_msgs/Header, read from
    its first bytes (CDR: 4-byte encapsulation, sec, nanosec, frame_id; ROS 1: seq, sec, nsec, frame_id)."""
    raw = bytes(raw[:4096])
    if len(raw) < 16:
        raise ValueError(f"{what}: message of {len(raw)} bytes, expected a std_msgs/Header first")
    end = "<" if (not ros2 or raw[1] & 1) else ">"
    sec, nsec, n = struct.unpack(end + ("iII" if ros2 else "III"), raw[4:16])
    fid = raw[16: 16 + n].rstrip(b"\0").decode("utf-8", "replace") if n < 4080 else ""
    return sec * 1_000_000_000 + nsec, fid.lstrip("/")


_MCAP_MAGIC = b"\x89MCAP0\r\n"
_MCAP_FOOTER, _MCAP_CHUNK, _MCAP_CHUNK_INDEX = 0x02, 0x06, 0x08
_MAX_RATIO = 1000  # a chunk's records take at most this many times its compressed bytes


def check_mcap(path: Path) -> None:
    """An MCAP file's records (opcode, uint64 length) walked against the file's size, and each chunk's
    declared sizes against its own, before rosbags reads it: rosbags allocates what a length says,
    so one flipped byte would ask for terabytes. Records, not messages: a few per megabyte.
    One line naming the file and the record that lies, else nothing."""
    size = path.stat().st_size
    rec = struct.Struct("<BQ")
    if size < 2 * len(_MCAP_MAGIC):
        raise ValueError(f"{path}: not an MCAP file ({size} bytes; expected its magic at both ends); a recording "
                         f"cut short needs 'mcap recover'")
    with open(path, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as data:
        if data[:8] != _MCAP_MAGIC or data[size - 8:] != _MCAP_MAGIC:
            raise ValueError(f"{path}: not an MCAP file (expected its magic at both ends; {size} bytes); a "
                             f"recording cut short needs 'mcap recover'")
        pos, end, starts = 8, size - 8, {0}
        while pos < end:  # loop over the file's records (chunks, indexes, a footer: a few)
            starts.add(pos)
            if pos + 9 > end:
                raise ValueError(f"{path}: record at byte {pos} cut short (MCAP: opcode and length, 9 bytes)")
            op, n = rec.unpack_from(data, pos)
            if pos + 9 + n > end:
                raise ValueError(f"{path}: record at byte {pos} (opcode {op:#04x}) says {n:,} bytes; "
                                 f"{end - pos - 9:,} are left before the end magic")
            body = pos + 9
            if op == _MCAP_CHUNK and n >= 36:
                raw_size, = struct.unpack_from("<Q", data, body + 16)
                clen, = struct.unpack_from("<I", data, body + 28)
                if 32 + clen + 8 > n or raw_size > _MAX_RATIO * n:
                    raise ValueError(f"{path}: chunk at byte {pos} says {raw_size:,} bytes uncompressed from "
                                     f"{n:,} (compression name of {clen:,} bytes): the chunk lies")
            elif op == _MCAP_CHUNK_INDEX and n >= 36:  # where a chunk is and how large, as the summary says
                start, length, mlen = struct.unpack_from("<QQI", data, body + 16)
                tail = body + 36 + mlen + 8
                clen = struct.unpack_from("<I", data, tail)[0] if tail + 4 <= body + n else n
                sizes = struct.unpack_from("<QQ", data, tail + 4 + clen) if tail + 4 + clen + 16 <= body + n else None
                if start + length > size or sizes is None or sizes[0] > length or sizes[1] > _MAX_RATIO * max(length, 1):
                    raise ValueError(f"{path}: chunk index at byte {pos} says a chunk of {length:,} bytes at byte "
                                     f"{start:,} ({sizes} compressed, uncompressed); the file has {size:,} bytes")
            elif op == _MCAP_FOOTER and n >= 16:  # the last record: where the summary starts, a record's start
                summary = struct.unpack_from("<QQ", data, body)
                if not set(summary) <= starts:
                    raise ValueError(f"{path}: footer says the summary starts at byte {summary[0]:,} (offsets at "
                                     f"{summary[1]:,}), not where a record starts")
            pos += 9 + n


class _Bag:
    """The bag, opened once per thread for the lazy frame reads (``rosbags.highlevel.AnyReader``)."""

    def __init__(self, path: Path):
        self.path = path
        self._local = threading.local()

    def open(self):
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        r = getattr(self._local, "reader", None)
        if r is None:
            for f in ([self.path] if self.path.is_file() else sorted(self.path.glob("*.mcap"))):
                if f.suffix == ".mcap":
                    check_mcap(f)
            for f in ([self.path] if self.path.is_file() else sorted(p for p in self.path.iterdir() if p.is_file())):
                inputs.record(f, "capture")  # the bag's files (a ROS 2 folder: its storage and metadata.yaml)
            r = AnyReader([self.path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            try:
                r.open()
            except Exception as e:  # rosbags raises its own errors (and KeyError, struct.error) on a damaged bag
                raise ValueError(f"{self.path}: not a readable ROS bag ({type(e).__name__}: "
                                 f"{str(e).splitlines()[0] if str(e) else ''}); a recording cut short needs "
                                 f"'mcap recover' (MCAP) or 'rosbag reindex' (ROS 1)") from None
            self._local.reader = r
        return r

    def message(self, topic: str, t: int, ordinal: int):
        """The ``ordinal``-th message of ``topic`` recorded at ``t`` ns, deserialised."""
        r = self.open()
        conns = [c for c in r.connections if c.topic == topic]
        try:
            for k, (c, _, raw) in enumerate(r.messages(connections=conns, start=t, stop=t + 1)):
                if k == ordinal:
                    return r.deserialize(raw, c.msgtype)
        except Exception as e:
            raise ValueError(f"{self.path}: {topic} message at {t * 1e-9:.6f} s unreadable ({type(e).__name__}: "
                             f"{str(e).splitlines()[0] if str(e) else ''})") from None
        raise ValueError(f"{self.path}: {topic} has no message recorded at {t * 1e-9:.6f} s")


def _topics_line(topics: dict) -> str:
    return ", ".join(f"{n} ({i.msgtype})" for n, i in sorted(topics.items())) or "none"


def _pick(topics: dict, name: Optional[str], types, key: str, bag: Path, words=(), exclude=()) -> Optional[str]:
    """The topic ``name`` (checked: present, of one of ``types``), or for ``auto`` / None (where the
    key has no null meaning none) the one image topic whose name has one of ``words``."""
    if name is not None and name != "auto":
        if name not in topics:
            raise ValueError(f"{bag}: no topic {name} (scene.options.{key}); topics present: {_topics_line(topics)}")
        if topics[name].msgtype not in types:
            raise ValueError(f"{bag}: topic {name} (scene.options.{key}) is {topics[name].msgtype}, expected "
                             f"{' or '.join(types)}")
        return name
    cand = [n for n, i in topics.items() if i.msgtype in types and any(w in n.lower() for w in words)
            and not any(w in n.lower() for w in exclude)]
    cand = [n for n in cand if not (n.endswith("/compressed") and n[: -len("/compressed")] in cand)] or cand
    if len(cand) == 1:
        return cand[0]
    if key == "color_topic" and not cand:
        return None
    raise ValueError(f"{bag}: {'no' if not cand else 'several'} {' / '.join(words)} image topics "
                     f"({', '.join(sorted(cand)) or 'none'}): set scene.options.{key}; topics present: "
                     f"{_topics_line(topics)}")


def _info_topic(topics: dict, name: Optional[str], depth_topic: str, bag: Path) -> str:
    if name is not None:
        return _pick(topics, name, (INFO_TYPE,), "camera_info_topic", bag)
    base = depth_topic
    for suffix in ("/compressedDepth", "/compressed"):  # image_transport's sub-topics
        base = base[: -len(suffix)] if base.endswith(suffix) else base
    sibling = base.rsplit("/", 1)[0] + "/camera_info"
    if sibling in topics and topics[sibling].msgtype == INFO_TYPE:
        return sibling
    infos = [n for n, i in topics.items() if i.msgtype == INFO_TYPE]
    if len(infos) == 1:
        return infos[0]
    raise ValueError(f"{bag}: no CameraInfo topic {sibling} beside {depth_topic} and {len(infos)} others "
                     f"({', '.join(sorted(infos)) or 'none'}): set scene.options.camera_info_topic")


def _intrinsics(msg, bag: Path, topic: str) -> tuple[np.ndarray, Optional[tuple[int, int]], Optional[LensModel]]:
    """CameraInfo -> (3, 3) K, (H, W) it is for (None when width/height are 0), its lens (None when
    D is all zero: a rectified topic)."""
    K = np.asarray(getattr(msg, "k", None) if hasattr(msg, "k") else msg.K, np.float64).reshape(3, 3)
    D = np.asarray(getattr(msg, "d", None) if hasattr(msg, "d") else msg.D, np.float64).ravel()
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"{bag}: {topic} K = {K.ravel().tolist()}, expected fx, fy > 0")
    size = (int(msg.height), int(msg.width)) if msg.height and msg.width else None
    lens = ros_lens(msg.distortion_model, D, f"{bag}: {topic}") if np.any(D != 0) else None
    if lens is not None and size is None:
        raise ValueError(f"{bag}: {topic} has distortion D = {np.round(D, 5).tolist()} but width/height 0: "
                         f"expected the image size the calibration is for")
    return K, size, lens


def _undistorted(read: Callable[[], np.ndarray], K: np.ndarray, K_size: tuple[int, int], lens: LensModel,
                 order: int, fill) -> Callable[[], np.ndarray]:
    """``read`` resampled to the pinhole camera of the same K (the one undistortion, data/distortion.py):
    ``order`` 1 (colour) or 0 (depth, labels); an image of another size than the calibration's takes K scaled."""
    return lambda: undistort_image(read(), K, lens, order=order, fill=fill, K_size=K_size)


def _choose_topics(topics: dict, o: RosbagOptions, bag: Path) -> tuple:
    """(depth, colour or None, labels or None, CameraInfo, pose topic or None, [/tf, /tf_static present])
    of a bag's ``topics`` (name -> an object with ``msgtype``), as the keys say; one line otherwise."""
    depth_t = _pick(topics, o.depth_topic, IMAGE_TYPES, "depth_topic", bag, ("depth",))
    color_t = None if o.color_topic is None else _pick(topics, o.color_topic, IMAGE_TYPES, "color_topic", bag,
                                                       ("color", "rgb"), ("depth",))
    label_t = None if o.labels_topic is None else _pick(topics, o.labels_topic, IMAGE_TYPES, "labels_topic", bag)
    info_t = _info_topic(topics, o.camera_info_topic, depth_t, bag)
    pose_t = None if o.pose_topic is None else _pick(topics, o.pose_topic, POSE_TYPES, "pose_topic", bag)
    tf_t = [] if pose_t else [t for t in ("/tf", "/tf_static") if t in topics and topics[t].msgtype == TF_TYPE]
    if not pose_t and not tf_t:
        raise ValueError(f"{bag}: no /tf or /tf_static topic and no scene.options.pose_topic; topics present: "
                         f"{_topics_line(topics)}")
    return depth_t, color_t, label_t, info_t, pose_t, tf_t


@contextlib.contextmanager
def _readable(bag: Path):
    """Any error reading the bag's messages (a damaged chunk, a message that does not deserialise) as one
    line naming the bag (a line that names it already passes as it is)."""
    try:
        yield
    except Exception as e:  # rosbags raises its own errors (and KeyError, struct.error)
        if isinstance(e, ValueError) and str(e).startswith(str(bag)):
            raise
        raise ValueError(f"{bag}: unreadable messages ({type(e).__name__}: "
                         f"{str(e).splitlines()[0] if str(e) else ''})") from None


class _Pass:
    """The one pass over a bag's messages, in record order (a closed bag's, or a followed bag's as its
    records come): image messages indexed by (stamp, record time, ordinal among the topic's messages of
    that record time), the small ones (CameraInfo, tf, poses) decoded; :meth:`frames` makes the frames of
    what it has seen. ``topics``: the bag's (name -> an object with ``msgtype``), chosen from by the keys."""

    def __init__(self, o: RosbagOptions, bag: Path, ros2: bool, topics: dict):
        self.o, self.bag, self.ros2 = o, bag, ros2
        self.depth_t, self.color_t, self.label_t, self.info_t, self.pose_t, self.tf_t = _choose_topics(topics, o, bag)
        # per image topic: stamps, record times, ordinals
        self.images = {t: ([], [], []) for t in (self.depth_t, self.color_t, self.label_t) if t}
        self.depth_frame: Optional[str] = None
        self.info_msg = None
        self.edges: dict[str, _Track] = {}
        self.track = _Track("", False, f"{bag}: {self.pose_t}")
        self.pose_frame: Optional[str] = None
        self._last: dict[str, tuple[int, int]] = {}
        self.wanted = set(self.images) | {self.info_t, *self.tf_t} | ({self.pose_t} if self.pose_t else set())

    def add(self, topic: str, msgtype: str, t: int, raw, deserialize: Callable) -> Optional[int]:
        """One message of a wanted topic (record time ``t`` ns, ``raw`` serialised; ``deserialize(raw,
        msgtype)``); returns an image message's ordinal (:meth:`frames`' readers fetch it by it)."""
        o, bag = self.o, self.bag
        if topic in self.images:
            lt, n = self._last.get(topic, (None, 0))
            n = n + 1 if lt == t else 0
            self._last[topic] = (t, n)
            stamp, fid = _header(raw, self.ros2, f"{bag}: {topic}")
            s = self.images[topic]
            s[0].append(stamp if o.use_header_stamp else t), s[1].append(t), s[2].append(n)
            if topic == self.depth_t and self.depth_frame is None:
                self.depth_frame = fid
            return n
        if topic == self.info_t:
            if self.info_msg is None:
                self.info_msg = deserialize(raw, msgtype)
        elif topic == self.pose_t:
            m = deserialize(raw, msgtype)
            self.pose_frame = self.pose_frame or m.header.frame_id.lstrip("/")
            self.track.t.append(_stamp_ns(m.header.stamp) if o.use_header_stamp else t)
            self.track.v.append(_pose_values(m, msgtype))
        else:  # /tf, /tf_static
            for ts in deserialize(raw, msgtype).transforms:
                child, parent = ts.child_frame_id.lstrip("/"), ts.header.frame_id.lstrip("/")
                e = self.edges.setdefault(child, _Track(parent, topic == "/tf_static",
                                                        f"{bag}: {topic} {parent} -> {child}"))
                if e.parent != parent or e.static != (topic == "/tf_static"):
                    raise ValueError(f"{bag}: frame {child!r} has two parents in /tf + /tf_static ({e.parent!r} "
                                     f"and {parent!r}), expected one tf tree")
                e.t.append(_stamp_ns(ts.header.stamp)), e.v.append(_tf_values(ts.transform))
        return None

    def settled(self) -> int:
        """The latest depth stamp (ns) whose frame no later message can change, while the bag is written:
        every stream the frame is matched against has a message stamped beyond its window after it (colour
        and labels: ``max_time_diff``; the pose topic, or each moving tf link between the world and the
        camera: ``pose_max_time_diff``). Streams keep their stamps' order, as recorders write them."""
        o, none = self.o, np.iinfo(np.int64).min
        img_tol, pose_tol = int(o.max_time_diff * 1e9), int(o.pose_max_time_diff * 1e9)
        bounds = [max(self.images[t][0]) - img_tol for t in (self.color_t, self.label_t)
                  if t and self.images[t][0]]
        if self.color_t and not self.images[self.color_t][0]:
            return none
        if self.pose_t:
            tracks = [self.track]
        else:
            try:
                up_world, up_cam = _chain(self.edges, o.world_frame, o.camera_frame or self.depth_frame, self.bag)
            except ValueError:  # the chain's links are not all there yet
                return none
            tracks = [self.edges[f] for f in up_world + up_cam if not self.edges[f].static]
        for tr in tracks:  # loop over the few pose streams
            if not tr.t:
                return none
            bounds.append(max(tr.t) - pose_tol)
        return min(bounds) - 1 if bounds else none

    def frames(self, fetch: Callable, upto: Optional[int] = None,
               after: Optional[int] = None) -> tuple[list[CapturedFrame], np.ndarray, dict]:
        """The frames of the messages seen (readers only: ``fetch(topic, record time, ordinal)`` gives a
        message), their (F,) depth stamps (ns) and the statistics for ``scene.frames.info``. A bag still
        being written: ``upto``, only the depth images stamped up to it (ns), ``after`` (ns), only those
        stamped after it (the frames taken already are not made again); none is then no error."""
        o, bag, live = self.o, self.bag, upto is not None
        depth_t, color_t, label_t, info_t, pose_t = self.depth_t, self.color_t, self.label_t, self.info_t, self.pose_t
        if self.info_msg is None:
            if live:
                return [], np.zeros(0, np.int64), {}
            raise ValueError(f"{bag}: no message on {info_t} (scene.options.camera_info_topic)")
        K, K_size, lens = _intrinsics(self.info_msg, bag, info_t)
        d_st, d_rt, d_ord = (np.asarray(x, np.int64) for x in self.images[depth_t])
        order = np.argsort(d_st, kind="stable")
        if live:
            lo, hi = np.searchsorted(d_st[order], [np.iinfo(np.int64).min if after is None else after, upto],
                                     side="right")
            order = order[lo:hi]
        d_st, d_rt, d_ord = d_st[order], d_rt[order], d_ord[order]
        if len(d_st) == 0:
            if live:
                return [], np.zeros(0, np.int64), {}
            raise ValueError(f"{bag}: no message on {depth_t} (scene.options.depth_topic)")
        keep = np.ones(len(d_st), bool)
        info: dict = {"bag": str(bag), "depth_topic": depth_t, "n_frames_found": int(len(d_st))}
        if lens is not None:
            info["undistorted"] = lens.text()

        def match(topic):  # (index into the topic's sorted messages per depth frame, their arrays)
            st, rt, od = (np.asarray(x, np.int64) for x in self.images[topic])
            o2 = np.argsort(st, kind="stable")
            st, rt, od = st[o2], rt[o2], od[o2]
            j = associate(d_st * 1e-9, st * 1e-9, o.max_time_diff, one_to_one=False) if len(st) else \
                np.full(len(d_st), -1)
            return j, rt, od

        if color_t:
            cj, c_rt, c_ord = match(color_t)
            info["n_no_color"] = int(np.count_nonzero(cj < 0))
            keep &= cj >= 0
        if label_t:
            lj, l_rt, l_ord = match(label_t)
            info["n_no_labels"] = int(np.count_nonzero(keep & (lj < 0)))  # kept, without ground truth
        if pose_t:
            if not self.track.t:
                raise ValueError(f"{bag}: no message on {pose_t} (scene.options.pose_topic)")
            st, tr, q = self.track.arrays()
            T_wb, ok = interpolate_poses(st, tr, q, d_st, o.pose_max_time_diff * 1e9, o.pose_interpolation)
            T_bc = np.eye(4) if o.camera_in_body is None else pose_matrices(
                np.asarray(o.camera_in_body[:3], float)[None], np.asarray(o.camera_in_body[3:], float)[None])[0]
            T_wc = T_wb @ T_bc
            world = self.pose_frame
            camera = "(camera_in_body)" if o.camera_in_body is not None else pose_t
        else:
            world = o.world_frame
            camera = o.camera_frame or self.depth_frame
            if not world or not camera:
                raise ValueError(f"{bag}: scene.options.world_frame / camera_frame not set and the depth images "
                                 f"have no header.frame_id")
            T_wc, ok = _chain_poses(self.edges, world, camera, d_st, o.pose_max_time_diff, o.pose_interpolation, bag)
        info["n_no_pose"] = int(np.count_nonzero(keep & ~ok))
        keep &= ok
        info.update(world_frame=world, camera_frame=camera)
        sel = np.flatnonzero(keep)
        if len(sel) == 0 and not live:
            raise ValueError(f"{bag}: none of the {len(d_st)} depth images on {depth_t} has "
                             f"{'a colour image and ' if color_t else ''}a pose within max_time_diff="
                             f"{o.max_time_diff} s / pose_max_time_diff={o.pose_max_time_diff} s "
                             f"({info.get('n_no_color', 0)} without colour, {info['n_no_pose']} without pose)")
        if len(sel) < 0.5 * len(d_st) and not live:
            warnings.warn(f"{bag}: {len(d_st) - len(sel)} of {len(d_st)} depth images dropped "
                          f"({info.get('n_no_color', 0)} without colour, {info['n_no_pose']} without pose)",
                          stacklevel=3)
        T_cw = rigid_inverse(T_wc)  # every pose at once
        info["timestamps"] = (d_st[sel] * 1e-9).tolist()

        def reader(topic, t, n, convert, order=0, fill=0):
            what = f"{bag}: {topic} at {t * 1e-9:.6f} s"
            read = lambda: convert(*decode_image(fetch(topic, int(t), int(n)), what), what)  # noqa: E731
            return read if lens is None else _undistorted(read, K, K_size, lens, order, fill)

        scale = o.depth_scale
        frames = []
        for i in sel:  # one CapturedFrame (readers only) per kept depth message
            name = f"{d_st[i] // 1_000_000_000}.{d_st[i] % 1_000_000_000:09d}"
            frames.append(CapturedFrame(
                name=name, T_cw=T_cw[i], K=K, K_size=K_size, K_from=f"{bag}: {info_t} (width x height)",
                depth=reader(depth_t, d_rt[i], d_ord[i], lambda a, e, w: _to_depth(a, e, scale, w)),
                rgb=reader(color_t, c_rt[cj[i]], c_ord[cj[i]], _to_rgb, order=1) if color_t else None,
                labels=reader(label_t, l_rt[lj[i]], l_ord[lj[i]], _to_labels, fill=IGNORE)
                if label_t and lj[i] >= 0 else None))
        return frames, d_st[sel], info


def load_rosbag(o: RosbagOptions, taxonomy: Taxonomy) -> Scene:
    """The capture in the bag ``o.path`` (module docstring) as a Scene (lazy frames ordered by stamp);
    ``o.follow``: the bag followed as a recorder writes it (:func:`follow_rosbag`)."""
    if o.follow:
        return follow_rosbag(o, taxonomy)
    bag = Path(o.path)
    if not bag.exists():
        raise FileNotFoundError(f"ROS bag {bag} does not exist (scene.options.path)")
    handle = _Bag(bag)
    r = handle.open()
    one = _Pass(o, bag, r.is2, r.topics)
    conns = [c for c in r.connections if c.topic in one.wanted]
    with _readable(bag):
        for c, t, raw in r.messages(connections=conns):  # the one pass: metadata; small messages decoded
            one.add(c.topic, c.msgtype, t, raw, r.deserialize)
    frames, _, info = one.frames(handle.message)
    scene = capture_scene(bag.stem if bag.is_file() else bag.name, frames, o, taxonomy, root=bag, info=info)
    check_depth_unit(scene.frames[0], hint=f"scene.options.depth_scale={o.depth_scale} (16UC1 units per metre)")
    return scene


# --------------------------------------------------------------------------- a bag followed as it is written


class _McapTail:
    """An MCAP file read while a recorder writes it: from where the last :meth:`read` stopped, each record
    once it is whole on disk (its opcode, length and every byte it says); a chunk's messages once the
    whole chunk is (a chunk still being filled is not on disk at all: writers keep it in memory).
    ``done`` once the footer is read: the writer has closed the file."""

    def __init__(self, path: Path):
        self.path, self.pos, self.done = path, 0, False
        self.schemas: dict[int, tuple[str, str, bytes]] = {}  # id -> (type name, encoding, definition)
        self.channels: dict[int, tuple[str, int]] = {}  # id -> (topic, schema id)
        self._chunk: tuple[int, bytes] = (-1, b"")  # the last chunk decompressed (its record's offset)
        self._lock = threading.Lock()

    def read(self) -> list[tuple[str, str, int, memoryview, tuple[int, int, int]]]:
        """The messages of the records made whole since the last call: (topic, type name, record time ns,
        serialised message, where it lies: (chunk record offset or -1, offset, length))."""
        out: list = []
        try:
            fh = open(self.path, "rb")
        except FileNotFoundError:
            return out
        with fh:
            size = os.fstat(fh.fileno()).st_size
            if self.pos == 0:
                if size < len(_MCAP_MAGIC):
                    return out
                if fh.read(len(_MCAP_MAGIC)) != _MCAP_MAGIC:
                    raise ValueError(f"{self.path}: not an MCAP file (its first bytes are not the MCAP magic)")
                self.pos = len(_MCAP_MAGIC)
            while not self.done and self.pos + 9 <= size:  # loop over the whole records not read yet
                fh.seek(self.pos)
                op, n = struct.unpack("<BQ", fh.read(9))
                if self.pos + 9 + n > size:
                    break  # being written
                body = fh.read(n)
                if op == _MCAP_CHUNK:
                    data = self._decompress(body)
                    self._chunk = (self.pos, data)
                    at = 0
                    while at + 9 <= len(data):  # loop over the chunk's records
                        op2, n2 = struct.unpack_from("<BQ", data, at)
                        self._record(op2, memoryview(data)[at + 9: at + 9 + n2], self.pos, at + 9, out)
                        at += 9 + n2
                else:
                    self._record(op, memoryview(body), -1, self.pos + 9, out)
                self.done = op == _MCAP_FOOTER
                self.pos += 9 + n
        return out

    def _decompress(self, body: bytes) -> bytes:
        """A chunk record's records: (start, end, uncompressed size, crc, compression, records)."""
        raw_size, = struct.unpack_from("<Q", body, 16)
        clen, = struct.unpack_from("<I", body, 28)
        kind = body[32: 32 + clen].decode()
        n, = struct.unpack_from("<Q", body, 32 + clen)
        data = body[40 + clen: 40 + clen + n]
        if kind == "zstd":
            try:
                from compression import zstd  # Python 3.14
            except ImportError:
                from backports import zstd  # rosbags' own dependency
            data = zstd.decompress(data)
        elif kind == "lz4":
            from lz4.frame import decompress

            data = decompress(data)
        elif kind:
            raise ValueError(f"{self.path}: chunk compression {kind!r}, expected zstd, lz4 or none")
        if len(data) != raw_size:
            raise ValueError(f"{self.path}: a chunk of {len(data):,} bytes says {raw_size:,} (damaged)")
        return data

    def _record(self, op: int, body: memoryview, chunk: int, at: int, out: list) -> None:
        def text(k: int) -> tuple[str, int]:  # an MCAP string at k: uint32 length, UTF-8
            m, = struct.unpack_from("<I", body, k)
            return bytes(body[k + 4: k + 4 + m]).decode(), k + 4 + m

        if op == 0x03:  # Schema: id, name, encoding, data
            sid, = struct.unpack_from("<H", body, 0)
            name, k = text(2)
            enc, k = text(k)
            m, = struct.unpack_from("<I", body, k)
            self.schemas[sid] = (name, enc, bytes(body[k + 4: k + 4 + m]))
        elif op == 0x04:  # Channel: id, schema id, topic, ...
            cid, sid = struct.unpack_from("<HH", body, 0)
            self.channels[cid] = (text(4)[0], sid)
        elif op == 0x05:  # Message: channel id, sequence, log time, publish time, data
            cid, _, t = struct.unpack_from("<HIQ", body, 0)
            topic, sid = self.channels[cid]
            out.append((topic, self.schemas[sid][0] if sid in self.schemas else "", t, body[22:],
                        (chunk, at + 22, len(body) - 22)))

    def raw(self, where: tuple[int, int, int]) -> bytes:
        """A message's serialised bytes where :meth:`read` found it."""
        chunk, at, n = where
        with self._lock:
            if chunk < 0:
                with open(self.path, "rb") as fh:
                    fh.seek(at)
                    return fh.read(n)
            if self._chunk[0] != chunk:
                with open(self.path, "rb") as fh:
                    fh.seek(chunk)
                    _, size = struct.unpack("<BQ", fh.read(9))
                    self._chunk = (chunk, self._decompress(fh.read(size)))
            return self._chunk[1][at: at + n]


def _mcap_files(bag: Path) -> list[Path]:
    """A followed bag's MCAP files in recording order (a rosbag2 folder's split files, <name>_<n>.mcap, by n)."""
    if bag.suffix == ".mcap":
        return [bag] if bag.is_file() else []

    def order(p: Path):
        m = re.search(r"_(\d+)\.mcap$", p.name)
        return (int(m.group(1)) if m else -1, p.name)

    return sorted(bag.glob("*.mcap"), key=order) if bag.is_dir() else []


FOLLOW_SPAN_S = 0.5
"""A followed bag's topics are chosen once it holds this many seconds of messages (or is closed): every
topic of a recorder has published by then."""


def follow_rosbag(o: RosbagOptions, taxonomy: Taxonomy) -> Scene:
    """The bag ``o.path`` (a rosbag2 folder of MCAP files, or an .mcap file) followed as a recorder writes
    it (docs/online.md): polled for whole records; the topics chosen once :data:`FOLLOW_SPAN_S` seconds of
    messages are there; a frame taken once :meth:`_Pass.settled` says later messages cannot change it.
    Closed: an .mcap file once its footer is written; a rosbag2 folder once each MCAP file's footer is
    and ``metadata.yaml`` (the recorder writes it when it stops: ``ros2 bag record`` and rosbags' Writer)."""
    from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

    bag = Path(o.path)
    if bag.is_dir() and any(bag.glob("*.db3")):
        raise ValueError(f"{bag}: a rosbag2 folder of .db3 (SQLite) files; scene.options.follow=true reads MCAP "
                         f"storage (ros2 bag record -s mcap)")
    types = get_typestore(Stores.EMPTY)
    st: dict = {"tails": {}, "pass": None, "last": np.iinfo(np.int64).min, "types": set(), "locs": {}, "span": []}

    def deserialize(raw, msgtype: str):
        return types.deserialize_cdr(raw, msgtype)

    def read() -> tuple[list, bool]:
        files = _mcap_files(bag)
        msgs = []
        for f in files:  # loop over the bag's files, in recording order
            tail = st["tails"].setdefault(f, _McapTail(f))
            msgs += [(tail, *m) for m in tail.read()]
            for name, enc, data in tail.schemas.values():  # the bag's own message definitions
                if name not in st["types"] and data:
                    st["types"].add(name)
                    types.register(get_types_from_msg(data.decode(), name) if enc == "ros2msg"
                                   else get_types_from_idl(data.decode()))
        done = bool(files) and all(st["tails"][f].done for f in files) and (
            bag.suffix == ".mcap" or (bag / "metadata.yaml").is_file())
        return msgs, done

    def fetch(topic: str, t: int, n: int):
        tail, where, msgtype = st["locs"][(topic, t, n)]
        with _readable(bag):
            return deserialize(tail.raw(where), msgtype)

    def poll() -> bool:
        if st.get("closed"):
            return True
        with _readable(bag):
            msgs, closed = read()
            if st["pass"] is None:  # the topics are not chosen yet: the messages' times, their channels
                if msgs:
                    times = [m[3] for m in msgs] + st["span"]
                    st["span"] = [min(times), max(times)]
                span = st["span"]
                if not closed and (not span or span[1] - span[0] < FOLLOW_SPAN_S * 1e9):
                    follow.waiting = f"{FOLLOW_SPAN_S:g} s of messages in {bag}"
                    return False
                topics = {topic: SimpleNamespace(msgtype=tail.schemas[sid][0] if sid in tail.schemas else "")
                          for tail in st["tails"].values() for topic, sid in tail.channels.values()}
                try:
                    st["pass"] = _Pass(o, bag, True, topics)
                except ValueError as e:
                    if closed:
                        raise
                    follow.waiting = first_line(e)
                    return False
                st["tails"] = {}  # chosen: the bag is read again from its start for them
                msgs, closed = read()
            one: _Pass = st["pass"]
            for tail, topic, msgtype, t, raw, where in msgs:  # loop over the messages new since the last poll
                if topic in one.wanted:
                    n = one.add(topic, msgtype, t, raw, deserialize)
                    if n is not None:
                        st["locs"][(topic, t, n)] = (tail, where, msgtype)
            if not msgs and not closed:
                return False  # nothing new: nothing settled since the last poll
            try:
                frames, stamps, info = one.frames(fetch, None if closed else one.settled(), st["last"])
            except ValueError as e:
                if closed:
                    raise
                follow.waiting = first_line(e)
                return False
        if closed or "depth_topic" not in scene_info:  # the topics and frames read; the counts of the closed bag
            scene_info.update({k: v for k, v in info.items() if k != "timestamps"})
        for cf, s in zip(frames, stamps):  # loop over the frames settled: the new ones are added
            if s > st["last"]:
                follow.add(cf.name, cf.T_cw, cf)
                st["last"] = s
        st["closed"] = closed
        return closed

    follow = o.follower(poll, f"ROS bag {bag}")
    scene_info: dict = {"bag": str(bag)}
    return followed_capture(bag.stem if bag.suffix == ".mcap" else bag.name, follow, o, taxonomy, scene_info)


def load(cfg: SceneConfig, taxonomy: Taxonomy, sensor: Optional[SensorModel]) -> Scene:
    """``scene.source=rosbag``: the bag of ``scene.options`` (a :class:`RosbagOptions`; real depth)."""
    return load_rosbag(cfg.options, taxonomy)
