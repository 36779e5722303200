"""run.mcap's message formats (see :mod:`.mcap_write` for the channels): the point clouds
(foxglove.PointCloud, packed RGBA colours, int16 labels), the Z states (diffuser_lab.ZState:
float32 or float16, stored class-major) serialised straight into reused buffers, and their
decoders. Nothing here opens a file."""
from __future__ import annotations

from typing import Any, Optional

import numpy as np

from . import schema

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


Z_BITS = {"q8": 8, "q16": 16}
"""Bits per share of the quantised Z precisions."""


def z_state_bytes(iteration: int, Z: np.ndarray, dtype: str, out: Optional[bytearray] = None,
                  class_major: bool = True, labels: Optional[np.ndarray] = None) -> memoryview:
    """``ZState(...).SerializeToString()`` with Z copied once (transposed when ``class_major``)
    into ``out`` (see :func:`_with_bytes_field`); ``data`` is field 5. ``dtype``: float32 (exact),
    float16 (Z / max Z), q8 / q16 (row sums + shares, always class-major). ``labels`` (M,) int:
    the exact Z's labels, stored with an inexact state (field 9) so readers keep the run's own."""
    lab = b"" if labels is None or dtype == "float32" else np.asarray(labels, "<i2").tobytes()
    from diffuser_lab.backends.numba.float16 import shares, transpose_into  # numba: only where Z is written

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
