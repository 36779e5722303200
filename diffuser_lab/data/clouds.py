"""Point cloud files in and out: PLY, LAS and LAZ (the cloud to label, the labelled result).

:func:`read_cloud` reads any of them by extension -> ``points`` (N, 3) float32 metres and, when the
file has them, ``colors`` (N, 3) uint8, ``normals`` (N, 3) float32 unit, ``labels`` (N,) int64 (a
PLY's ``label`` property; a LAS/LAZ file's ``label`` extra dimension, as :func:`write_las` writes
it), with ``source`` naming the file.

:func:`write_las` writes labelled points as LAS 1.4 (point format 7: x y z, RGB) or LAZ
(compressed through laspy's ``lazrs`` backend): the class goes to the ``classification`` field as
``class id + 1`` (0 = unlabelled: LAS reserves 0 for "never classified"), the exact id (-1 =
unlabelled) to an extra dimension ``label``, and the taxonomy's names to a VLR
(``diffuser-lab``/``classes``, JSON ``{"1": "wall", ...}``) and a side file ``<name>.classes.json``.

:func:`write_pointcloud2_bag` writes them as a ROS 2 bag (MCAP storage) with one
``sensor_msgs/msg/PointCloud2`` message that rviz2 and Foxglove display; :func:`read_pointcloud2_bag`
reads it back.
"""
from __future__ import annotations

import json
import struct
import time
from pathlib import Path
from typing import Optional

import numpy as np

from diffuser_lab.data import inputs
from diffuser_lab.data.scene import IGNORE, Taxonomy

__all__ = ["read_cloud", "read_point_cloud_ply", "read_las", "write_las", "write_pointcloud2_bag",
           "read_pointcloud2_bag", "CLOUD_SUFFIXES"]

CLOUD_SUFFIXES = (".ply", ".las", ".laz")


def read_cloud(path: str | Path) -> dict:
    """A PLY, LAS or LAZ file -> dict (module docstring); one line naming the file otherwise."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in CLOUD_SUFFIXES:
        raise ValueError(f"{path}: point cloud of unknown type {suffix or '(no suffix)'}, expected one of "
                         f"{', '.join(CLOUD_SUFFIXES)}")
    out = read_point_cloud_ply(path) if suffix == ".ply" else read_las(path)
    inputs.record(path, "cloud")  # after the reader: a missing or unreadable file is its one line
    out["source"] = path.name
    return out


def read_point_cloud_ply(path: str | Path) -> dict:
    """PLY vertices -> dict with ``points`` (N, 3) float32 and, when present, ``colors``
    (N, 3) uint8, ``normals`` (N, 3) float32 unit, ``labels`` (N,) int64 (property ``label``)."""
    from plyfile import PlyData

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"point cloud {path} does not exist")
    try:
        ply = PlyData.read(str(path))
    except Exception as e:  # plyfile raises several types for corrupt files
        raise ValueError(f"{path}: not a readable PLY file ({type(e).__name__}: {e})") from None
    if "vertex" not in ply:
        raise ValueError(f"{path}: PLY has no 'vertex' element, expected points with x, y, z")
    v = ply["vertex"].data
    names = set(v.dtype.names or ())
    if not {"x", "y", "z"} <= names or len(v) == 0:
        raise ValueError(f"{path}: PLY vertices lack x/y/z or are empty, expected points in metres")
    out = {"points": np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float32)}
    if {"red", "green", "blue"} <= names:
        out["colors"] = np.stack([v["red"], v["green"], v["blue"]], 1).astype(np.uint8)
    if {"nx", "ny", "nz"} <= names:
        n = np.stack([v["nx"], v["ny"], v["nz"]], 1).astype(np.float32)
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        out["normals"] = np.where(norm > 0, n / np.maximum(norm, 1e-12), 0).astype(np.float32)
    if "label" in names:
        out["labels"] = np.asarray(v["label"]).astype(np.int64)
    return out




# LAS 1.0-1.4 point formats 0-10: the smallest record (bytes) each can have
_LAS_RECORD = {0: 20, 1: 28, 2: 26, 3: 34, 4: 57, 5: 63, 6: 30, 7: 36, 8: 38, 9: 59, 10: 67}
_LAZ_MAX_RATIO = 1000  # a LAZ file's points take at most this many times its compressed bytes


def check_las_header(path: Path) -> Optional[int]:
    """What a LAS/LAZ public header declares (ASPRS LAS 1.0-1.4: version, header size, point data
    offset, VLR and EVLR counts, point format, record length, point count) against the file's size,
    before laspy reads it: laspy loops over the declared VLRs and allocates the declared points, so
    a file that is garbage after its ``LASF`` magic would keep it busy for minutes. One line naming
    the file and the field that lies; else the bytes a LAZ file's points decode to (points x record
    length), None for an uncompressed LAS."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        h = fh.read(375)
    if len(h) < 227 or h[:4] != b"LASF":
        raise ValueError(f"{path}: not a LAS/LAZ file (expected the 'LASF' signature and a header of at least "
                         f"227 bytes; the file has {size} bytes)")
    major, minor = h[24], h[25]
    if major != 1 or minor > 4:
        raise ValueError(f"{path}: LAS version {major}.{minor} in the header, expected 1.0-1.4")
    header_size, offset, n_vlrs, fmt, rec_len, n_points = struct.unpack_from("<HIIBHI", h, 94)
    need_header = 375 if minor >= 4 else 235 if minor == 3 else 227
    if not need_header <= header_size <= offset <= size:
        raise ValueError(f"{path}: LAS header says a {header_size}-byte header (LAS 1.{minor}: at least {need_header}) "
                         f"and points from byte {offset}; the file has {size} bytes")
    if n_vlrs * 54 > offset - header_size:
        raise ValueError(f"{path}: LAS header says {n_vlrs:,} VLRs (54 bytes each at least) in the "
                         f"{offset - header_size:,} bytes between header and points")
    compressed, pf = bool(fmt & 0xC0), fmt & 0x3F  # LAZ sets bit 7 (and 6) of the format id
    if pf not in _LAS_RECORD or rec_len < _LAS_RECORD[pf]:
        raise ValueError(f"{path}: LAS header says point format {pf} with {rec_len}-byte records, expected "
                         f"format 0-10 with at least its fields' bytes")
    if minor >= 4:
        start_evlr, n_evlrs, n64 = struct.unpack_from("<QIQ", h, 235)
        n_points = n64 or n_points
        if n_evlrs and not (offset <= start_evlr and start_evlr + n_evlrs * 60 <= size):
            raise ValueError(f"{path}: LAS header says {n_evlrs:,} EVLRs (60 bytes each at least) from byte "
                             f"{start_evlr:,}; the file has {size:,} bytes")
    data = n_points * rec_len
    if not compressed and offset + data > size:
        raise ValueError(f"{path}: LAS header says {n_points:,} points of {rec_len} bytes from byte {offset:,} "
                         f"({offset + data:,} bytes); the file has {size:,} bytes (truncated, or the header lies)")
    if compressed and data > _LAZ_MAX_RATIO * max(size - offset, 1):
        raise ValueError(f"{path}: LAZ header says {n_points:,} points of {rec_len} bytes ({data / 2**20:,.0f} MiB) "
                         f"from {size - offset:,} compressed bytes, more than {_LAZ_MAX_RATIO}x: the header lies")
    return data if compressed else None


def read_las(path: str | Path) -> dict:
    """LAS / LAZ -> dict (module docstring): scaled x y z (metres, as the file's CRS has them),
    RGB (16-bit scaled to 8 when any value exceeds 255), the ``label`` extra dimension if present.

    A LAZ file is decoded in a child process (:func:`_laz_in_child`): its decoder (lazrs, Rust)
    aborts the whole process when a damaged file makes it allocate more than it can (a lying chunk
    or layer size), which would end a run without a line; the child's end becomes one."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"point cloud {path} does not exist")
    decoded = check_las_header(path)
    return _read_las_here(path) if decoded is None else _laz_in_child(path, decoded)


_LAZ_CHILD = """
import sys
import numpy as np
from diffuser_lab.data.clouds import _read_las_here
try:
    out = _read_las_here(sys.argv[1])
except Exception as e:
    print("diffuser-lab-laz: " + (str(e).splitlines()[0] if str(e) else type(e).__name__), file=sys.stderr)
    sys.exit(3)
np.savez(sys.argv[2], **out)
"""


def _laz_in_child(path: Path, decoded: int) -> dict:
    """:func:`_read_las_here` of the LAZ ``path`` in a child interpreter (a fresh one: a fork would
    inherit the decoder's thread pool without its threads), its address space bounded by 3x the
    ``decoded`` bytes its header declares (:func:`check_las_header`) + 3 GiB, the arrays back through a
    temporary ``.npz``: its arrays, or one line naming the file when it fails or dies (~0.3 s of start-up)."""
    import resource
    import signal
    import subprocess
    import sys
    import tempfile

    limit = 3 * decoded + (3 << 30)

    def bounded():  # in the child: a lying size fails its allocation instead of swapping the machine
        _, hard = resource.getrlimit(resource.RLIMIT_AS)
        resource.setrlimit(resource.RLIMIT_AS, (limit if hard == resource.RLIM_INFINITY else min(limit, hard), hard))

    with tempfile.TemporaryDirectory(prefix="diffuser-lab-laz-") as tmp:
        out = Path(tmp) / "cloud.npz"
        p = subprocess.run([sys.executable, "-c", _LAZ_CHILD, str(path), str(out)], capture_output=True, text=True,
                           errors="replace", preexec_fn=bounded)
        if p.returncode == 0:
            with np.load(out) as z:
                return {k: z[k] for k in z.files}
        lines = [ln.strip() for ln in p.stderr.splitlines() if ln.strip()]
        own = [ln[len("diffuser-lab-laz: "):] for ln in lines if ln.startswith("diffuser-lab-laz: ")]
        if p.returncode == 3 and own:  # the reader's own line (it names the file)
            raise ValueError(own[-1])
        how = f"signal {signal.Signals(-p.returncode).name}" if p.returncode < 0 else f"exit status {p.returncode}"
        raise ValueError(f"{path}: the LAZ decoder stopped ({how}: {lines[0][:160] if lines else 'no message'}): "
                         f"a damaged LAZ file, or one whose sizes lie")


def _read_las_here(path: str | Path) -> dict:
    """LAS / LAZ -> dict, decoded in this process (laspy; lazrs for LAZ)."""
    import laspy

    path = Path(path)
    try:
        las = laspy.read(str(path))
    except Exception as e:  # laspy raises several types for truncated or foreign files
        raise ValueError(f"{path}: not a readable LAS/LAZ file ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})") from None
    if len(las.points) == 0:
        raise ValueError(f"{path}: LAS/LAZ file holds no points, expected points in metres")
    out = {"points": np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], 1).astype(np.float32)}
    dims = set(las.point_format.dimension_names)
    if {"red", "green", "blue"} <= dims:
        rgb = np.stack([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)], 1)
        if rgb.max(initial=0) > 255:
            rgb = rgb >> 8
        out["colors"] = rgb.astype(np.uint8)
    if "label" in dims:
        out["labels"] = np.asarray(las["label"]).astype(np.int64)
    return out


def write_las(path: str | Path, points: np.ndarray, labels: np.ndarray, names, colors: np.ndarray | None = None,
              extra: Optional[dict] = None) -> list[Path]:
    """Labelled points -> LAS (``.las``) or LAZ (``.laz``) at ``path`` (module docstring).

    Args:
        points: (N, 3) world metres. labels: (N,) int class ids, -1 = unlabelled.
        names: the taxonomy's class names (class id c -> ``names[c]``).
        colors: (N, 3) uint8 (e.g. the class colours); None = no RGB.
        extra: {name: (N,) float32} more extra dimensions (float32), e.g. a run's per-point confidence.
    Returns:
        The files written (the cloud and its ``.classes.json``).
    """
    import laspy

    path = Path(path)
    if len(names) > 254:
        raise ValueError(f"{path}: {len(names)} classes do not fit LAS classification (at most 254 besides 0)")
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.add_extra_dim(laspy.ExtraBytesParams(name="label", type=np.int16, description="class id, -1 unlabelled"))
    for name in extra or {}:
        header.add_extra_dim(laspy.ExtraBytesParams(name=name, type=np.float32))
    pts = np.asarray(points, np.float64)
    header.offsets = np.floor(pts.min(0)) if len(pts) else np.zeros(3)
    header.scales = np.array([1e-4, 1e-4, 1e-4])  # 0.1 mm: below any cloud's noise
    classes = {str(c + 1): str(n) for c, n in enumerate(names)}
    header.vlrs.append(laspy.VLR(user_id="diffuser-lab", record_id=1, description="classes",
                                 record_data=json.dumps(classes).encode()))
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    lab = np.asarray(labels).astype(np.int64)
    las.classification = np.where(lab >= 0, lab + 1, 0).astype(np.uint8)
    las["label"] = lab.astype(np.int16)
    for name, values in (extra or {}).items():
        las[name] = np.asarray(values, np.float32)
    if colors is not None:
        c = np.asarray(colors, np.uint16) * 257  # 8 -> 16 bit, as LAS stores colour
        las.red, las.green, las.blue = c[:, 0], c[:, 1], c[:, 2]
    las.write(str(path))
    side = path.with_name(path.stem + ".classes.json")
    side.write_text(json.dumps({"classification": "class id + 1 (0 = unlabelled)", "classes": classes}, indent=1))
    return [path, side]


# --------------------------------------------------------------------------- ROS 2 PointCloud2 bags


_PC2_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<f4"), ("label", "<i4")])


def write_pointcloud2_bag(path, points: np.ndarray, labels: np.ndarray, taxonomy: Taxonomy, frame_id: str = "map",
                          topic: str = "/diffuser_lab/labels", stamp_ns: int | None = None,
                          ignore_color=(128, 128, 128)) -> Path:
    """Labelled points as a ROS 2 bag (MCAP storage, CDR, ROS 2 Humble message definitions).

    One ``sensor_msgs/msg/PointCloud2`` on ``topic``: fields x y z (float32, metres in ``frame_id``),
    rgb (float32 holding the packed 0x00RRGGBB bytes, as rviz reads it: the class colours; IGNORE
    ``ignore_color``) and label (int32 class id, -1 = IGNORE); height 1, little endian, dense.

    Args:
        path: the bag folder to create (``<path>/<name>.mcap`` + ``metadata.yaml``); must not exist.
        points: (N, 3) world metres. labels: (N,) class ids of ``taxonomy``.
        stamp_ns: header stamp and record time; None = now.
    Returns:
        the ``.mcap`` file (Foxglove opens it as it is; ``ros2 bag play`` takes the folder).
    """
    from rosbags.rosbag2 import StoragePlugin, Writer, WriterError
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    points = np.asarray(points, np.float32).reshape(-1, 3)
    labels = np.asarray(labels).reshape(-1)
    if len(labels) != len(points):
        raise ValueError(f"{path}: {len(points)} points but {len(labels)} labels")
    ts = get_typestore(Stores.ROS2_HUMBLE)
    PointCloud2, PointField = ts.types["sensor_msgs/msg/PointCloud2"], ts.types["sensor_msgs/msg/PointField"]
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    rgb = taxonomy.colorize(labels, ignore_color).astype(np.uint32)
    packed = (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
    rec = np.empty(len(points), _PC2_DTYPE)
    rec["x"], rec["y"], rec["z"] = points[:, 0], points[:, 1], points[:, 2]
    rec["rgb"] = packed.view(np.float32)
    rec["label"] = np.where(labels == IGNORE, -1, labels).astype(np.int32)
    stamp = time.time_ns() if stamp_ns is None else int(stamp_ns)
    fields = [PointField(name=n, offset=_PC2_DTYPE.fields[n][1], datatype=d, count=1)
              for n, d in (("x", 7), ("y", 7), ("z", 7), ("rgb", 7), ("label", 5))]  # 7 FLOAT32, 5 INT32
    msg = PointCloud2(header=Header(stamp=Time(sec=stamp // 1_000_000_000, nanosec=stamp % 1_000_000_000),
                                    frame_id=frame_id),
                      height=1, width=len(points), fields=fields, is_bigendian=False,
                      point_step=_PC2_DTYPE.itemsize, row_step=_PC2_DTYPE.itemsize * len(points),
                      data=rec.view(np.uint8).reshape(-1), is_dense=True)
    try:
        with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
            conn = w.add_connection(topic, PointCloud2.__msgtype__, typestore=ts)
            w.write(conn, stamp, ts.serialize_cdr(msg, PointCloud2.__msgtype__))
    except WriterError as e:
        raise FileExistsError(f"{path}: {e}") from None
    return next(path.glob("*.mcap"))


def read_pointcloud2_bag(path, topic: str = "/diffuser_lab/labels") -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """What :func:`write_pointcloud2_bag` wrote: (N, 3) float32 points, (N,) int32 labels, (N, 3) uint8
    colours and the frame_id (the first message on ``topic``)."""
    from rosbags.highlevel import AnyReader

    with AnyReader([Path(path)]) as r:
        conns = [c for c in r.connections if c.topic == topic]
        if not conns:
            raise ValueError(f"{path}: no topic {topic}; topics present: {', '.join(sorted(r.topics)) or 'none'}")
        c, _, raw = next(r.messages(connections=conns))
        m = r.deserialize(raw, c.msgtype)
    fields = [(f.name, int(f.offset), int(f.datatype)) for f in m.fields]
    want = [(n, _PC2_DTYPE.fields[n][1], d) for n, d in (("x", 7), ("y", 7), ("z", 7), ("rgb", 7), ("label", 5))]
    n = int(m.width) * int(m.height)
    if fields != want or m.point_step != _PC2_DTYPE.itemsize or m.is_bigendian or len(m.data) != n * m.point_step:
        raise ValueError(f"{path}: {topic} declares {m.width} x {m.height} points of {m.point_step} bytes, fields "
                         f"{fields} with {len(m.data)} data bytes; expected the fields {want} of "
                         f"write_pointcloud2_bag, little endian, {_PC2_DTYPE.itemsize} bytes a point")
    rec = np.frombuffer(np.asarray(m.data, np.uint8).tobytes(), _PC2_DTYPE)
    p = rec["rgb"].view(np.uint32)
    cols = np.stack([(p >> 16) & 255, (p >> 8) & 255, p & 255], 1).astype(np.uint8)
    return np.stack([rec["x"], rec["y"], rec["z"]], 1), rec["label"].copy(), cols, m.header.frame_id
