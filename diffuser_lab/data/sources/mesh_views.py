"""Views rendered from a labelled triangle mesh (e.g. ScanNet's ``*_vh_clean_2.labels.ply``).

The scene's points are the mesh vertices (as in the paper's global protocol, which labels
every vertex of the scene mesh) with their ground-truth labels and the mesh's vertex normals.
Frames are rendered with open3d ray casting along a seeded camera path that stays inside the
scene and looks at its content: z-depth and ground-truth label images, which the predictions
layer then corrupts or replaces.
"""
from __future__ import annotations

from pathlib import Path
from dataclasses import dataclass
from typing import Optional

import numpy as np
from omegaconf import MISSING

from diffuser_lab import progress
from diffuser_lab.config import SceneConfig, Section, at_least, check, key, within
from diffuser_lab.data.mapping import load_mapping, native_mapping
from diffuser_lab.data.meshes import mesh_label_ids, read_labelled_mesh, vertex_normals
from diffuser_lab.data.render import MeshRenderer, camera_trajectory, intrinsics, render_views
from diffuser_lab.data.scene import IGNORE, SCANNET20, Frame, Scene, Taxonomy
from diffuser_lab.data.sensor import SensorModel

__all__ = ["MeshViewsOptions", "load_mesh_views", "triangle_labels", "load", "label_ids"]


@dataclass
class MeshViewsOptions(Section):
    """Views rendered from a labelled mesh (diffuser_lab.data.sources.mesh_views)."""

    KEY = "scene.options"
    path: str = MISSING  # PLY mesh with a per-vertex `label` (e.g. ScanNet's *_vh_clean_2.labels.ply)
    mapping: Optional[str] = "nyu40_to_scannet20"  # mesh label ids -> taxonomy (shipped table or CSV); null = taxonomy ids
    n_views: int = key(40, at_least(1))
    seed: int = 0
    image_width: int = 320
    image_height: int = 240
    fov_deg: float = key(58.0, within(10, 150))  # horizontal; ScanNet's depth camera: fx = 577.9 at 640 px
    min_coverage: float = key(0.3, within(0, 1, open_hi=True))  # reject views whose valid-depth share is below this
    eye_height_min: float = 1.2  # metres above the floor
    eye_height_max: float = 1.8

    def _check_keys(self) -> None:
        check(self.image_width >= 16 and self.image_height >= 16, "scene.options.image_width/height",
               (self.image_width, self.image_height), ">= 16 pixels")
        check(0.0 < self.eye_height_min <= self.eye_height_max, "scene.options.eye_height_min/max",
               (self.eye_height_min, self.eye_height_max), "0 < min <= max")



def triangle_labels(vertex_labels: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(T,) label of each triangle: the majority of its three vertex labels (first vertex on a tie)."""
    a, b, c = (vertex_labels[triangles[:, i]] for i in range(3))
    return np.where((b == c) & (a != b), b, a).astype(np.int16)


def load_mesh_views(path: str | Path, *, taxonomy: Taxonomy = SCANNET20, mapping: str | None = "nyu40_to_scannet20",
                    n_views: int = 40, seed: int = 0, image_width: int = 320, image_height: int = 240,
                    fov_deg: float = 58.0, min_coverage: float = 0.3,
                    eye_height_range: tuple[float, float] = (1.2, 1.8), name: str | None = None,
                    sensor=None) -> Scene:
    """Load a labelled mesh and render ``n_views`` views of it.

    Args:
        path: PLY mesh with faces and a per-vertex ``label`` property.
        mapping: mesh label ids -> ``taxonomy`` (shipped table name or CSV path); None = the ids
            already are taxonomy ids.
        fov_deg: horizontal field of view; intrinsics have square pixels and a centred principal point.
        sensor: a :class:`~diffuser_lab.data.sensor.SensorModel` for the frames' depth, or None
            (perfect z-depth). Points, poses and label images do not depend on it.
    Returns:
        Scene with points = vertices (world metres), normals, colours, gt_labels (IGNORE where
        unannotated or unmapped) and frames carrying depth and gt label images.
    """
    path = Path(path)
    with progress.stage(f"reading mesh {path.name}"):
        vertices, triangles, raw_labels, colors = read_labelled_mesh(path)
    if raw_labels is None:
        raise ValueError(f"{path}: the mesh has no per-vertex 'label' property; mesh_views needs a labelled mesh")
    table = load_mapping(mapping, taxonomy) if mapping is not None else native_mapping(taxonomy)
    if table is not None:
        try:
            gt, _ = table.apply(raw_labels)
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None
    else:
        gt = raw_labels.astype(np.int16)
        if gt.max() >= taxonomy.num_classes or gt.min() < IGNORE:
            raise ValueError(f"{path}: labels in [{gt.min()}, {gt.max()}] are not {taxonomy.name} ids; set a mapping")
    renderer = MeshRenderer(vertices, triangles, triangle_labels(gt, triangles))
    K = intrinsics(image_width, image_height, fov_deg)
    poses = camera_trajectory(vertices, n_views, seed, width=image_width, height=image_height, K=K,
                              renderer=renderer, min_coverage=min_coverage, eye_height_range=eye_height_range)
    views = render_views(renderer, K, poses, image_width, image_height, sensor=sensor)
    frames = [Frame(name=f"view_{i:04d}", K=K, T_cw=T, depth=depth, gt_labels=labels)
              for i, (T, (depth, labels)) in enumerate(zip(poses, views))]
    stem = path.name.split(".")[0]
    return Scene(name=name or f"{stem}_views{len(frames)}_seed{seed}", points=vertices.astype(np.float32),
                 taxonomy=taxonomy, frames=frames, normals=vertex_normals(vertices, triangles), colors=colors,
                 gt_labels=gt)


def load(cfg: SceneConfig, taxonomy: Taxonomy, sensor: Optional[SensorModel]) -> Scene:
    """``scene.source=mesh_views``: the views the ``scene.options`` keys ask for."""
    m = cfg.options
    return load_mesh_views(m.path, taxonomy=taxonomy, mapping=m.mapping, n_views=m.n_views, seed=m.seed,
                           image_width=m.image_width, image_height=m.image_height, fov_deg=m.fov_deg,
                           min_coverage=m.min_coverage, eye_height_range=(m.eye_height_min, m.eye_height_max),
                           sensor=sensor)


def label_ids(cfg: SceneConfig, n: int) -> list[tuple[np.ndarray, str]]:
    """``taxonomy=ids``: the mesh's vertex labels."""
    return mesh_label_ids(Path(cfg.options.path))
