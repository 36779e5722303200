"""Data containers shared by every stage: taxonomy, frames and scenes.

Conventions (everywhere in diffuser-lab):
- world coordinates in metres; ``T_cw`` is the 4x4 world-to-camera transform
  (x_cam = R x_world + t, camera looks along +z, x right, y down);
- class ids are 0..C-1 indices into a :class:`Taxonomy`; ``IGNORE`` (-1) marks
  "no label" (unlabeled point, unannotated pixel, unmapped class).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

IGNORE = -1
"""Class id meaning 'no label': never a real class, excluded from metrics."""


@dataclass(frozen=True)
class Taxonomy:
    """Evaluation classes: ``names[c]`` and ``colors[c]`` (uint8 RGB) for class id c.

    ``ids[c]`` is the label id that class c has in the data (label images, PLY ``label``);
    None = the data's ids already are 0..C-1. ``ignore_ids`` are label ids meaning "no label".
    Shipped ones and files: :mod:`diffuser_lab.data.taxonomy`."""

    name: str
    names: tuple[str, ...]
    colors: np.ndarray  # (C, 3) uint8
    ids: tuple[int, ...] | None = None
    ignore_ids: tuple[int, ...] = ()

    @property
    def num_classes(self) -> int:
        return len(self.names)

    def colorize(self, labels: np.ndarray, ignore_color=(0, 0, 0)) -> np.ndarray:
        """(...,) class ids -> (..., 3) uint8 colours; IGNORE gets ``ignore_color``."""
        lut = np.vstack([self.colors, np.asarray(ignore_color, np.uint8)[None]])
        idx = np.where(labels == IGNORE, len(self.names), labels)
        return lut[idx]


# ScanNet benchmark classes (NYU40 ids 1 2 3 4 5 6 7 8 9 10 11 12 14 16 24 28 33 34 36 39)
# with the benchmark's usual colour palette.
SCANNET20 = Taxonomy(
    name="scannet20",
    names=(
        "wall", "floor", "cabinet", "bed", "chair", "sofa", "table", "door", "window",
        "bookshelf", "picture", "counter", "desk", "curtain", "refrigerator",
        "shower curtain", "toilet", "sink", "bathtub", "otherfurniture",
    ),
    colors=np.array(
        [
            (174, 199, 232), (152, 223, 138), (31, 119, 180), (255, 187, 120), (188, 189, 34),
            (140, 86, 75), (255, 152, 150), (214, 39, 40), (197, 176, 213), (148, 103, 189),
            (196, 156, 148), (23, 190, 207), (247, 182, 210), (219, 219, 141), (255, 127, 14),
            (158, 218, 229), (44, 160, 44), (112, 128, 144), (227, 119, 194), (82, 84, 163),
        ],
        dtype=np.uint8,
    ),
)
SCANNET20_NYU40_IDS = (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14, 16, 24, 28, 33, 34, 36, 39)


@dataclass
class Frame:
    """One posed RGB-D view with its 2D labels.

    Attributes:
        name: identifier (file stem or view index).
        K: (3, 3) float64 pinhole intrinsics of the depth/label image, pixels.
        T_cw: (4, 4) float64 world-to-camera transform, metres.
        depth: (H, W) float32 z-depth in metres along the optical axis; 0 = no depth.
        labels: (H, W) int16 predicted class ids (IGNORE = no prediction), or None.
        probs: (H, W, C) float32 per-pixel class probabilities (soft labels), or None.
            When both are given, ``probs`` is used as evidence.
        gt_labels: (H, W) int16 ground-truth class ids when known, else None.
        rgb: (H, W, 3) uint8 colour image registered to depth, or None.
        features: (h, w, D) float16/float32 a network's per-pixel embeddings over the same field
            of view (h, w: its patch grid or the image's size; NaN = no feature), or None. When
            set, it is the evidence (features runs: :mod:`diffuser_lab.method.features`).
    """

    name: str
    K: np.ndarray
    T_cw: np.ndarray
    depth: np.ndarray
    labels: np.ndarray | None = None
    probs: np.ndarray | None = None
    gt_labels: np.ndarray | None = None
    rgb: np.ndarray | None = None
    features: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.depth.shape[:2]


@dataclass
class Scene:
    """A point cloud to label and the frames that see it.

    Attributes:
        name: scene identifier.
        points: (N, 3) float32 world coordinates, metres.
        normals: (N, 3) float32 unit normals in world frame, or None (estimated later).
        colors: (N, 3) uint8 RGB, or None.
        gt_labels: (N,) int16 ground-truth class ids (IGNORE = unannotated), or None.
        taxonomy: the class set of labels, predictions and ground truth.
        frames: sequence of :class:`Frame`; may be lazy (loaded on indexing).
    """

    name: str
    points: np.ndarray
    taxonomy: Taxonomy
    frames: Sequence[Frame] = field(default_factory=list)
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    gt_labels: np.ndarray | None = None

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])
