"""Benchmark workloads: voxel-downsampled room clouds with rendered, simulated-network evidence.

A workload is the demo room (:func:`~diffuser_lab.data.sources.demo.demo_mesh`) sampled densely and
voxel-downsampled to about ``n_points`` (the paper diffuses on a 2 cm voxel grid), with exact mesh
normals averaged per voxel, ``n_views`` rendered views (640x480 by default) whose ground-truth
label images are corrupted by the simulated 2D network (:mod:`diffuser_lab.data.simulate`) over
``num_classes`` classes, and the evidence of those views (:mod:`diffuser_lab.method.evidence`). A sparse
sprinkle of random single votes (``noise_votes`` of the seen points) makes every class active, as
a real network's scattered mistakes do, so the diffusion works on all ``num_classes`` columns.
Above ``tile_points`` points the room is repeated side by side (``tiles`` copies, 1 m apart), each
copy with its own translated views, so 3M-point clouds do not need a 3M-point surface sampling.

Points come in the order :func:`~diffuser_lab.data.geometry.voxel_downsample` leaves them (sorted by
voxel key, x-major), as a voxelised scan would; nothing here orders them for the solver.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from diffuser_lab import progress
from diffuser_lab.data.geometry import voxel_downsample
from diffuser_lab.data.scene import SCANNET20, Frame, Scene, Taxonomy

ROOM_AREA_M2 = 82.0  # visible surface of the default demo room (calibrated: N ~ area / voxel^2)


def taxonomy21() -> Taxonomy:
    """ScanNet-20 plus an ``otherprop`` class: the 21 classes of the benchmark rows."""
    colors = np.vstack([SCANNET20.colors, np.array([[120, 120, 120]], np.uint8)])
    return Taxonomy(name="scannet20+other", names=SCANNET20.names + ("otherprop",), colors=colors)


@dataclass
class Workload:
    """points (N, 3) float32, normals (N, 3) float32 unit, gt (N,) int16, mass (N, C) float32
    (pixel mass before lambda, from ``frames``), frames (one room's views; see :func:`room_workload`)."""

    points: np.ndarray
    normals: np.ndarray
    gt: np.ndarray
    mass: Optional[np.ndarray]
    frames: Sequence[Frame]
    taxonomy: Taxonomy
    voxel_size: float

    @property
    def n(self) -> int:
        return int(self.points.shape[0])

    def scene(self) -> Scene:
        return Scene(name=f"bench_room_{self.n}", points=self.points, taxonomy=self.taxonomy,
                     frames=self.frames, normals=self.normals, gt_labels=self.gt)


class CycledFrames(Sequence[Frame]):
    """``n`` frames that cycle through ``base`` (renamed per index): many frames, constant memory."""

    def __init__(self, base: Sequence[Frame], n: int):
        self.base, self.n = base, n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(self.n))]
        if i < 0:
            i += self.n
        if not 0 <= i < self.n:
            raise IndexError(i)
        f = self.base[i % len(self.base)]
        return dataclasses.replace(f, name=f"{f.name}_{i:05d}")


class TiledFrames(Sequence[Frame]):
    """The views of one room, repeated for each of the room's translated copies (lazy)."""

    def __init__(self, base: Sequence[Frame], offsets: np.ndarray):
        self.base, self.offsets = base, offsets

    def __len__(self) -> int:
        return len(self.base) * len(self.offsets)

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        if i < 0:
            i += len(self)
        t, j = divmod(i, len(self.base))
        f = self.base[j]
        T = np.eye(4)
        T[:3, 3] = -self.offsets[t]
        return dataclasses.replace(f, name=f"tile{t:03d}_{f.name}", T_cw=f.T_cw @ T)


def _room_cloud(n_points: int, rng: np.random.Generator, verts, tris, labs, renderer):
    from diffuser_lab.data.render import sample_surface

    vs = math.sqrt(ROOM_AREA_M2 / n_points)
    for _ in range(3):  # secant on the voxel size: a couple of tries land within ~1 %
        pts, nrm, lab = sample_surface(verts, tris, labs, vs / 2.0, rng, noise=0.002, renderer=renderer)
        grid = voxel_downsample(pts, vs)
        m = grid.points.shape[0]
        if abs(m - n_points) <= 0.02 * n_points:
            break
        vs *= math.sqrt(m / n_points)
    normals = grid.mean(nrm)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    first = np.full(m, -1, np.int64)
    first[grid.inverse[::-1]] = np.arange(len(pts))[::-1]  # one member sample's label per voxel
    return grid.points, normals.astype(np.float32), lab[first].astype(np.int16), vs


def room_workload(n_points: int, *, seed: int = 0, n_views: int = 30, width: int = 640, height: int = 480,
                  num_classes: int = 21, with_mass: bool = True, noise_votes: float = 0.01,
                  tile_points: int = 400_000) -> Workload:
    """A benchmark cloud of about ``n_points`` points with rendered evidence (see module doc)."""
    from diffuser_lab.data.render import MeshRenderer, camera_trajectory, intrinsics
    from diffuser_lab.data.simulate import simulate_predictions
    from diffuser_lab.data.sources.demo import demo_mesh
    from diffuser_lab.method.evidence import Evidence, add_frame

    tax = taxonomy21() if num_classes == 21 else SCANNET20
    if tax.num_classes != num_classes:
        raise ValueError("num_classes must be 20 or 21")
    rng = np.random.default_rng(seed)
    verts, tris, labs = demo_mesh(seed)
    renderer = MeshRenderer(verts, tris, labs)
    tiles = max(1, math.ceil(n_points / tile_points))
    pts, nrm, gt, vs = _room_cloud(round(n_points / tiles), rng, verts, tris, labs, renderer)
    K = intrinsics(width, height, 70.0)
    poses = camera_trajectory(verts, n_views, rng, width=width, height=height, K=K, renderer=renderer)
    frames = []
    with progress.stage("workload views: rendering + simulated 2D predictions", total=len(poses), unit="view") as bar:
        for i, T in enumerate(poses):
            depth, lab = renderer.render(K, T, width, height)
            pred = simulate_predictions(lab, num_classes, np.random.default_rng([seed, i]), class_names=tax.names)
            frames.append(Frame(name=f"view_{i:04d}", K=K.copy(), T_cw=T, depth=depth, labels=pred, gt_labels=lab))
            bar.update()
    mass = None
    if with_mass:
        ev = Evidence.empty(len(pts), num_classes)
        with progress.stage("workload evidence", total=len(frames), unit="frame") as bar:
            for f in frames:
                add_frame(ev, pts, f)
                bar.update()
        mass = ev.mass
        seen = np.flatnonzero(mass.any(1))
        noisy = rng.choice(seen, size=int(noise_votes * len(seen)), replace=False)
        mass[noisy, rng.integers(0, num_classes, len(noisy))] += 1.0
    if tiles > 1:
        extent = pts.max(0) - pts.min(0)
        offsets = np.zeros((tiles, 3))
        offsets[:, 0] = np.arange(tiles) * (extent[0] + 1.0)
        pts = (pts[None] + offsets[:, None].astype(np.float32)).reshape(-1, 3)
        nrm, gt = np.tile(nrm, (tiles, 1)), np.tile(gt, tiles)
        mass = None if mass is None else np.tile(mass, (tiles, 1))
        frames = TiledFrames(frames, offsets)
    return Workload(points=np.ascontiguousarray(pts, np.float32), normals=nrm, gt=gt, mass=mass,
                    frames=frames, taxonomy=tax, voxel_size=vs)
