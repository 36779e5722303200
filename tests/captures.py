"""The 7-Scenes sample as every capture format lays it out: the same frames, written by each format's
test into its own layout, must label the same points as the posed RGB-D folder does (issue 27).

:func:`seven_frames` gives the frames (name, K, camera-to-world pose, depth in metres, colour);
:func:`write_rgbd_reference` writes them as a posed RGB-D folder; :func:`labels_of` runs
``diffuser-lab`` (composed from conf/, the toy grey-level network as predictions) on overrides and
returns the points and labels; :func:`agreement` compares two runs point by point (nearest point
within 1 mm, so a cloud re-ordered or rounded by a format still compares)."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import SHARED, compose
from scipy.spatial import cKDTree

SEVEN = SHARED / "data" / "7scenes_sample"
needs_7scenes = pytest.mark.skipif(not (SEVEN / "camera-intrinsics.txt").is_file(),
                                   reason=f"the real 7-Scenes sample is absent ({SEVEN})")
NETWORK = ["predictions=model", "predictions.model._target_=tests.toy_networks.grey_levels",
           "predictions.mapping=null", "predictions.cache_dir=null", "record=off", "output.labels_ply=false"]
"""The run every format is compared with: the toy network's labels (4 grey levels) as predictions."""


def seven_frames(n: int = 6, step: int = 15) -> list[dict]:
    """``n`` frames of the 7-Scenes sample, every ``step``-th file (real depth, colour, poses):
    dicts with ``name``, ``K`` (3, 3), ``c2w`` (4, 4), ``depth`` (480, 640) float32 metres (0 = none),
    ``depth_path``, ``color_path``, ``pose_path``."""
    from diffuser_lab.data.images import read_depth_png
    from diffuser_lab.data.intrinsics import read_intrinsics
    from diffuser_lab.data.poses import read_pose_c2w

    K = read_intrinsics(SEVEN / "camera-intrinsics.txt")
    names = sorted(p.name[: -len(".depth.png")] for p in SEVEN.glob("frame-*.depth.png"))[::step][:n]
    out = []
    for name in names:  # loop over a few frames
        out.append(dict(name=name, K=K, c2w=read_pose_c2w(SEVEN / f"{name}.pose.txt"),
                        depth=read_depth_png(SEVEN / f"{name}.depth.png", 1000.0),
                        depth_path=SEVEN / f"{name}.depth.png", color_path=SEVEN / f"{name}.color.jpg",
                        pose_path=SEVEN / f"{name}.pose.txt"))
    return out


def write_rgbd_reference(parent: Path, frames: list[dict]) -> Path:
    """The frames as a posed RGB-D folder (the reference layout, files copied)."""
    root = Path(parent) / "rgbd"
    root.mkdir(parents=True, exist_ok=True)
    shutil.copy(SEVEN / "camera-intrinsics.txt", root)
    for f in frames:  # loop over frames
        for kind in ("depth_path", "color_path", "pose_path"):
            shutil.copy(f[kind], root)
    return root


def labels_of(*overrides: str) -> tuple[np.ndarray, np.ndarray, object]:
    """``diffuser-lab OVERRIDES`` with the toy network (:data:`NETWORK`): (points (N, 3), labels (N,), result)."""
    from diffuser_lab.runs.pipeline import run

    res = run(compose(*overrides, *NETWORK))
    return res.scene.points, res.labels, res


def reference_labels(parent: Path, frames: list[dict], *extra: str):
    """The posed RGB-D folder's run on ``frames`` (what each format must reproduce)."""
    root = write_rgbd_reference(parent, frames)
    return labels_of("scene=rgbd_folder", f"scene.options.root={root}", *extra)


def agreement(points_a, labels_a, points_b, labels_b, tol: float = 1e-3) -> float:
    """Share of the points of run a whose nearest point of run b (within ``tol`` metres) has the
    same label (a point without such a neighbour counts as different)."""
    d, j = cKDTree(points_b).query(points_a, k=1)
    same = (d <= tol) & (labels_b[np.minimum(j, len(labels_b) - 1)] == labels_a)
    return float(same.mean())
