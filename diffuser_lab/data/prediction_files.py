"""2D predictions of any network stored as files, matched to frames by name.

Two kinds of file per frame:
- a label image (PNG, 8- or 16-bit single channel or palette) of source class ids,
  turned into evaluation class ids by a :class:`~diffuser_lab.data.mapping.ClassMapping`;
- class probabilities as ``.npy`` / ``.npz`` (first array, or the one keyed ``probs``),
  (H, W, C) or (C, H, W) float, already in the evaluation taxonomy's class order.

Predictions made at another resolution are resized to the frame's depth resolution by the one
resize of :mod:`.images` (pixel centres aligned): label ids nearest (ids kept), probabilities
bilinear (a convex combination of the neighbours' vectors, so still a distribution), as a
network's outputs are; this assumes the prediction covers the same field of view as depth.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .arrays import open_npz, read_array
from .images import read_label_png, resize_bilinear, resize_nearest
from .mapping import ClassMapping

__all__ = [
    "load_label_prediction",
    "load_probability_prediction",
    "find_prediction",
    "load_feature_prediction",
    "DEFAULT_PATTERNS",
]

DEFAULT_PATTERNS = ("{name}.png", "{name}.label.png", "{name}.npy", "{name}.npz")  # = predictions.pattern's default


def load_label_prediction(path: str | Path, mapping: ClassMapping | None,
                          shape: tuple[int, int]) -> tuple[np.ndarray, int]:
    """A predicted label image for a frame of depth resolution ``shape`` = (H, W).

    Args:
        path: PNG of source class ids.
        mapping: source ids -> evaluation ids; None = the file already holds
            evaluation ids (IGNORE can then not be expressed; use a mapping with an
            ``ignore`` row for a void id).
        shape: (H, W) of the frame's depth image; the labels are resized nearest to it.
    Returns:
        labels: (H, W) int16 evaluation class ids, IGNORE for unmapped classes;
        n_unmapped: pixels whose source class maps to ignore.
    """
    ids = resize_nearest(read_label_png(path, stored=True, role="predictions"), shape)
    if mapping is not None:
        try:
            return mapping.apply(ids)
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None
    if ids.size and ids.max() > np.iinfo(np.int16).max:
        raise ValueError(f"{path}: label id {int(ids.max())} does not fit int16; give a class mapping")
    return ids.astype(np.int16), 0


def load_probability_prediction(path: str | Path, num_classes: int, shape: tuple[int, int]) -> np.ndarray:
    """Per-pixel class probabilities for a frame of depth resolution ``shape`` = (H, W).

    Args:
        path: ``.npy`` or ``.npz`` (array ``probs`` if present, else the first array),
            (H', W', C) or (C, H', W'); C must equal ``num_classes``.
        num_classes: C of the evaluation taxonomy.
        shape: (H, W) target resolution (bilinear resize, :func:`~diffuser_lab.data.images.resize_bilinear`).
    Returns:
        (H, W, C) float32 non-negative scores (not renormalised; evidence normalises rows).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"probability file {path} does not exist")
    if path.suffix not in (".npy", ".npz"):
        raise ValueError(f"{path}: probability file must be .npy or .npz, got {path.suffix or 'no suffix'}")
    arr = read_array(path, "probabilities", key="probs", role="predictions", ndim=3, kinds="fiu",
                     expected=f"numeric (H, W, {num_classes}) or ({num_classes}, H, W)")
    last, first = arr.shape[2] == num_classes, arr.shape[0] == num_classes
    if last and first:  # C == H or C == W: let the spatial size decide, else assume (H, W, C)
        first = tuple(arr.shape[1:]) == tuple(shape) and tuple(arr.shape[:2]) != tuple(shape)
        last = not first
    if first and not last:
        arr = np.moveaxis(arr, 0, 2)
    elif not last:
        raise ValueError(f"{path}: probabilities of shape {arr.shape} have no axis of {num_classes} classes "
                         f"(expected (H, W, {num_classes}) or ({num_classes}, H, W))")
    arr = arr.astype(np.float32, copy=False)
    if not np.isfinite(arr).all() or (arr < 0).any():
        raise ValueError(f"{path}: probabilities contain NaN/inf or negative values, expected scores >= 0")
    return np.ascontiguousarray(resize_bilinear(arr, shape))


def find_prediction(folder: str | Path, frame_name: str, patterns=DEFAULT_PATTERNS) -> Path:
    """First existing file ``folder / pattern.format(name=frame_name)`` among ``patterns``
    (``predictions.pattern``: e.g. ``{name}.segm.png``; a ``.npy`` / ``.npz`` is read as probabilities,
    anything else as a label image)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"prediction folder {folder} does not exist")
    patterns = [patterns] if isinstance(patterns, str) else patterns
    tried = [folder / p.format(name=frame_name) for p in patterns]
    for p in tried:
        if p.is_file():
            return p
    raise FileNotFoundError(f"no prediction for frame {frame_name!r} in {folder} "
                            f"(tried {', '.join(t.relative_to(folder).as_posix() for t in tried)}; predictions.pattern)")


FEATURE_LAYOUTS = ("auto", "hwd", "dhw")


def load_feature_prediction(path: str | Path, *, key: str = "features", layout: str = "auto",
                            dim: int | None = None, mask_key: str = "mask") -> np.ndarray:
    """A network's per-pixel embeddings for one frame, at the network's resolution.

    Args:
        path: ``.npy`` or ``.npz`` (the array ``key``, else the only array), float16 or float32.
        layout: ``hwd`` (h, w, D), ``dhw`` (D, h, w, channel first) or ``auto``: the axis that is
            not spatial is the one of size ``dim`` when given (the last when both are: a (30, 40, 64)
            patch grid with D = 64 is (h, w, D)), else the last unless the first is smaller than both
            others (a (512, 60, 80) map is channel first).
        dim: the expected D (the run's queries', else the first frame's), or None.
        mask_key: in an ``.npz``, an optional (h, w) bool array: False cells have no feature.
    Returns:
        (h, w, D) float16/float32 as stored (NaN cells: no feature; masked cells set to NaN).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"feature file {path} does not exist")
    if layout not in FEATURE_LAYOUTS:
        raise ValueError(f"predictions.layout={layout}: expected one of {', '.join(FEATURE_LAYOUTS)}")
    mask = None
    expect = dict(ndim=3, dtypes=(np.float16, np.float32), expected="float16/float32 (h, w, D) or (D, h, w)")
    if path.suffix == ".npy":
        arr = read_array(path, "features", role="features", **expect)
    elif path.suffix == ".npz":
        with open_npz(path, "a feature map", "features") as z:
            names = [n for n in z.files if n != mask_key]
            if key not in z and len(names) != 1:
                raise ValueError(f"{path}: no array {key!r} (predictions.key) among {', '.join(z.files) or 'none'}")
            arr = z.read(key if key in z else names[0], **expect)
            mask = z.read(mask_key, ndim=2, expected="(h, w) bool") if mask_key in z else None
    else:
        raise ValueError(f"{path}: feature file must be .npy or .npz, got {path.suffix or 'no suffix'}")
    if layout == "auto" and dim is not None and dim in (arr.shape[0], arr.shape[2]):
        first = arr.shape[2] != dim  # the axis of size D (the last when both are)
    else:
        first = layout == "dhw" or (layout == "auto" and arr.shape[0] < min(arr.shape[1:]))
    if first:
        arr = np.moveaxis(arr, 0, 2)
    if dim is not None and arr.shape[2] != dim:
        raise ValueError(f"{path}: features of shape {arr.shape} ({layout}), expected D = {dim} like the first frame")
    if mask is not None:
        if mask.shape != arr.shape[:2]:
            raise ValueError(f"{path}: mask of shape {mask.shape}, expected {arr.shape[:2]}")
        arr = np.where(np.asarray(mask, bool)[..., None], arr, np.nan).astype(arr.dtype)
    return np.ascontiguousarray(arr)
