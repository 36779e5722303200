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

With ``num_classes`` C above 21 (the many-classes rows: 64, 150, 200, as ScanNet-200, ADE20K-150
or MSeg-194 would give), each of the 21 base classes b is split into sub-classes b, b + 21,
b + 42, ... < C by space (:func:`split_classes`): a point's votes and ground truth for b go to the
sub-class picked by a hash of its 1 m grid cell. So a point sees the few classes of its
surroundings, as in a real 200-class scene, while every class occurs somewhere; the random
single votes then go to any of the C classes. The frames keep the 21 base classes.

Points come in the order :func:`~diffuser_lab.data.geometry.voxel_downsample` leaves them (sorted by
voxel key, x-major), as a voxelised scan would; nothing here orders them for the solver.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from diffuser_lab import progress, seeding
from diffuser_lab.data.frames import LazyFrames
from diffuser_lab.data.geometry import voxel_downsample
from diffuser_lab.data.render import MeshRenderer, camera_trajectory, intrinsics, sample_surface
from diffuser_lab.data.scene import SCANNET20, Frame, Scene, Taxonomy
from diffuser_lab.data.simulate import simulate_predictions
from diffuser_lab.data.sources.demo import demo_mesh
from diffuser_lab.method.evidence import Evidence, add_frame

ROOM_AREA_M2 = 82.0  # visible surface of the default demo room (calibrated: N ~ area / voxel^2)


def taxonomy21() -> Taxonomy:
    """ScanNet-20 plus an ``otherprop`` class: the 21 classes of the benchmark rows."""
    colors = np.vstack([SCANNET20.colors, np.array([[120, 120, 120]], np.uint8)])
    return Taxonomy(name="scannet20+other", names=SCANNET20.names + ("otherprop",), colors=colors)


def split_classes(points: np.ndarray, labels: np.ndarray, num_classes: int, base: int = 21,
                  cell: float = 1.0) -> np.ndarray:
    """Per point, the sub-class of base class ``labels`` (N,) in ``num_classes`` C >= ``base``
    classes: b + base * (h % n_b), h a hash of the point's ``cell``-metre grid cell and
    n_b = ceil((C - b) / base) the sub-classes of b (module doc). IGNORE (negative) stays."""
    ijk = np.floor(points / cell).astype(np.int64)
    h = (ijk[:, 0] * 73856093) ^ (ijk[:, 1] * 19349663) ^ (ijk[:, 2] * 83492791)
    lab = np.asarray(labels, np.int64)
    n_sub = np.maximum((num_classes - np.clip(lab, 0, None) + base - 1) // base, 1)
    out = lab + base * (np.abs(h) % n_sub)
    return np.where(lab < 0, lab, out)


def taxonomy_many(num_classes: int) -> Taxonomy:
    """The workload's C-class taxonomy: sub-class b + 21 v is ``{name of b}_{v}`` (module doc)."""
    base = taxonomy21()
    ids = np.arange(num_classes)
    names = tuple(f"{base.names[c % 21]}_{c // 21}" for c in ids)
    colors = base.colors[ids % 21].astype(np.int64) + 7 * (ids // 21)[:, None]
    return Taxonomy(name=f"bench{num_classes}", names=names, colors=(colors % 256).astype(np.uint8))


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


def cycled_frames(base: Sequence[Frame], n: int) -> LazyFrames:
    """``n`` frames that cycle through ``base`` (renamed per index): many frames, constant memory."""

    def load(i: int) -> Frame:
        f = base[i % len(base)]
        return dataclasses.replace(f, name=f"{f.name}_{i:05d}")

    return LazyFrames(n, load)


def tiled_frames(base: Sequence[Frame], offsets: np.ndarray) -> LazyFrames:
    """The views of one room, repeated for each of the room's translated copies (lazy)."""

    def load(i: int) -> Frame:
        t, j = divmod(i, len(base))
        f = base[j]
        T = np.eye(4)
        T[:3, 3] = -offsets[t]
        return dataclasses.replace(f, name=f"tile{t:03d}_{f.name}", T_cw=f.T_cw @ T)

    return LazyFrames(len(base) * len(offsets), load)


def _room_cloud(n_points: int, seed: int, verts, tris, labs, renderer):
    vs = math.sqrt(ROOM_AREA_M2 / n_points)
    for attempt in range(3):  # secant on the voxel size: a couple of tries land within ~1 %
        pts, nrm, lab = sample_surface(verts, tris, labs, vs / 2.0, (seed, attempt), noise=0.002, renderer=renderer)
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
    if num_classes not in (20, 21) and not 21 < num_classes <= 32767:
        raise ValueError(f"num_classes={num_classes}: expected 20, 21 or 22..32767")
    many = num_classes > 21
    tax = taxonomy21() if num_classes == 21 else SCANNET20 if num_classes == 20 else taxonomy_many(num_classes)
    base_classes = 21 if many else num_classes
    verts, tris, labs = demo_mesh(seed)
    renderer = MeshRenderer(verts, tris, labs)
    tiles = max(1, math.ceil(n_points / tile_points))
    pts, nrm, gt, vs = _room_cloud(round(n_points / tiles), seed, verts, tris, labs, renderer)
    K = intrinsics(width, height, 70.0)
    poses = camera_trajectory(verts, n_views, seed, width=width, height=height, K=K, renderer=renderer)
    frames = []
    with progress.stage("workload views: rendering + simulated 2D predictions", total=len(poses), unit="view") as bar:
        for i, T in enumerate(poses):
            depth, lab = renderer.render(K, T, width, height)
            pred = simulate_predictions(lab, base_classes, (seed, i),
                                        class_names=taxonomy21().names if many else tax.names)
            frames.append(Frame(name=f"view_{i:04d}", K=K.copy(), T_cw=T, depth=depth, labels=pred, gt_labels=lab))
            bar.update()
    mass = None
    if with_mass:
        ev = Evidence.empty(len(pts), base_classes)
        with progress.stage("workload evidence", total=len(frames), unit="frame") as bar:
            for f in frames:
                add_frame(ev, pts, f)
                bar.update()
        mass = ev.mass
        if many:  # base class b's votes to b's sub-class at the point (split_classes)
            sub = split_classes(pts, np.broadcast_to(np.arange(21), mass.shape).T, num_classes).T  # (N, 21)
            many_mass = np.zeros((len(pts), num_classes), np.float32)
            np.put_along_axis(many_mass, sub, mass, axis=1)
            mass = many_mass
        seen = np.flatnonzero(mass.any(1))  # a share noise_votes of them get one vote of a random class
        noisy = seen[seeding.uniform(seed, "workload.noise_vote", seen) < noise_votes]
        mass[noisy, seeding.integers(seed, "workload.noise_class", num_classes, noisy)] += 1.0
    if many:
        gt = split_classes(pts, gt, num_classes).astype(np.int16)
    if tiles > 1:
        extent = pts.max(0) - pts.min(0)
        offsets = np.zeros((tiles, 3))
        offsets[:, 0] = np.arange(tiles) * (extent[0] + 1.0)
        pts = (pts[None] + offsets[:, None].astype(np.float32)).reshape(-1, 3)
        nrm, gt = np.tile(nrm, (tiles, 1)), np.tile(gt, tiles)
        mass = None if mass is None else np.tile(mass, (tiles, 1))
        frames = tiled_frames(frames, offsets)
    return Workload(points=np.ascontiguousarray(pts, np.float32), normals=nrm, gt=gt, mass=mass,
                    frames=frames, taxonomy=tax, voxel_size=vs)
