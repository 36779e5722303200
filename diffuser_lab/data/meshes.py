"""Triangle meshes shared by the scene sources and the renderer: a PLY mesh with per-vertex labels and
colours, its label ids, and the one rule for its normals: a face's by the right-hand rule on its
vertex order (:func:`triangle_normals`), a vertex's the area-weighted sum of its faces' (a local-PCA
normal where a vertex has no face of non-zero area: :func:`vertex_normals`)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from diffuser_lab.data import inputs
from diffuser_lab.data.geometry import estimate_normals

__all__ = ["read_labelled_mesh", "triangle_normals", "vertex_normals", "mesh_label_ids", "closed_components",
           "inside_closed"]


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
    inputs.record(path, "mesh")
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


def closed_components(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh's connected components and which of them are closed solids.

    Two triangles are connected when they share a vertex index (vertices are not welded by position:
    two boxes that touch at a corner stay two solids). A component is a closed solid when every edge of it is used
    by exactly two of its triangles, once in each direction: a watertight, consistently wound surface
    (for an outward winding, :func:`inside_closed`'s winding number is 1 inside).

    Args:
        vertices: (V, 3) world metres. triangles: (T, 3) int vertex indices.

    Returns:
        comp (T,) int64 component of each triangle, closed (C,) bool per component.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    t = np.asarray(triangles, np.int64)
    nv = len(vertices)
    a, b = t.ravel(), t[:, [1, 2, 0]].ravel()  # the directed edges, three per triangle
    graph = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(nv, nv))
    n_comp, vcomp = connected_components(graph, directed=False)
    comp = vcomp[t[:, 0]].astype(np.int64)
    key = a * nv + b
    uk, cnt = np.unique(key, return_counts=True)
    rev = b * nv + a
    pos = np.minimum(np.searchsorted(uk, rev), len(uk) - 1)
    ok = (cnt[np.searchsorted(uk, key)] == 1) & (uk[pos] == rev) & (a != b)
    edge_comp = np.repeat(comp, 3)
    bad = np.bincount(edge_comp[~ok], minlength=n_comp)
    return comp, (bad == 0) & (np.bincount(comp, minlength=n_comp) > 0)


def inside_closed(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray,
                  components: tuple[np.ndarray, np.ndarray] | None = None, chunk: int = 1 << 18) -> np.ndarray:
    """Whether each point lies inside a closed solid of the mesh: its generalised winding number
    with respect to a closed component (:func:`closed_components`; outward winding) is above 1/2,
    computed in float64 from the exact geometry (the solid angle of each triangle, Van Oosterom and
    Strackee's formula). A point more than a rounding error away from the surface gets a winding
    number within 1e-9 of 0 or 1, so the answer does not depend on how a CPU rounds.

    Args:
        points: (N, 3) world metres. vertices: (V, 3). triangles: (T, 3) int.
        components: :func:`closed_components` of the mesh, if already known.
        chunk: point-triangle pairs evaluated at once (memory bound).

    Returns:
        (N,) bool.
    """
    from scipy.spatial import cKDTree

    p = np.asarray(points, np.float64)
    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles, np.int64)
    comp, closed = closed_components(v, t) if components is None else components
    out = np.zeros(len(p), bool)
    solids = np.flatnonzero(closed)
    if len(p) == 0 or len(solids) == 0:
        return out
    order = np.argsort(comp, kind="stable")
    starts = np.searchsorted(comp[order], np.arange(len(closed) + 1))
    corners = v[t]  # (T, 3, 3)
    lo = np.minimum.reduceat(corners.min(1)[order], starts[:-1].clip(max=len(t) - 1))
    hi = np.maximum.reduceat(corners.max(1)[order], starts[:-1].clip(max=len(t) - 1))
    tree = cKDTree(p)
    centre, radius = (lo + hi) / 2, np.linalg.norm(hi - lo, axis=1) / 2 * (1 + 1e-9) + 1e-12
    near = tree.query_ball_point(centre[solids], radius[solids])
    for c, cand in zip(solids, near):  # loop over solids, each vectorised over its points and faces
        cand = np.asarray(cand, np.int64)
        cand = cand[np.all((p[cand] >= lo[c]) & (p[cand] <= hi[c]), axis=1)]
        if len(cand) == 0:
            continue
        faces = corners[order[starts[c]:starts[c + 1]]]  # (F, 3, 3)
        step = max(1, chunk // len(faces))
        for s in range(0, len(cand), step):  # loop over chunks of points
            q = cand[s:s + step]
            out[q] = _winding(p[q], faces) > 0.5
    return out


def _winding(q: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(M,) generalised winding numbers of the (M, 3) points with respect to the (F, 3, 3) triangles."""
    d = faces[None] - q[:, None, None, :]  # (M, F, 3, 3)
    a, b, c = d[:, :, 0], d[:, :, 1], d[:, :, 2]
    la, lb, lc = (np.sqrt(np.einsum("mfk,mfk->mf", x, x)) for x in (a, b, c))
    det = np.einsum("mfk,mfk->mf", a, np.cross(b, c))
    den = (la * lb * lc + np.einsum("mfk,mfk->mf", a, b) * lc + np.einsum("mfk,mfk->mf", b, c) * la
           + np.einsum("mfk,mfk->mf", c, a) * lb)
    return np.arctan2(det, den).sum(1) / (2 * np.pi)


def mesh_label_ids(path: Path) -> list[tuple[np.ndarray, str]]:
    """``taxonomy=ids``: the vertex label ids of a labelled mesh, ``[]`` when it has none."""
    labels = read_labelled_mesh(path)[2]
    return [] if labels is None else [(np.unique(labels), f"the labels of {path.name}")]
