"""Ray-cast rendering of labelled triangle meshes, surface sampling and camera paths.

Used to build synthetic scenes whose every quantity is known exactly: z-depth and
label images of posed pinhole views, and a labelled point cloud sampled on the
same mesh.

Conventions (see :mod:`diffuser_lab.data.scene`): world metres, ``T_cw`` world-to-camera,
camera looks along +z with x right and y down. Pixel ``(u, v)`` (column, row) has its
centre at image coordinate ``(u, v)`` (the OpenCV convention used by
:mod:`diffuser_lab.data.geometry`), so a point projecting to ``(x, y)`` lands in pixel
``(round(x), round(y))``. Open3D's ``create_rays_pinhole`` puts pixel centres at
``(u + 0.5, v + 0.5)``; :meth:`MeshRenderer.render` shifts the principal point by half
a pixel to match.
"""
from __future__ import annotations

import math
import threading

import numpy as np

from diffuser_lab import progress
from diffuser_lab import seeding
from diffuser_lab.seeding import Seed

from .meshes import closed_components, inside_closed, triangle_normals
from .o3d import open3d
from .scene import IGNORE

__all__ = [
    "look_at",
    "intrinsics",
    "MeshRenderer",
    "sample_surface",
    "camera_trajectory",
    "render_views",
]


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera transform of a camera at ``eye`` looking at ``target``.

    Args:
        eye: (3,) camera centre, world metres.
        target: (3,) point the optical axis (+z) goes through, world metres.
        up: (3,) world up direction; the image's y axis (down) points against it.
            When the gaze is (nearly) parallel to ``up`` another up is used.

    Returns:
        (4, 4) float64 ``T_cw`` with rows of the rotation = camera x, y, z axes in world.
    """
    # Norms and products written out, not through BLAS (np.linalg.norm of a vector and @ call
    # OpenBLAS, whose kernels round differently on AVX2 and AVX-512 CPUs): the same pose everywhere.
    eye = np.asarray(eye, np.float64)
    z = np.asarray(target, np.float64) - eye
    norm = _norm3(z)
    if norm < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    z /= norm
    up = np.asarray(up, np.float64)
    x = np.cross(z, up)
    if _norm3(x) < 1e-6 * _norm3(up):
        # Looking straight along up: any horizontal right vector will do.
        alt = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
        x = np.cross(z, alt)
    x /= _norm3(x)
    y = np.cross(z, x)  # image down = forward x right
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z])
    T[:3, 3] = -(T[:3, :3] * eye).sum(1)
    return T


def _norm3(v: np.ndarray) -> float:
    """|v| of a (3,) vector, summed in a fixed order."""
    return float(np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]))


def intrinsics(width: int, height: int, fov_deg: float) -> np.ndarray:
    """(3, 3) float64 pinhole K with square pixels, horizontal field of view
    ``fov_deg`` (degrees) and principal point at the image centre ((w-1)/2, (h-1)/2),
    pixel centres at integer coordinates."""
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2.0)  # libm: numpy's tan rounds by CPU
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def _open3d():
    """open3d, imported on first use (~0.5 s: importing a scene source does not pay it)."""
    return open3d()


class MeshRenderer:
    """Ray caster for a labelled triangle mesh (Open3D Embree scene, built once).

    Args:
        vertices: (V, 3) world coordinates, metres.
        triangles: (T, 3) int vertex indices.
        triangle_labels: (T,) int class id of each triangle (IGNORE allowed).
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, triangle_labels: np.ndarray):
        self.vertices = np.ascontiguousarray(vertices, np.float32)
        self.triangles = np.ascontiguousarray(triangles, np.uint32)
        self.triangle_labels = np.asarray(triangle_labels, np.int16)
        if self.triangle_labels.shape != (len(self.triangles),):
            raise ValueError("triangle_labels must have one entry per triangle")
        self.normals, _ = triangle_normals(self.vertices, self.triangles)
        self.normals = self.normals.astype(np.float32)  # (T, 3) unit, winding order
        o3d = _open3d()
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.triangles))
        # Label lookup with a trailing IGNORE slot for "no hit" (INVALID_ID).
        self._label_lut = np.append(self.triangle_labels, np.int16(IGNORE))
        self._planes: tuple[np.ndarray, np.ndarray] | None = None  # float64 normals and offsets, on first render
        self._lock = threading.Lock()  # one cast at a time (open3d's own threads cast each batch)

    def _cast(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:  # frames read ahead on several threads may render from one scene
            ans = self.scene.cast_rays(_open3d().core.Tensor(np.ascontiguousarray(rays, np.float32)))
        t_hit = ans["t_hit"].numpy()
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        prim[~np.isfinite(t_hit)] = len(self.triangles)
        return t_hit, prim

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """First-hit ray parameter for rays ``origins + t * directions``.

        Args:
            origins: (..., 3) world metres. directions: (..., 3), not necessarily unit.

        Returns:
            (...,) float32 ``t`` in units of ``|direction|`` (metres for unit
            directions); inf where nothing is hit.
        """
        o, d = np.broadcast_arrays(np.asarray(origins, np.float32), np.asarray(directions, np.float32))
        return self._cast(np.concatenate([o, d], axis=-1))[0]

    def cast_full(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Like :meth:`cast` but also returns the (...,) int64 hit triangle index
        (``len(triangles)`` where nothing is hit)."""
        o, d = np.broadcast_arrays(np.asarray(origins, np.float32), np.asarray(directions, np.float32))
        return self._cast(np.concatenate([o, d], axis=-1))

    def hits_back_face(self, directions: np.ndarray, prim: np.ndarray) -> np.ndarray:
        """(...,) bool: the ray with (..., 3) ``directions`` hit triangle ``prim`` from
        behind (direction along its normal), i.e. it started inside a closed solid or
        behind a one-sided surface. False where nothing was hit."""
        hit = prim < len(self.triangles)
        n = self.normals[np.where(hit, prim, 0)]
        return hit & (np.einsum("...k,...k->...", np.asarray(directions, np.float32), n) > 0)

    def render(self, K: np.ndarray, T_cw: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Render z-depth and label images of a pinhole view.

        Args:
            K: (3, 3) intrinsics, pixels. T_cw: (4, 4) world-to-camera, metres.
            width, height: image size in pixels.

        Returns:
            depth: (H, W) float32 z-depth in metres along the optical axis, 0 = no hit.
            labels: (H, W) int16 label of the hit triangle, IGNORE where nothing is hit.
        """
        depth, labels, _ = self._render(K, T_cw, width, height)
        return depth, labels

    def render_with_normals(self, K: np.ndarray, T_cw: np.ndarray, width: int,
                            height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Like :meth:`render`, plus (H, W, 3) float32 unit normals of the hit triangles in the
        camera frame (winding-order sign, as the mesh has it; zero where nothing is hit)."""
        depth, labels, prim = self._render(K, T_cw, width, height)
        hit = prim < len(self.triangles)
        R = np.asarray(T_cw, np.float64)[:3, :3]
        n = _rotate(self._normals64[np.where(hit, prim, 0)], R)  # written-out sums, no BLAS
        return depth, labels, np.where(hit[..., None], n, 0.0).astype(np.float32)

    def _render(self, K, T_cw, width, height):
        """Depth, labels and hit triangles of a view. The ray caster decides which triangle a pixel
        sees; the depth is then the exact z of that triangle's plane along the pixel's ray, in
        float64 rounded to float32, not the caster's own t (Embree's AVX2 and AVX-512 kernels round
        t differently, ~1e-7 relative): the same depth image on every CPU."""
        K_o3d = np.array(K, np.float64)
        K_o3d[:2, 2] += 0.5  # Open3D casts pixel (u, v) through (u + 0.5, v + 0.5)
        o3d = _open3d()
        T = np.asarray(T_cw, np.float64)
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            o3d.core.Tensor(K_o3d), o3d.core.Tensor(T), int(width), int(height))
        _, prim = self._cast(rays.numpy())
        hit = prim < len(self.triangles)
        # the pixel's ray in the world, z = 1 in the camera: eye + z * dirs
        Kf = np.asarray(K, np.float64)
        u = (np.arange(width, dtype=np.float64) - Kf[0, 2]) / Kf[0, 0]
        v = (np.arange(height, dtype=np.float64) - Kf[1, 2]) / Kf[1, 1]
        cam = np.empty((height, width, 3))
        cam[..., 0], cam[..., 1], cam[..., 2] = u[None, :], v[:, None], 1.0
        R = T[:3, :3]
        dirs = _rotate(cam, R.T)
        eye = -_rotate(T[:3, 3], R.T)
        p = np.where(hit, prim, 0)
        n = self._normals64[p]
        num = self._offsets64[p] - _dot3(n, eye)
        den = _dot3(n, dirs)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = num / den
        depth = np.where(hit & np.isfinite(z) & (z > 0), z, 0.0).astype(np.float32)
        return depth, self._label_lut[prim], prim

    @property
    def _normals64(self) -> np.ndarray:
        """(T, 3) float64 unit normals of the triangles (the planes :meth:`_render` intersects)."""
        if self._planes is None:
            n, _ = triangle_normals(self.vertices, self.triangles)
            self._planes = (n, _dot3(n, self.vertices.astype(np.float64)[self.triangles[:, 0]]))
        return self._planes[0]

    @property
    def _offsets64(self) -> np.ndarray:
        """(T,) float64 plane offsets n . v0 of the triangles."""
        self._normals64
        return self._planes[1]


def _dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a . b over the last axis (size 3), summed in a fixed order (no BLAS, no SIMD reordering)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _rotate(x: np.ndarray, R: np.ndarray) -> np.ndarray:
    """(..., 3) vectors x multiplied by the (3, 3) matrix R (R @ x), summed in a fixed order."""
    return np.stack([_dot3(x, R[i]) for i in range(3)], -1)


def sample_surface(
    vertices: np.ndarray,
    triangles: np.ndarray,
    triangle_labels: np.ndarray,
    spacing: float,
    seed: Seed,
    noise: float = 0.0,
    *,
    occlusion_offset: float = 1e-3,
    occlusion_dist: float = 0.05,
    backface_occludes: bool = True,
    renderer: MeshRenderer | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Area-uniform random points on a labelled mesh, as a scanner would see them.

    Each triangle gets ``area / spacing^2`` points in expectation (stochastic rounding
    of the count, uniform barycentric positions). Points whose surface is covered by
    other geometry (wall behind a picture, floor under a cabinet, touching box faces)
    are dropped: a point is hidden when a ray from it along its normal (starting
    ``occlusion_offset`` off the surface) hits geometry within ``occlusion_dist``, or when
    that start lies inside a closed solid of the mesh (a leg top under a table top, the end
    of a shelf against a side panel: :func:`~diffuser_lab.data.meshes.inside_closed`, decided
    in float64 from the geometry, not from which of two coincident faces the ray caster reports
    first), or when the ray first hits the back of an open surface (it starts behind a
    one-sided wall). Normals must therefore point to the visible side (outward winding).

    Every draw is keyed (:mod:`diffuser_lab.seeding`): a triangle's count by (seed, triangle),
    a sample's position and noise by (seed, triangle, sample number), so a point that is kept
    on one machine and dropped on another changes nothing else.

    Args:
        vertices: (V, 3) world metres. triangles: (T, 3) int. triangle_labels: (T,) int.
        spacing: metres; density is one point per ``spacing^2`` of area.
        seed: the draws' seed, an int or a key prefix (e.g. ``(seed, bx, by)``).
        noise: std of isotropic gaussian position noise, metres (applied after the
            visibility test; normals stay the exact triangle normals).
        occlusion_offset, occlusion_dist: metres, see above.
        backface_occludes: apply the inside and back-face rules (needs outward-wound
            solids; turn off for open scanned meshes with unreliable winding).
        renderer: a :class:`MeshRenderer` of the same mesh to reuse, else one is built.

    Returns:
        points (N, 3) float32 world metres, normals (N, 3) float32 unit,
        labels (N,) int16 triangle labels.
    """
    v = np.asarray(vertices, np.float64)
    tri = np.asarray(triangles, np.int64)
    tri_lab = np.asarray(triangle_labels, np.int16)
    n_tri, area = triangle_normals(v, tri)

    tid = np.arange(len(tri))
    expected = area / float(spacing) ** 2
    counts = np.floor(expected).astype(np.int64)
    counts += seeding.uniform(seed, "surface.count", tid) < (expected - counts)
    idx = np.repeat(tid, counts)
    j = np.arange(len(idx)) - np.repeat(np.cumsum(counts) - counts, counts)  # sample number in its triangle

    # Uniform barycentric sampling: fold the unit square onto the triangle.
    uv = seeding.uniform(seed, "surface.uv", idx[:, None], j[:, None], np.arange(2)[None])
    flip = uv.sum(1) > 1.0
    uv[flip] = 1.0 - uv[flip]
    a, b, c = v[tri[idx, 0]], v[tri[idx, 1]], v[tri[idx, 2]]
    pts = a + uv[:, :1] * (b - a) + uv[:, 1:] * (c - a)
    nrm = n_tri[idx]

    with progress.stage(f"sampling surface points ({len(idx):,} candidates)"):
        if renderer is None:
            renderer = MeshRenderer(v, tri, tri_lab)
        start = pts + occlusion_offset * nrm
        t, prim = renderer.cast_full(start, nrm)
        keep = t > occlusion_dist  # near hit = covered by a touching or hung object
        if backface_occludes:
            comp, closed = closed_components(v, tri)
            keep &= ~inside_closed(start, v, tri, (comp, closed))
            open_face = np.append(~closed[comp], False)  # the no-hit slot: not a face
            keep &= ~(renderer.hits_back_face(nrm, prim) & open_face[prim])
    pts, nrm, idx, j = pts[keep], nrm[keep], idx[keep], j[keep]

    if noise > 0:
        pts = pts + noise * seeding.normal(seed, "surface.noise", idx[:, None], j[:, None], np.arange(3)[None])
    return pts.astype(np.float32), nrm.astype(np.float32), tri_lab[idx]


def _fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) float64 near-uniform unit directions (deterministic)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z**2)
    phi = np.pi * (1.0 + 5**0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def camera_trajectory(
    vertices: np.ndarray,
    n_views: int,
    seed: Seed,
    *,
    width: int,
    height: int,
    K: np.ndarray,
    renderer: MeshRenderer,
    min_coverage: float = 0.3,
    eye_height_range: tuple[float, float] = (1.2, 1.8),
    margin: float = 0.5,
    max_tries_factor: int = 20,
    pitch_range_deg: tuple[float, float] = (-40.0, -5.0),
    min_clearance: float = 0.3,
    min_target_dist: float = 1.0,
) -> list[np.ndarray]:
    """Handheld-scan-like camera poses inside a room mesh, ordered like a video.

    Eyes are uniform in the mesh's axis-aligned bounding box shrunk by ``margin``
    (metres) in x and y, at a height drawn from ``eye_height_range`` (metres above
    the floor = min z, clipped to the box). Each camera heads towards a point sampled
    area-uniformly on the mesh (at least ``min_target_dist`` metres away horizontally
    when possible), with a downward pitch drawn in ``pitch_range_deg`` (degrees,
    negative = down), like someone scanning a room. A candidate is rejected when:
    its eye is closer than ``min_clearance`` metres to geometry, it looks from inside
    or behind a surface (most first hits around it are back faces, or nothing is
    below it), or the fraction of pixels with valid depth is below ``min_coverage``.
    Accepted views are chained greedily by nearest neighbour on (eye, point 1 m
    ahead), so consecutive views overlap.

    Candidate c's draws (eye, height, targets, pitch) are keyed by (seed, c)
    (:mod:`diffuser_lab.seeding`), so rejecting or accepting one candidate changes no other.
    "Inside" is decided from the geometry where it can be: an eye inside a closed solid
    (:func:`~diffuser_lab.data.meshes.inside_closed`); only back faces of open surfaces are
    counted (a face coincident with another's reads front or back by a rounding).

    Args:
        vertices: (V, 3) mesh vertices, world metres (z up).
        n_views: number of poses to return.
        seed: the draws' seed, an int or a key prefix.
        width, height, K: image size (pixels) and (3, 3) intrinsics used for coverage.
        renderer: :class:`MeshRenderer` of the mesh.
        max_tries_factor: at most ``max_tries_factor * n_views`` candidates are tried.

    Returns:
        list of ``n_views`` (4, 4) float64 ``T_cw``.

    Raises:
        ValueError: when fewer than ``n_views`` acceptable poses are found.
    """
    v = np.asarray(vertices, np.float64)
    lo, hi = v.min(0), v.max(0)
    xy_lo, xy_hi = lo[:2] + margin, hi[:2] - margin
    bad = xy_lo > xy_hi  # room narrower than 2 * margin: use its centre line
    mid = 0.5 * (lo[:2] + hi[:2])
    xy_lo, xy_hi = np.where(bad, mid, xy_lo), np.where(bad, mid, xy_hi)

    # Area-weighted target sampling on the mesh (vertices are not uniform on box meshes).
    tri = renderer.triangles.astype(np.int64)
    tv = renderer.vertices.astype(np.float64)
    _, area = triangle_normals(tv, tri)
    cdf = np.cumsum(area)
    cdf /= cdf[-1]

    probe = _fibonacci_sphere(64)
    comp, closed = closed_components(tv, tri)
    open_face = np.append(~closed[comp], False)  # the no-hit slot: not a face
    max_tries = int(max_tries_factor * n_views)
    batch = max(8, 2 * n_views)
    poses: list[np.ndarray] = []
    tried = 0
    n_close = n_inside = n_cover = 0
    with progress.stage("choosing camera views", total=n_views, unit="view") as bar:
        while len(poses) < n_views and tried < max_tries:
            m = min(batch, max_tries - tried)
            cand = np.arange(tried, tried + m)[:, None]  # the candidates' numbers: their draws' keys
            tried += m
            eyes = np.empty((m, 3))
            eyes[:, :2] = xy_lo + (xy_hi - xy_lo) * seeding.uniform(seed, "camera.eye", cand, np.arange(2))
            h = eye_height_range[0] + (eye_height_range[1] - eye_height_range[0]) * seeding.uniform(
                seed, "camera.height", cand[:, 0])
            eyes[:, 2] = np.clip(lo[2] + h, lo[2], hi[2])

            # Clearance / inside test for the whole batch in one cast.
            dirs = np.broadcast_to(probe, (m, len(probe), 3))
            t_hit, prim = renderer.cast_full(np.repeat(eyes[:, None], len(probe), 1), dirs)
            hit = np.isfinite(t_hit)
            back = renderer.hits_back_face(dirs, prim) & open_face[prim]
            below = np.isfinite(renderer.cast(eyes, np.array([0.0, 0.0, -1.0])))
            close = np.where(hit, t_hit, np.inf).min(1) < min_clearance
            inside = (back.sum(1) > 0.3 * np.maximum(hit.sum(1), 1)) | ~below
            inside |= inside_closed(eyes, tv, tri, (comp, closed))

            # Heading towards a content point; a few draws to get one far enough away.
            tgt_idx = np.searchsorted(cdf, seeding.uniform(seed, "camera.target", cand, np.arange(4)))
            tgt_idx = np.minimum(tgt_idx, len(tri) - 1)
            r = seeding.uniform(seed, "camera.target_point", cand[..., None], np.arange(4)[:, None], np.arange(2))
            r = np.where(r.sum(-1, keepdims=True) > 1.0, 1.0 - r, r)  # uniform in the triangle (folded square)
            w = np.concatenate([1.0 - r.sum(-1, keepdims=True), r], -1)  # (m, 4, 3) barycentric
            tgt = np.einsum("mjk,mjkd->mjd", w, tv[tri[tgt_idx]])  # (m, 4, 3)
            hd = np.linalg.norm(tgt[..., :2] - eyes[:, None, :2], axis=-1)
            pick = np.argmax(hd >= min_target_dist, axis=1)  # first far one (0 if none)
            heading = tgt[np.arange(m), pick, :2] - eyes[:, :2]
            heading /= np.maximum(np.linalg.norm(heading, axis=1, keepdims=True), 1e-9)
            pitch = np.deg2rad(pitch_range_deg[0] + (pitch_range_deg[1] - pitch_range_deg[0]) * seeding.uniform(
                seed, "camera.pitch", cand[:, 0]))
            fwd = np.concatenate([heading * np.cos(pitch)[:, None], np.sin(pitch)[:, None]], axis=1)

            for i in range(m):
                if len(poses) >= n_views:
                    break
                if close[i]:
                    n_close += 1
                    continue
                if inside[i]:
                    n_inside += 1
                    continue
                T = look_at(eyes[i], eyes[i] + fwd[i])
                depth, _ = renderer.render(K, T, width, height)
                if np.count_nonzero(depth) < min_coverage * depth.size:
                    n_cover += 1
                    continue
                poses.append(T)
                bar.set(len(poses))

    if len(poses) < n_views:
        raise ValueError(
            f"camera_trajectory: found only {len(poses)} of {n_views} acceptable views in "
            f"{tried} tries (rejected: {n_close} too close to geometry (<{min_clearance} m), "
            f"{n_inside} inside/behind geometry, {n_cover} valid-depth fraction < {min_coverage}); "
            f"lower min_coverage/margin or raise max_tries_factor")
    return _order_chain(poses)


def _order_chain(poses: list[np.ndarray]) -> list[np.ndarray]:
    """Greedy nearest-neighbour chain on (eye, point 1 m ahead) so that consecutive
    views are close in position and gaze; starts at the view nearest the scene's
    min-x end of the eye cloud for a deterministic, open-ended path."""
    R = np.stack([T[:3, :3] for T in poses])
    t = np.stack([T[:3, 3] for T in poses])
    eyes = -np.einsum("nji,nj->ni", R, t)  # -R^T t
    feat = np.concatenate([eyes, eyes + R[:, 2]], axis=1)
    d = np.linalg.norm(feat[:, None] - feat[None], axis=-1)
    order = [int(np.argmin(eyes[:, 0]))]
    used = np.zeros(len(poses), bool)
    used[order[0]] = True
    for _ in range(len(poses) - 1):  # loop over views, not points
        row = np.where(used, np.inf, d[order[-1]])
        j = int(np.argmin(row))
        order.append(j)
        used[j] = True
    return [poses[i] for i in order]


def render_views(renderer: MeshRenderer, K: np.ndarray, poses, width: int, height: int, sensor=None):
    """Render every pose of ``poses`` ((4, 4) ``T_cw``): a list of (depth, labels) as
    :meth:`MeshRenderer.render` returns them, shown as the stage "rendering views".

    ``sensor``: a :class:`~diffuser_lab.data.sensor.SensorModel` applied to the depth of view i
    (seeded by i, with the rendered normals), or None for perfect depth."""
    out = []
    what = "rendering views" if sensor is None else "rendering views (sensor depth)"
    with progress.stage(what, total=len(poses), unit="view") as bar:
        for i, T in enumerate(poses):  # loop over views
            if sensor is None:
                out.append(renderer.render(K, T, width, height))
            else:
                depth, labels, normals = renderer.render_with_normals(K, T, width, height)
                out.append((sensor.apply(depth, K, i, normals=normals), labels))
            bar.update()
    return out
