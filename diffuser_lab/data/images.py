"""Depth and colour images shared by the capture formats (label images: :mod:`.prediction_files`)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from diffuser_lab.data.prediction_files import open_image

__all__ = ["read_depth_png", "read_rgb"]


def read_depth_png(path: str | Path, depth_scale: float, bit_shift: int = 0,
                   invalid=(0, 65535), shift_kind: str = "circular") -> np.ndarray:
    """16-bit depth PNG -> (H, W) float32 z-depth in metres, 0 = invalid.

    Args:
        depth_scale: stored units per metre (1000 for millimetres), applied after the shift.
        bit_shift: right shift of the raw 16-bit value before scaling.
        invalid: raw stored values (before the shift) meaning "no depth".
        shift_kind: ``circular`` = 16-bit rotate right (SUN3D, ``bit_shift=3``), ``plain`` =
            ``raw >> bit_shift`` (low bits dropped, e.g. ``(raw >> 3) / 1e4`` m).
    """
    if shift_kind not in ("circular", "plain"):
        raise ValueError(f"depth shift kind {shift_kind!r}: expected circular or plain")
    path = Path(path)
    with open_image(path, "depth image") as im:
        raw = np.asarray(im)
    if raw.ndim != 2 or raw.dtype.kind not in "ui" or raw.dtype.itemsize < 2:
        raise ValueError(f"{path}: depth image of dtype {raw.dtype} shape {raw.shape}, expected single-channel 16-bit")
    raw = raw.astype(np.uint32) & 0xFFFF
    bad = np.isin(raw, np.asarray(invalid, np.uint32))
    if bit_shift and shift_kind == "plain":
        raw = raw >> int(bit_shift)
    elif bit_shift:
        s = int(bit_shift) % 16
        raw = ((raw >> s) | (raw << (16 - s))) & 0xFFFF  # 16-bit rotate right
    depth = raw.astype(np.float32) / np.float32(depth_scale)
    depth[bad] = 0.0
    return depth


def read_rgb(path: str | Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Colour image -> (H, W, 3) uint8, bilinearly resized to ``shape`` = (H, W) when given."""
    from PIL import Image

    path = Path(path)
    with open_image(path, "colour image") as im:
        im = im.convert("RGB")
        if shape is not None and im.size != (shape[1], shape[0]):
            im = im.resize((int(shape[1]), int(shape[0])), Image.BILINEAR)
        return np.asarray(im, dtype=np.uint8).copy()
