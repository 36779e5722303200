"""Where the single-frame protocol's gains come from, pixel by pixel: each target frame's pixels
split into interior pixels and ground-truth boundary pixels, the boundaries into creases (the
surfaces on either side meet at an angle) and coplanar boundaries (a label change on one surface,
e.g. a picture on a wall), and each row's accuracy on each kind::

    python -m analysis.gains scene=scannet0470 predictions=realistic depth=sensor [overrides]

Boundary: a pixel with ground truth whose ``--radius`` neighbourhood holds another label. Crease:
the mean normal of the neighbourhood's same-label pixels and that of its other-label pixels differ
by more than ``--crease-deg`` (sign-invariant; normals from the frame's own depth image, smoothed
as ``protocol.normals=depth_image`` does). Pixels without depth are their own kind.
"""
from __future__ import annotations

import argparse
import sys
from typing import Sequence

import numpy as np

KINDS = ("interior", "crease", "coplanar", "no depth")


def pixel_kinds(gt: np.ndarray, depth: np.ndarray, K: np.ndarray, radius: int = 2, crease_deg: float = 30.0,
                window: int = 7) -> np.ndarray:
    """(H, W) int8 kind of each pixel (index into :data:`KINDS`; -1 where gt is IGNORE)."""
    from scipy.ndimage import maximum_filter, minimum_filter, uniform_filter

    from diffuser_lab.data.scene import IGNORE
    from diffuser_lab.data.geometry import normals_from_depth

    valid = gt != IGNORE
    size = 2 * radius + 1
    g = np.where(valid, gt, -1).astype(np.int32)
    hi = maximum_filter(g, size, mode="nearest")
    lo = minimum_filter(np.where(valid, g, np.iinfo(np.int32).max), size, mode="nearest")
    boundary = valid & ((hi != g) | (lo != g))
    d = np.asarray(depth, np.float64)
    ok = d > 0
    classes = np.unique(g[valid])
    smooth = np.zeros_like(d)
    for c in classes:  # loop over the classes in the frame: depth smoothed within each label only,
        m = (ok & (g == c)).astype(np.float64)  # so that a crease is not rounded off
        cnt = uniform_filter(m, window, mode="constant")
        smooth = np.where(m > 0, uniform_filter(d * m, window, mode="constant") / np.maximum(cnt, 1e-12), smooth)
    n = normals_from_depth(np.where(valid, smooth, d), K)  # (H, W, 3), 0 without depth
    side = size + 2 * window  # the two sides' normals from beyond the pixels next to the boundary
    same = np.zeros_like(n)
    total = np.zeros_like(n)
    for c in classes:
        m = (g == c)[..., None] * n
        s = np.stack([uniform_filter(m[..., k], side, mode="constant") for k in range(3)], -1)
        total += s
        same += np.where((g == c)[..., None], s, 0.0)
    other = total - same
    unit = lambda v: v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)  # noqa: E731
    cos = np.abs(np.sum(unit(same) * unit(other), -1))
    crease = boundary & (cos < np.cos(np.radians(crease_deg)))
    kinds = np.where(boundary, np.where(crease, 1, 2), 0).astype(np.int8)
    kinds[d <= 0] = 3
    kinds[~valid] = -1
    return kinds


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--radius", type=int, default=2)
    ap.add_argument("--crease-deg", type=float, default=30.0)
    a, overrides = ap.parse_known_args(list(sys.argv[1:] if argv is None else argv))

    from hydra import compose, initialize_config_dir

    from diffuser_lab.cli.main import config_dir
    from diffuser_lab.config import register, to_object
    from diffuser_lab.runs.single_frame import single_frame

    register()
    with initialize_config_dir(config_dir=config_dir(), version_base="1.3", job_name="gains"):
        cfg = to_object(compose("config", overrides=["protocol=single_frame", *overrides]))
    hits: dict = {}
    count = np.zeros(len(KINDS), np.int64)

    def on_frame(f, images):
        kinds = pixel_kinds(f.gt_labels, f.depth, f.K, a.radius, a.crease_deg)
        count[:] += np.bincount(kinds[kinds >= 0], minlength=len(KINDS))
        for key, img in images.items():
            right = (img == f.gt_labels) & (kinds >= 0)
            hits.setdefault(key, np.zeros(len(KINDS), np.int64))
            hits[key] += np.bincount(kinds[right], minlength=len(KINDS))

    res = single_frame(cfg, on_frame=on_frame)
    keys = [(r["method"], r["views"]) for r in res.rows]
    print(f"single-frame pixel accuracy by kind | {res.scene.name} | {len(res.targets)} target frames | "
          f"radius {a.radius} px, crease > {a.crease_deg:g} deg")
    print("| kind | pixels | " + " | ".join(f"{m}_{v}v" for m, v in keys) + " |")
    print("| --- | --- | " + " | ".join("---" for _ in keys) + " |")
    for k, name in enumerate(KINDS):
        if count[k]:
            print(f"| {name} | {count[k] / count.sum() * 100:.1f} % | "
                  + " | ".join(f"{hits[key][k] / count[k] * 100:.1f}" for key in keys) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
