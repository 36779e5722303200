"""Triangle meshes shared by the scene sources and the renderer: a PLY mesh with per-vertex labels and
colours, its label ids, and the one rule for its normals: a face's by the right-hand rule on its
vertex order (:func:`triangle_normals`), a vertex's the area-weighted sum of its faces' (a local-PCA
normal where a vertex has no face of non-zero area: :func:`vertex_normals`)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from diffuser_lab.data.geometry import estimate_normals

__all__ = ["read_labelled_mesh", "triangle_normals", "vertex_normals", "mesh_label_ids"]


def read_labelled_mesh(path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Read a PLY triangle mesh with an optional per-vertex ``label`` property (plyfile;
    open3d drops ushort properties).

    Returns:
        vertices (V, 3) float32 (file units, metres for ScanNet), triangles (T, 3) int64,
        vertex_labels (V,) int64 or None, colors (V, 3) uint8 or None.
    Raises:
        FileNotFoundError / ValueError: missing file, no x/y/z, no faces, non-triangle faces
        or out-of-range vertex indices.
    """
    from plyfile import PlyData

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file {path} does not exist")
    try:
        # Fixed list length: plyfile parses faces as one (T, 3) array instead of T Python lists.
        ply = PlyData.read(str(path), known_list_len={"face": {"vertex_indices": 3, "vertex_index": 3}})
    except Exception as e:  # plyfile raises several types (non-triangle faces, corrupt files)
        try:
            PlyData.read(str(path))
        except Exception as e2:
            raise ValueError(f"{path}: not a readable PLY file ({type(e2).__name__}: {e2})") from None
        raise ValueError(f"{path}: faces are not all triangles ({e}), expected a triangle mesh") from None
    if "vertex" not in ply or not {"x", "y", "z"} <= set(ply["vertex"].data.dtype.names or ()):
        raise ValueError(f"{path}: PLY has no vertex x/y/z, expected a triangle mesh")
    if "face" not in ply or len(ply["face"].data) == 0:
        raise ValueError(f"{path}: PLY has no faces, expected a triangle mesh (element 'face')")
    v = ply["vertex"].data
    names = set(v.dtype.names)
    vertices = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float32)
    fdata = ply["face"].data
    key = next((k for k in ("vertex_indices", "vertex_index") if k in fdata.dtype.names), None)
    if key is None:
        raise ValueError(f"{path}: faces have no vertex_indices list, expected a triangle mesh")
    triangles = np.asarray(fdata[key]).astype(np.int64).reshape(-1, 3)
    if triangles.min() < 0 or triangles.max() >= len(vertices):
        raise ValueError(f"{path}: face vertex indices outside 0..{len(vertices) - 1}")
    labels = np.asarray(v["label"]).astype(np.int64) if "label" in names else None
    colors = np.stack([v["red"], v["green"], v["blue"]], 1).astype(np.uint8) \
        if {"red", "green", "blue"} <= names else None
    return vertices, triangles, labels, colors


def triangle_normals(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (T, 3) float64 (right-hand rule on the vertex order, zero for
    degenerate triangles) and areas (T,) float64 m^2 of a triangle mesh."""
    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles, np.int64)
    cr = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    norm = np.linalg.norm(cr, axis=1)
    n = cr / np.maximum(norm, 1e-20)[:, None]
    return n, 0.5 * norm


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(V, 3) float32 unit vertex normals: the area-weighted sum of the :func:`triangle_normals` of
    the vertex's faces (open3d's compute_vertex_normals rule), oriented by the mesh winding; a vertex
    in no triangle of non-zero area (or whose faces cancel) gets the local-PCA normal of
    :func:`~diffuser_lab.data.geometry.estimate_normals` instead (sign arbitrary)."""
    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles, np.int64)
    n_tri, area = triangle_normals(v, t)
    w = np.repeat(n_tri * area[:, None], 3, axis=0)  # each face's area-weighted normal, once per corner
    corner = t.ravel()
    acc = np.stack([np.bincount(corner, w[:, k], minlength=len(v)) for k in range(3)], 1)
    norm = np.linalg.norm(acc, axis=1)
    n = (acc / np.maximum(norm, 1e-30)[:, None]).astype(np.float32)
    bad = ~(norm > 1e-12 * max(float(area.max(initial=0.0)), 1e-30))
    if bad.any():  # isolated or only-degenerate-face vertices
        n[bad] = estimate_normals(vertices)[bad]
    return n


def mesh_label_ids(path: Path) -> list[tuple[np.ndarray, str]]:
    """``taxonomy=ids``: the vertex label ids of a labelled mesh, ``[]`` when it has none."""
    labels = read_labelled_mesh(path)[2]
    return [] if labels is None else [(np.unique(labels), f"the labels of {path.name}")]
