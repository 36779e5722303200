"""A recorder that writes a capture frame by frame at a sensor's rate, from another process, for the
tests of a capture followed as it is written (``scene.options.follow``, docs/online.md).

:func:`demo_frames` renders the demo room's frames (depth, a colour image of their classes, K, poses) and
:func:`save` puts them in an ``.npz``; :func:`start` runs this file as a process that writes them at
``rate`` Hz as

- ``folder``: a posed RGB-D folder (7-Scenes naming: ``camera-intrinsics.txt`` first, then per frame
  ``frame-XXXXXX.color.png``, ``.depth.png`` (16-bit mm) and ``.pose.txt`` (camera-to-world));
- ``bag``: a ROS 2 bag in MCAP storage as ``ros2 bag record -s mcap`` leaves it (rosbags' Writer:
  ``<folder>/<folder>.mcap``, zstd chunks, its footer written when it closes and then ``metadata.yaml``);
  a recorder closes a chunk once it is full (768 KiB for ``ros2 bag record``): here after each frame, so
  the frames reach the disk one by one. Its ``.mcap`` file alone is an MCAP capture of its own.

Every file and chunk reaches the disk in two halves a few milliseconds apart, so a follower also meets
half-written ones. The process prints nothing and exits 0 once the capture is closed. Messages: depth
``16UC1`` (mm), colour ``rgb8``, CameraInfo, ``/tf`` world -> camera_optical at each depth stamp.
Imports numpy, Pillow and rosbags only (a quick start)."""
from __future__ import annotations

import io
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

T0 = 1_700_000_000 * 10**9  # the first frame's stamp, ns
SPLIT_PAUSE_S = 0.003  # between a file's (or chunk's) two halves
GATE_AT = 20  # a gated recorder's first frame after the gate: a bag's follower takes frame 0 after 0.5 s of messages


def demo_frames(n: int, width: int = 64, height: int = 48) -> dict:
    """``n`` views of the demo room at ``width`` x ``height``: ``depth`` (n, H, W) float32 metres,
    ``rgb`` (n, H, W, 3) uint8 (the classes' colours), ``K`` (3, 3), ``c2w`` (n, 4, 4) camera-to-world."""
    from diffuser_lab import default_config
    from diffuser_lab.runs.pipeline import load_scene

    cfg = default_config(**{"scene.options.n_views": n, "scene.options.image_width": width,
                            "scene.options.image_height": height})
    scene = load_scene(cfg.scene)
    frames = [scene.frames[i] for i in range(n)]
    rgb = [scene.taxonomy.colorize(f.gt_labels) for f in frames]
    return {"depth": np.stack([f.depth for f in frames]).astype(np.float32), "rgb": np.stack(rgb).astype(np.uint8),
            "K": frames[0].K, "c2w": np.stack([np.linalg.inv(f.T_cw) for f in frames])}


def save(path: Path, frames: dict) -> Path:
    np.savez(path, **frames)
    return Path(path)


def start(kind: str, frames: Path, out: Path, rate: float = 30.0, gate: Path | None = None) -> subprocess.Popen:
    """This file as a process writing ``frames`` (:func:`save`'s file) to ``out`` as ``kind`` at ``rate`` Hz;
    with ``gate``, frames from :data:`GATE_AT` on once that file exists (:func:`_pace`)."""
    return subprocess.Popen([sys.executable, str(Path(__file__).resolve()), kind, str(frames), str(out), str(rate),
                             *([str(gate)] if gate is not None else [])],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


class _Halves(io.RawIOBase):
    """A binary file whose large writes reach the disk in two halves, :data:`SPLIT_PAUSE_S` apart."""

    def __init__(self, fh):
        self.fh = fh

    def write(self, b) -> int:
        b = bytes(b)
        if len(b) >= 1024:
            self.fh.write(b[: len(b) // 2])
            self.fh.flush()
            time.sleep(SPLIT_PAUSE_S)
        self.fh.write(b[len(b) // 2:] if len(b) >= 1024 else b)
        self.fh.flush()
        return len(b)

    def tell(self) -> int:
        return self.fh.tell()

    def close(self) -> None:
        self.fh.close()


def _write_file(path: Path, data: bytes) -> None:
    with open(path, "wb") as fh:
        _Halves(fh).write(data)


def _png(a: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format="PNG")
    return buf.getvalue()


def _pace(rate: float, n: int, gate: Path | None = None):
    """Yield 0..n-1, the i-th at the start time + i / rate; with ``gate``, frames from :data:`GATE_AT` on
    once that file exists (the follower has taken frame 0), paced from then."""
    t0 = time.monotonic()
    for i in range(n):  # loop over frames
        if i == GATE_AT and gate is not None:
            end = time.monotonic() + 120
            while not gate.exists() and time.monotonic() < end:
                time.sleep(0.005)
            t0 = time.monotonic() - i / rate
        time.sleep(max(0.0, t0 + i / rate - time.monotonic()))
        yield i


def write_folder(f: dict, root: Path, rate: float, gate: Path | None = None) -> None:
    root.mkdir(parents=True)
    np.savetxt(root / "camera-intrinsics.txt", f["K"])
    for i in _pace(rate, len(f["depth"]), gate):  # loop over frames: colour, depth, then the pose
        stem = root / f"frame-{i:06d}"
        _write_file(Path(f"{stem}.color.png"), _png(f["rgb"][i]))
        _write_file(Path(f"{stem}.depth.png"), _png(np.rint(f["depth"][i] * 1000).astype(np.uint16)))
        text = io.StringIO()
        np.savetxt(text, f["c2w"][i])
        _write_file(Path(f"{stem}.pose.txt"), text.getvalue().encode())


def write_bag(f: dict, path: Path, rate: float, gate: Path | None = None) -> None:
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    from scipy.spatial.transform import Rotation

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    types = {"/tf": "tf2_msgs/msg/TFMessage", "/camera/depth/camera_info": "sensor_msgs/msg/CameraInfo",
             "/camera/depth/image_raw": "sensor_msgs/msg/Image", "/camera/color/image_raw": "sensor_msgs/msg/Image"}
    w = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    w.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    w.open()
    w.storage.bio = _Halves(w.storage.bio)
    conns = {topic: w.add_connection(topic, typ, typestore=ts) for topic, typ in types.items()}
    K = f["K"]
    h, wd = f["depth"].shape[1:]

    def header(t):
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9),
                                        frame_id="camera_optical")

    def image(t, a, enc):
        a = np.ascontiguousarray(a)
        return T["sensor_msgs/msg/Image"](header=header(t), height=h, width=wd, encoding=enc, is_bigendian=0,
                                          step=a.strides[0], data=a.view(np.uint8).reshape(-1))

    for i in _pace(rate, len(f["depth"]), gate):  # loop over frames: one chunk each
        t = T0 + int(i * 1e9 / rate)
        c2w = f["c2w"][i]
        q = Rotation.from_matrix(c2w[:3, :3]).as_quat()
        V, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
        tf = T["geometry_msgs/msg/TransformStamped"](
            header=T["std_msgs/msg/Header"](stamp=header(t).stamp, frame_id="world"), child_frame_id="camera_optical",
            transform=T["geometry_msgs/msg/Transform"](translation=V(x=c2w[0, 3], y=c2w[1, 3], z=c2w[2, 3]),
                                                       rotation=Q(x=q[0], y=q[1], z=q[2], w=q[3])))
        info = T["sensor_msgs/msg/CameraInfo"](
            header=header(t), height=h, width=wd, distortion_model="plumb_bob", d=np.zeros(5), k=K.ravel(),
            r=np.eye(3).ravel(), p=np.hstack([K, np.zeros((3, 1))]).ravel(), binning_x=0, binning_y=0,
            roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
        depth = np.rint(f["depth"][i] * 1000).astype(np.uint16)
        for topic, m in (("/tf", T["tf2_msgs/msg/TFMessage"](transforms=[tf])), ("/camera/depth/camera_info", info),
                         ("/camera/depth/image_raw", image(t, depth, "16UC1")),
                         ("/camera/color/image_raw", image(t, f["rgb"][i], "rgb8"))):
            w.write(conns[topic], t, ts.serialize_cdr(m, types[topic]))
        w.storage.close_chunk()  # a full chunk, as a recorder's: on disk now
    w.close()


if __name__ == "__main__":
    kind, src, out, hz = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3]), float(sys.argv[4])
    go = Path(sys.argv[5]) if len(sys.argv) > 5 else None
    data = dict(np.load(src))
    if kind == "folder":
        write_folder(data, out, hz, go)
    else:
        write_bag(data, out, hz, go)
