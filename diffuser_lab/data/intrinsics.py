"""Camera intrinsics files as datasets and tools write them -> a pinhole K and the image size it is for.

One reader per format, each ``(path, ...) -> (K (3, 3) float64 pixels, size (H, W) or None)``; the
size is None when the file does not say which image the matrix is for. :func:`read_intrinsics_file`
picks the reader by name (``auto``: by the file's name and suffix). Every error is one line naming
the file (and the field) and what was expected.

- ``matrix``: a 3x3 text matrix, or 4x4 with K upper-left (ScanNet's ``intrinsic_*.txt``);
- ``scannet_info``: ScanNet's ``_info.txt`` (``m_calibrationColorIntrinsic`` /
  ``m_calibrationDepthIntrinsic`` 4x4 row-major, ``m_colorWidth``/``Height``, ``m_depthWidth``/``Height``,
  ``m_depthShift``), as the C++ SensReader writes it; ``camera`` picks depth or colour;
- ``ros_camera_info``: a ROS camera_info YAML as ``camera_calibration`` writes it (``image_width``,
  ``image_height``, ``camera_matrix.data``, ``distortion_model``, ``distortion_coefficients.data``);
  images with non-zero distortion are refused (the pinhole model here has none);
- ``json``: ``fx fy cx cy`` (+ optional ``w h`` / ``width height``) or ``"K"`` (3x3, or 9 numbers),
  optionally nested under a dotted key path.
"""
from __future__ import annotations

import io
import json
import warnings
from pathlib import Path
from typing import Optional

import numpy as np

from . import inputs

__all__ = ["FORMATS", "read_matrix_file", "read_intrinsics", "read_intrinsics_file", "read_matrix_intrinsics",
           "read_scannet_info", "read_scannet_info_intrinsics", "scannet_depth_shift", "read_ros_camera_info",
           "read_json_intrinsics", "detect_format"]

FORMATS = ("auto", "matrix", "scannet_info", "ros_camera_info", "json")
Size = Optional[tuple[int, int]]


def _checked_K(K: np.ndarray, path: Path, field: str) -> np.ndarray:
    K = np.asarray(K, np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0 \
            or np.abs(K[2] - [0, 0, 1]).max() > 1e-6:
        raise ValueError(f"{path}: {field} {K.tolist()} is not a pinhole K (3x3, positive fx fy, last row 0 0 1)")
    return K


def _checked_size(h, w, path: Path, field: str) -> tuple[int, int]:
    try:
        h, w = int(h), int(w)
    except (TypeError, ValueError, OverflowError):  # OverflowError: inf (JSON 1e400)
        raise ValueError(f"{path}: {field} = {h!r} x {w!r}, expected positive integer image height and width") from None
    if h <= 0 or w <= 0:
        raise ValueError(f"{path}: {field} = {h} x {w}, expected positive image height and width")
    return h, w


def read_matrix_file(path: str | Path, what: str, role: str = "intrinsics") -> np.ndarray:
    """A whitespace-separated numeric text matrix -> (r, c) float64; one line naming the file
    (and ``what`` it holds) otherwise. Shared with the pose reader (poses.read_pose_c2w); recorded
    as the run's input of ``role``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} file {path} does not exist")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # an empty file is reported below, not as a warning
            M = np.loadtxt(io.BytesIO(inputs.read_bytes(path, role)), dtype=np.float64, ndmin=2)
    except ValueError as e:
        raise ValueError(f"{path}: cannot parse {what} as a numeric matrix ({str(e).splitlines()[0]})") from None
    if M.size == 0:
        raise ValueError(f"{path}: empty {what} file")
    return M


def read_intrinsics(path: str | Path) -> np.ndarray:
    """3x3 intrinsics file (or 4x4 whose upper-left 3x3 is K, as ScanNet's) -> (3, 3) float64.

    Raises:
        ValueError: wrong shape, non-positive focal lengths or a non-[0 0 1] last row.
    """
    path = Path(path)
    M = read_matrix_file(path, "intrinsics")
    if M.shape not in ((3, 3), (4, 4)):
        raise ValueError(f"{path}: intrinsics of shape {M.shape}, expected 3x3 (or 4x4 with K upper-left)")
    K = M[:3, :3].copy()
    if not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0 or np.abs(K[2] - [0, 0, 1]).max() > 1e-6:
        raise ValueError(f"{path}: intrinsics {K.tolist()} need positive focal lengths fx, fy and last row 0 0 1")
    return K


def read_matrix_intrinsics(path: str | Path) -> tuple[np.ndarray, Size]:
    """3x3 (or 4x4, K upper-left) text matrix -> (K, None): such a file does not say its image size."""
    return read_intrinsics(path), None


def read_scannet_info(path: str | Path) -> dict[str, str]:
    """ScanNet's ``_info.txt`` (``key = value`` lines) -> {key: value text}."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"intrinsics file {path} does not exist")
    out = {}
    for n, line in enumerate(inputs.read_bytes(path, "intrinsics").decode(errors="replace").splitlines(), 1):  # a dozen lines
        if not line.strip():
            continue
        k, sep, v = line.partition("=")
        if not sep or not k.strip():
            raise ValueError(f"{path}: line {n} {line.strip()[:60]!r} is not 'key = value' (ScanNet _info.txt)")
        out[k.strip()] = v.strip()
    return out


def read_scannet_info_intrinsics(path: str | Path, camera: str = "depth") -> tuple[np.ndarray, Size]:
    """ScanNet ``_info.txt`` -> (K of the ``camera`` (depth | color), its (H, W))."""
    path = Path(path)
    if camera not in ("depth", "color"):
        raise ValueError(f"intrinsics camera {camera!r}: expected depth or color")
    info = read_scannet_info(path)
    cam = "Depth" if camera == "depth" else "Color"
    field = f"m_calibration{cam}Intrinsic"
    need = (field, f"m_{camera}Width", f"m_{camera}Height")
    missing = [k for k in need if k not in info]
    if missing:
        raise ValueError(f"{path}: no {', '.join(missing)}, expected ScanNet's _info.txt ({', '.join(need)})")
    try:
        M = np.array(info[field].split(), np.float64)
    except ValueError:
        raise ValueError(f"{path}: {field} = {info[field][:60]!r}, expected 16 numbers (4x4 row-major)") from None
    if M.size != 16:
        raise ValueError(f"{path}: {field} has {M.size} numbers, expected 16 (4x4 row-major)")
    K = _checked_K(M.reshape(4, 4)[:3, :3], path, field)
    return K, _checked_size(info[need[2]], info[need[1]], path, f"{need[2]} x {need[1]}")


def scannet_depth_shift(path: str | Path) -> Optional[float]:
    """``m_depthShift`` of a ScanNet ``_info.txt`` (depth units per metre), None when absent."""
    path = Path(path)
    v = read_scannet_info(path).get("m_depthShift")
    if v is None:
        return None
    try:
        shift = float(v)
    except ValueError:
        shift = -1.0
    if not shift > 0:
        raise ValueError(f"{path}: m_depthShift = {v!r}, expected a positive number (depth units per metre)")
    return shift


def _load_yaml(path: Path) -> dict:
    import yaml

    if not path.is_file():
        raise FileNotFoundError(f"intrinsics file {path} does not exist")
    try:
        text = inputs.read_bytes(path, "intrinsics").decode(errors="replace")
        if text.startswith("%YAML:1"):  # OpenCV FileStorage header: not plain YAML 1.1
            text = text.split("\n", 1)[1] if "\n" in text else ""
        doc = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise ValueError(f"{path}: not readable YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: expected a YAML mapping (ROS camera_info), got {type(doc).__name__}")
    return doc


def _numbers(doc: dict, name: str, n: Optional[int], path: Path) -> np.ndarray:
    """``doc[name]["data"]`` (or a plain list) as float64 numbers, ``n`` of them when given."""
    v = doc.get(name)
    data = v.get("data") if isinstance(v, dict) else v
    try:
        a = np.array(data, np.float64).ravel()
    except (TypeError, ValueError):
        a = np.zeros(0)
    if data is None or (n is not None and a.size != n):
        raise ValueError(f"{path}: {name}.data = {data!r}, expected {n if n else 'a list of'} numbers "
                         f"(ROS camera_info)")
    return a


def read_ros_camera_info(path: str | Path) -> tuple[np.ndarray, Size]:
    """ROS camera_info YAML (``camera_calibration``'s ``ost.yaml``) -> (K, (image_height, image_width)).

    Raises:
        ValueError: a missing field, or non-zero ``distortion_coefficients`` (images must be rectified).
    """
    path = Path(path)
    doc = _load_yaml(path)
    missing = [k for k in ("image_width", "image_height", "camera_matrix") if k not in doc]
    if missing:
        raise ValueError(f"{path}: no {', '.join(missing)}, expected a ROS camera_info YAML "
                         f"(image_width, image_height, camera_matrix.data)")
    K = _checked_K(_numbers(doc, "camera_matrix", 9, path).reshape(3, 3), path, "camera_matrix")
    if "distortion_coefficients" in doc:
        d = _numbers(doc, "distortion_coefficients", None, path)
        if np.any(d != 0):
            raise ValueError(f"{path}: distortion_coefficients {d.tolist()} ({doc.get('distortion_model', '?')}) are "
                             f"not zero, expected undistorted images (rectify them, then give zero distortion)")
    return K, _checked_size(doc["image_height"], doc["image_width"], path, "image_height x image_width")


def read_json_intrinsics(path: str | Path, key_path: Optional[str] = None) -> tuple[np.ndarray, Size]:
    """JSON intrinsics -> (K, (h, w) or None): ``fx fy cx cy`` (+ ``w h`` or ``width height``) or
    ``"K"`` (3x3 or 9 numbers), under the dotted ``key_path`` when given (``camera.intrinsics``)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"intrinsics file {path} does not exist")
    try:
        doc = json.loads(inputs.read_bytes(path, "intrinsics").decode(errors="replace"))
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not readable JSON ({e})") from None
    where = "the top level"
    for part in (key_path.split(".") if key_path else []):  # a few keys
        if not isinstance(doc, dict) or part not in doc:
            raise ValueError(f"{path}: no key {part!r} on the path {key_path!r} (scene.options.intrinsics_key)")
        doc, where = doc[part], key_path
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: {where} is not an object, expected fx fy cx cy (w h) or K")
    if "K" in doc:
        try:
            K = np.array(doc["K"], np.float64).reshape(3, 3)
        except (TypeError, ValueError):
            raise ValueError(f"{path}: K = {doc['K']!r}, expected a 3x3 list of numbers") from None
        K = _checked_K(K, path, "K")
    elif all(k in doc for k in ("fx", "fy", "cx", "cy")):
        try:
            fx, fy, cx, cy = (float(doc[k]) for k in ("fx", "fy", "cx", "cy"))
        except (TypeError, ValueError):
            raise ValueError(f"{path}: fx fy cx cy = {[doc[k] for k in ('fx', 'fy', 'cx', 'cy')]}, "
                             f"expected numbers") from None
        K = _checked_K([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], path, "fx fy cx cy")
    else:
        raise ValueError(f"{path}: {where} has neither fx fy cx cy nor K (keys: {', '.join(map(str, doc))})")
    for w, h in (("w", "h"), ("width", "height")):
        if w in doc and h in doc:
            return K, _checked_size(doc[h], doc[w], path, f"{h} x {w}")
    return K, None


def detect_format(path: str | Path) -> str:
    """``auto``: ``*_info.txt`` -> scannet_info, ``.yaml``/``.yml`` -> ros_camera_info, ``.json`` -> json,
    else matrix (a text file starting with ``m_`` keys is taken as scannet_info)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if path.name.endswith("_info.txt"):
        return "scannet_info"
    if suffix in (".yaml", ".yml"):
        return "ros_camera_info"
    if suffix == ".json":
        return "json"
    if path.is_file():
        with open(path, errors="replace") as fh:
            if fh.read(64).lstrip().startswith("m_"):
                return "scannet_info"
    return "matrix"


def read_intrinsics_file(path: str | Path, format: str = "auto", camera: str = "depth",
                         key_path: Optional[str] = None) -> tuple[np.ndarray, Size]:
    """An intrinsics file of ``format`` (one of :data:`FORMATS`) -> (K (3, 3) float64 pixels,
    (H, W) the K is for, or None when the file does not say). ``camera``: scannet_info's depth |
    color; ``key_path``: json's dotted key path."""
    fmt = detect_format(path) if format == "auto" else format
    if fmt == "matrix":
        return read_matrix_intrinsics(path)
    if fmt == "scannet_info":
        return read_scannet_info_intrinsics(path, camera)
    if fmt == "ros_camera_info":
        return read_ros_camera_info(path)
    if fmt == "json":
        return read_json_intrinsics(path, key_path)
    raise ValueError(f"intrinsics format {format!r}: expected one of {', '.join(FORMATS)}")
