"""run.mcap's message formats (see :mod:`.mcap_write` for the channels): the point clouds
(foxglove.PointCloud, packed RGBA colours, int16 labels), the Z states (diffuser_lab.ZState:
float32 or float16, stored class-major) serialised straight into reused buffers, the cameras
(foxglove.FrameTransform, CameraCalibration, CompressedImage of the label image as a palette
PNG), and their decoders. Nothing here opens a file."""
from __future__ import annotations

from typing import Any, Optional

import numpy as np

from diffuser_lab.backends.records import shares, to_float16, transpose_into
from diffuser_lab.data.scene import IGNORE

from . import schema

TOPIC_SCENE = "/scene/points"
TOPIC_EVIDENCE = "/evidence/bayesian"
TOPIC_RUN = "/diffuser_lab/run"
TOPIC_LABELS = "/diffusion/labels"
TOPIC_METRICS = "/diffuser_lab/metrics"
TOPIC_Z = "/diffuser_lab/z"
TOPIC_TF = "/tf"
TOPIC_CALIBRATION = "/cameras/calibration"
TOPIC_CAMERA_LABELS = "/cameras/labels"
TOPIC_ONLINE_FRAME = "/diffuser_lab/online/frame"
TOPIC_ONLINE_LABELS = "/online/labels"
TOPIC_TILED_LABELS = "/tiled/labels"
TOPIC_TILED_TILES = "/tiled/tiles"
TOPIC_TILED_RECORDS = "/diffuser_lab/tiles"
TOPIC_FEATURE_VIEW = "/diffuser_lab/features/pca"
TOPIC_FEATURES = "/diffuser_lab/features"
TOPIC_TARGET = "/diffuser_lab/single_frame/target"
TOPIC_TARGET_ROWS = "/diffuser_lab/single_frame/rows"
TOPIC_TARGET_IMAGES = "/single_frame/labels"
FRAME_ID = "world"
FRAME_STEP_NS = 100_000_000
"""run.mcap's timeline of an online run: frame i at the run's start + (i + 1) x 100 ms."""
UNLABELED_INDEX = 255
"""Palette index of unlabeled pixels (IGNORE) in the label PNGs; class c is index c."""
MAGIC = b"\x89MCAP0\r\n"


def _cloud_dtype() -> np.dtype:
    return np.dtype({"names": ["x", "y", "z", "red", "green", "blue", "alpha", "label"],
                     "formats": ["<f4", "<f4", "<f4", "u1", "u1", "u1", "u1", "<i2"]})


def packed_cloud(points: np.ndarray) -> np.ndarray:
    """(P, 3) points -> a packed cloud (:func:`_cloud_dtype`) with x y z set, opaque, label -1."""
    buf = np.zeros(len(points), _cloud_dtype())
    for i, ax in enumerate("xyz"):
        buf[ax] = points[:, i]
    buf["alpha"] = 255
    buf["label"] = -1
    return buf


def point_cloud(buf: np.ndarray, stamp_ns: int, with_data: bool = True) -> Any:
    """A foxglove.PointCloud of the packed structured array ``buf`` (without its ``data``
    field when not ``with_data``)."""
    from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

    kinds = {"<f4": PackedElementField.FLOAT32, "|u1": PackedElementField.UINT8, "<i2": PackedElementField.INT16}
    msg = PointCloud(frame_id=FRAME_ID, point_stride=buf.dtype.itemsize)
    msg.timestamp.FromNanoseconds(stamp_ns)
    msg.pose.position.SetInParent()  # an unset position reads as a null translation in Rerun's loader
    msg.pose.orientation.w = 1.0
    for name in buf.dtype.names:
        dt, off = buf.dtype.fields[name][:2]
        msg.fields.add(name=name, offset=off, type=kinds[dt.str])
    if with_data:
        msg.data = buf.tobytes()
    return msg


def point_cloud_bytes(buf: np.ndarray, stamp_ns: int, out: Optional[bytearray] = None) -> memoryview:
    """``point_cloud(buf, stamp_ns).SerializeToString()`` with ``buf`` copied once, into ``out``
    (see :func:`_with_bytes_field`); ``data`` is PointCloud's last field (6)."""
    head = point_cloud(buf, stamp_ns, with_data=False).SerializeToString()
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


Z_BITS = {"q8": 8, "q16": 16}
"""Bits per share of the quantised Z precisions."""


def z_state_bytes(iteration: int, Z: np.ndarray, dtype: str, out: Optional[bytearray] = None,
                  class_major: bool = True, labels: Optional[np.ndarray] = None) -> memoryview:
    """``ZState(...).SerializeToString()`` with Z copied once (transposed when ``class_major``)
    into ``out`` (see :func:`_with_bytes_field`); ``data`` is field 5. ``dtype``: float32 (exact),
    float16 (Z / max Z), q8 / q16 (row sums + shares, always class-major). ``labels`` (M,) int:
    the exact Z's labels, stored with an inexact state (field 9) so readers keep the run's own."""
    lab = b"" if labels is None or dtype == "float32" else np.asarray(labels, "<i2").tobytes()
    if dtype in Z_BITS:
        sums, q = shares(np.ascontiguousarray(Z, np.float32), Z_BITS[dtype])
        head = schema.ZState(iteration=int(iteration), n_points=Z.shape[0], n_classes=Z.shape[1],
                             dtype=dtype).SerializeToString()
        tail = schema.ZState(scale=1.0, class_major=True, row_sums=sums.astype("<f4").tobytes(),
                             labels=lab).SerializeToString()
        mv, at = _with_bytes_field(head, 5, q.nbytes, tail, out)
        np.frombuffer(mv, np.uint8, q.nbytes, at)[:] = q.reshape(-1).view(np.uint8)
        return mv
    scale = _z_scale(Z, dtype)
    stored = np.dtype("<f2" if dtype == "float16" else "<f4")
    head = schema.ZState(iteration=int(iteration), n_points=Z.shape[0], n_classes=Z.shape[1],
                         dtype=dtype).SerializeToString()
    tail = schema.ZState(scale=scale, class_major=bool(class_major), labels=lab).SerializeToString()
    mv, at = _with_bytes_field(head, 5, Z.size * stored.itemsize, tail, out)
    body = np.frombuffer(mv, stored, Z.size, at).reshape(Z.shape[::-1] if class_major else Z.shape)

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


def z_precision_text(dtype: str) -> str:
    """What a stored Z state's precision means, in one phrase (``diffuser-lab-inspect --at``)."""
    if dtype in Z_BITS:
        levels = (1 << Z_BITS[dtype]) - 1
        return (f"{dtype}: row sums exact, shares Z_ic / sum_c Z_ic in 1/{levels} steps "
                f"(|error| <= {0.5 / levels:.2g} of the row's sum)")
    if dtype == "float16":
        return "float16: Z / max Z as float16 (relative error <= 2^-11 above 6e-5 max Z)"
    return "float32: exact"


class RawMessage:
    """An already serialized message (what the writer thread calls SerializeToString on);
    ``done`` is called once the writer has copied it (returns a pooled buffer)."""

    __slots__ = ("data", "done")

    def __init__(self, data, done=None):
        self.data, self.done = data, done

    def SerializeToString(self):  # noqa: N802 - protobuf's name
        return self.data


def decode_z(msg: Any) -> np.ndarray:
    """diffuser_lab.ZState -> (M, C) float32 Z in the paper's units (q8 / q16: row sum x share,
    see :func:`z_precision_text` for the error)."""
    if msg.dtype in Z_BITS:
        q = np.frombuffer(msg.data, "<u1" if Z_BITS[msg.dtype] == 8 else "<u2").reshape(msg.n_classes, msg.n_points)
        sums = np.frombuffer(msg.row_sums, "<f4")
        Z = q.T.astype(np.float32, order="C")
        Z *= (sums / np.float32((1 << Z_BITS[msg.dtype]) - 1))[:, None]
        return Z
    dt = "<f2" if msg.dtype == "float16" else "<f4"
    if msg.class_major:
        Z = np.frombuffer(msg.data, dt).reshape(msg.n_classes, msg.n_points).T.astype(np.float32, order="C")
    else:
        Z = np.frombuffer(msg.data, dt).reshape(msg.n_points, msg.n_classes).astype(np.float32)
    if msg.scale not in (0.0, 1.0):
        Z *= np.float32(msg.scale)
    return Z


# -- cameras -------------------------------------------------------------------------------------
def camera_frame_id(index: int) -> str:
    """The TF frame of camera ``index`` (child of ``world``): ``camera_0007``."""
    return f"camera_{int(index):04d}"


def camera_index(frame_id: str) -> int:
    """:func:`camera_frame_id` backwards."""
    return int(frame_id.rsplit("_", 1)[1])


def strided(img: np.ndarray, K: np.ndarray, max_side: int) -> tuple[np.ndarray, np.ndarray]:
    """Image (H, W, ...) strided by s = ceil(max(H, W) / max_side) (what run.rrd stores) and the
    (3, 3) intrinsics of the strided image: pixel (u, v) of the full image is (u / s, v / s)."""
    h, w = img.shape[:2]
    s = int(np.ceil(max(h, w) / max_side))
    K = np.asarray(K, np.float64)
    if s <= 1:
        return img, K
    K = K.copy()
    K[:2, :] /= s
    return img[::s, ::s], K


PNG_LEVEL = 3
"""zlib level of the label PNGs (flat regions compress well at any level): a 160 x 120 demo
label image takes 1.6 kB at level 3, 1.3 kB at 6 (at 3x the time)."""


def _png(pixels: np.ndarray, palette: Optional[np.ndarray] = None) -> bytes:
    """A PNG of (H, W) palette indices with ``palette`` (P, 3) uint8, or of (H, W, 3) RGB; 8 bits,
    no row filter. Written here (zlib and struct) so that the recording thread imports no
    image library (Pillow's import and plugin registration cost ~35 ms)."""
    import struct
    import zlib

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    h, w = pixels.shape[:2]
    rows = np.zeros((h, 1 + pixels[0].size), np.uint8)  # each row: filter byte 0, then the pixels
    rows[:, 1:] = pixels.reshape(h, -1)
    head = struct.pack(">IIBBBBB", w, h, 8, 2 if palette is None else 3, 0, 0, 0)
    plte = b"" if palette is None else chunk(b"PLTE", np.asarray(palette, np.uint8).tobytes())
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", head) + plte
            + chunk(b"IDAT", zlib.compress(rows.tobytes(), PNG_LEVEL)) + chunk(b"IEND", b""))


def label_png(labels: np.ndarray, colors: np.ndarray, unlabeled=(70, 70, 70)) -> bytes:
    """(H, W) class ids (IGNORE = -1) -> PNG bytes. Up to 255 classes: a palette PNG whose pixel
    values are the class ids (unlabeled: :data:`UNLABELED_INDEX`) and whose palette is the
    taxonomy's colours ``colors`` (C, 3) uint8, so viewers show colours and the ids come back
    exactly (:func:`decode_label_png`); more classes: RGB of those colours."""
    colors = np.asarray(colors, np.uint8).reshape(-1, 3)
    c = len(colors)
    if c < UNLABELED_INDEX:
        pal = np.zeros((256, 3), np.uint8)
        pal[:c] = colors
        pal[UNLABELED_INDEX] = unlabeled
        return _png(np.where(labels < 0, UNLABELED_INDEX, labels).astype(np.uint8), pal)
    table = np.vstack([colors, np.asarray([unlabeled], np.uint8)])  # index -1: unlabeled
    return _png(table[labels])


def decode_label_png(data: bytes, colors: np.ndarray) -> np.ndarray:
    """:func:`label_png` bytes -> (H, W) int16 class ids, IGNORE (-1) where unlabeled. A
    palette PNG gives the ids exactly; an RGB one is matched to ``colors`` (C, 3) (the first
    class of a colour; any other colour: IGNORE)."""
    import io

    from PIL import Image

    im = Image.open(io.BytesIO(data))
    if im.mode == "P":
        idx = np.asarray(im).astype(np.int16)
        idx[idx == UNLABELED_INDEX] = IGNORE
        return idx
    rgb = np.asarray(im.convert("RGB")).astype(np.uint32)
    key = rgb[..., 0] << 16 | rgb[..., 1] << 8 | rgb[..., 2]
    cols = np.asarray(colors, np.uint32).reshape(-1, 3)
    ckey = cols[:, 0] << 16 | cols[:, 1] << 8 | cols[:, 2]
    order = np.argsort(ckey, kind="stable")  # stable: the first class of a repeated colour
    sk = ckey[order]
    at = np.clip(np.searchsorted(sk, key), 0, len(sk) - 1)
    return np.where(sk[at] == key, order[at], IGNORE).astype(np.int16)


def _quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """(3, 3) rotation matrix -> unit quaternion (x, y, z, w), w >= 0 (Shepperd's method: the
    largest of 4w^2, 4x^2, 4y^2, 4z^2 is divided by; a tenth of scipy's Rotation's cost)."""
    m = np.asarray(R, np.float64)
    d = np.array([m[0, 0] + m[1, 1] + m[2, 2], m[0, 0] - m[1, 1] - m[2, 2],
                  -m[0, 0] + m[1, 1] - m[2, 2], -m[0, 0] - m[1, 1] + m[2, 2]])
    k = int(np.argmax(d))
    r = np.sqrt(1.0 + d[k]) * 2.0  # 4 x the largest component
    a, b, c = m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]  # 4w x, 4w y, 4w z
    e, f, g = m[0, 1] + m[1, 0], m[0, 2] + m[2, 0], m[1, 2] + m[2, 1]  # 4x y, 4x z, 4y z
    h = r * r / 4
    q = np.array([(a, b, c, h), (h, e, f, a), (e, h, g, b), (f, g, h, c)][k]) / r
    q /= np.linalg.norm(q)
    return tuple(float(v) for v in (q if q[3] >= 0 else -q))


def camera_messages(index: int, K: np.ndarray, T_cw: np.ndarray, shape: tuple[int, int],
                    labels: Optional[np.ndarray], colors: Optional[np.ndarray], max_side: int,
                    stamp_ns: int) -> list[tuple[str, Any]]:
    """One frame's foxglove messages, ``[(topic, message)]``, all stamped ``stamp_ns``:

    - /tf  FrameTransform world -> camera_<i>: the camera's pose in the world, inv(T_cw)
      (translation metres, rotation quaternion), in the optical convention of Foxglove's camera
      frames (x right, y down, z forward), which is our T_cw's;
    - /cameras/calibration  CameraCalibration (frame camera_<i>) of the image stored: the frame
      (H, W) = ``shape`` strided to ``max_side`` (:func:`strided`), K strided alike, P = [K | 0],
      no distortion;
    - /cameras/labels  CompressedImage (png, frame camera_<i>) of the (H, W) class ids ``labels``
      strided the same way, in the taxonomy colours ``colors`` (C, 3) (:func:`label_png`); left
      out when either is None.
    """
    from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform

    frame = camera_frame_id(index)
    h, w = (int(v) for v in shape)
    s = max(1, int(np.ceil(max(h, w) / max_side)))
    _, K_img = strided(np.empty((h, w, 0), np.uint8), K, max_side)  # K of the strided image
    T_wc = np.linalg.inv(np.asarray(T_cw, np.float64))
    tf = FrameTransform(parent_frame_id=FRAME_ID, child_frame_id=frame)
    tf.translation.SetInParent()  # present even when zero: Rerun's loader reads an absent one as null
    tf.translation.x, tf.translation.y, tf.translation.z = (float(v) for v in T_wc[:3, 3])
    q = _quaternion(T_wc[:3, :3])
    tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = q
    P = np.zeros((3, 4))
    P[:, :3] = K_img
    cal = CameraCalibration(frame_id=frame, width=-(-w // s), height=-(-h // s), distortion_model="plumb_bob",
                            D=[0.0] * 5, K=K_img.ravel().tolist(), R=np.eye(3).ravel().tolist(),
                            P=P.ravel().tolist())
    out: list[tuple[str, Any]] = [(TOPIC_TF, tf), (TOPIC_CALIBRATION, cal)]
    if labels is not None and colors is not None:
        lab, _ = strided(np.asarray(labels), K, max_side)
        img = CompressedImage(frame_id=frame, format="png", data=label_png(lab, colors))
        out.append((TOPIC_CAMERA_LABELS, img))
    for _, msg in out:
        msg.timestamp.FromNanoseconds(int(stamp_ns))
    return out
