"""Ray-cast rendering, surface sampling and camera trajectories (diffuser_lab.data.render)."""

import numpy as np
import pytest
from conftest import SHARED

from diffuser_lab.data.render import (
    MeshRenderer,
    camera_trajectory,
    intrinsics,
    look_at,
    sample_surface,
)
from diffuser_lab.data.meshes import triangle_normals, vertex_normals
from diffuser_lab.data.scene import IGNORE

_SIGNS = np.array([[(i >> 0) & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], float)
_FACES = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
                   [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])


def box(lo, hi):
    """Closed axis-aligned box mesh with outward winding: (8, 3) verts, (12, 3) tris."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = lo + _SIGNS * (hi - lo)
    t = _FACES.copy()
    n, _ = triangle_normals(v, t)
    flip = np.einsum("tk,tk->t", n, v[t].mean(1) - (lo + hi) / 2) < 0
    t[flip] = t[flip][:, ::-1]
    return v, t


def merge(*meshes):
    vs, ts, n = [], [], 0
    for v, t in meshes:
        vs.append(v)
        ts.append(t + n)
        n += len(v)
    return np.concatenate(vs), np.concatenate(ts)


def slab_hit(o, d, lo, hi):
    """Analytic first intersection parameter of a ray with an axis-aligned box."""
    t1, t2 = (lo - o) / d, (hi - o) / d
    return np.max(np.minimum(t1, t2)), np.min(np.maximum(t1, t2))


def project(K, T, p):
    pc = T[:3, :3] @ p + T[:3, 3]
    return (K @ pc)[:2] / pc[2], pc[2]


def test_fronto_parallel_depth_is_z_not_ray_length():
    v, t = box((-1, -1, 3), (1, 1, 4))
    r = MeshRenderer(v, t, np.full(12, 5))
    K = intrinsics(64, 48, 90.0)
    depth, lab = r.render(K, np.eye(4), 64, 48)
    hit = depth > 0
    # Every hit is on the front face z = 3: the z-depth is exactly 3 although the ray
    # lengths to it differ across the image.
    assert hit[20:28, 28:36].all()
    np.testing.assert_allclose(depth[hit], 3.0, atol=1e-5)
    assert (lab[hit] == 5).all() and (lab[~hit] == IGNORE).all() and (depth[~hit] == 0).all()
    assert (~hit).any()  # the box does not fill the 90 deg view at the corners
    assert depth.dtype == np.float32 and lab.dtype == np.int16


def test_depth_matches_analytic_ray_box_distance_on_axis():
    lo, hi = np.array([-0.4, 0.3, 0.0]), np.array([0.6, 1.1, 0.9])
    v, t = box(lo, hi)
    r = MeshRenderer(v, t, np.zeros(12))
    W, H = 41, 31  # odd: the centre pixel's ray is the optical axis (cx = (W-1)/2 = 20)
    K = intrinsics(W, H, 60.0)
    eye, target = np.array([1.7, -2.3, 1.6]), np.array([0.05, 0.7, 0.4])
    T = look_at(eye, target)
    depth, _ = r.render(K, T, W, H)
    axis = T[2, :3]  # camera z in world
    t_in, t_out = slab_hit(eye, axis, lo, hi)
    assert t_in < t_out and t_in > 0
    assert depth[H // 2, W // 2] == pytest.approx(t_in, abs=1e-4)
    # Every hit pixel back-projects onto the box surface.
    v_, u_ = np.nonzero(depth > 0)
    z = depth[v_, u_]
    pc = np.stack([(u_ - K[0, 2]) / K[0, 0] * z, (v_ - K[1, 2]) / K[1, 1] * z, z], 1)  # centres at integers
    pw = (pc - T[:3, 3]) @ T[:3, :3]
    rel = np.abs(pw - (lo + hi) / 2) / ((hi - lo) / 2)
    np.testing.assert_allclose(rel.max(1), 1.0, atol=1e-4)


def test_look_at_projects_target_to_centre():
    K = intrinsics(160, 120, 70.0)
    for eye, target in [((0.5, 0.2, 1.5), (3.0, 2.5, 0.7)), ((2, 2, 1), (2.1, 1.0, 1.0)),
                        ((0, 0, 2), (0, 0, 0))]:  # the last looks straight down (up || gaze)
        T = look_at(eye, target)
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
        assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
        uv, z = project(K, T, np.asarray(target, float))
        np.testing.assert_allclose(uv, [79.5, 59.5], atol=1e-9)
        assert z > 0
    # Horizontal gaze: world up is image up (smaller v), camera x is world right.
    T = look_at((0, 0, 1), (0, 5, 1))
    (u_up, v_up), _ = project(K, T, np.array([0, 5, 2.0]))
    (u_r, _), _ = project(K, T, np.array([1, 5, 1.0]))
    assert v_up < 59.5 and u_r > 79.5


def test_intrinsics_horizontal_fov():
    K = intrinsics(200, 100, 90.0)
    assert K[0, 0] == pytest.approx(100.0) and K[1, 1] == K[0, 0]
    assert (K[0, 2], K[1, 2]) == (99.5, 49.5)  # image centre with pixel centres at integers


def test_sample_surface_points_on_mesh_and_density():
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.5, 0.25])
    v, t = box(lo, hi)
    pts, nrm, lab = sample_surface(v, t, np.full(12, 3), 0.02, 0)
    area = 2 * (0.5 + 0.25 + 0.125)
    assert len(pts) == pytest.approx(area / 0.02**2, rel=0.05)
    rel = np.abs(pts - (lo + hi) / 2) / ((hi - lo) / 2)
    assert np.abs(rel.max(1) - 1.0).max() < 1e-4 / 0.125
    # Normal points out of the face the point lies on.
    face_axis = np.argmax(rel, axis=1)
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-6)
    assert (np.abs(nrm[np.arange(len(pts)), face_axis]) > 0.999).all()
    assert pts.dtype == np.float32 and nrm.dtype == np.float32 and lab.dtype == np.int16
    assert (lab == 3).all()
    # Noise moves points off the surface by about its std.
    pts_n, _, _ = sample_surface(v, t, np.full(12, 3), 0.02, 0, noise=0.01)
    off = np.abs(np.abs(pts_n - (lo + hi) / 2) - (hi - lo) / 2).min(1)
    assert 0.003 < np.median(off) < 0.02


def test_sample_surface_drops_covered_points():
    # Floor quad (normal +z) with a thin box lying on it 2 mm above, like a rug.
    fv = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    ft = np.array([[0, 1, 2], [0, 2, 3]])
    bv, bt = box((-0.25, -0.25, 0.002), (0.25, 0.25, 0.022))
    v, t = merge((fv, ft), (bv, bt))
    labels = np.r_[np.full(2, 1), np.full(12, 7)]
    pts, nrm, lab = sample_surface(v, t, labels, 0.01, 1)
    fl = lab == 1
    under = fl & (np.abs(pts[:, 0]) < 0.25) & (np.abs(pts[:, 1]) < 0.25)
    assert under.sum() == 0
    away = fl & ((np.abs(pts[:, 0]) > 0.3) | (np.abs(pts[:, 1]) > 0.3))
    assert away.sum() == pytest.approx((4 - 0.36) / 1e-4, rel=0.05)
    # The box's bottom face is hidden too, its top is kept.
    assert not ((lab == 7) & (nrm[:, 2] < -0.5)).any()
    assert ((lab == 7) & (nrm[:, 2] > 0.5)).sum() == pytest.approx(0.25 / 1e-4, rel=0.1)

    # Two cubes touching face to face: the shared faces are inside, both dropped.
    v, t = merge(box((0, 0, 0), (1, 1, 1)), box((1, 0, 0), (2, 1, 1)))
    pts, nrm, _ = sample_surface(v, t, np.zeros(24), 0.05, 2)
    assert not (np.abs(pts[:, 0] - 1.0) < 1e-6).any()
    assert len(pts) == pytest.approx(10 / 0.05**2, rel=0.06)  # the outer 10 m^2 survive


def _shelf():
    """A shelf board (box S, x in [0.1, 1.0]) between two side panels (A: x in [0, 0.1], B: x in
    [1.0, 1.1]) that it touches face to face: a ray from A's inner face starts inside S and leaves S
    where B's face lies, two coincident faces hit at the same t (which one a ray caster reports is
    a rounding: AVX2 and AVX-512 Embree kernels reported different ones)."""
    return merge(box((0, 0, 0), (0.1, 0.4, 1.0)), box((0.1, 0, 0.45), (1.0, 0.4, 0.5)),
                 box((1.0, 0, 0), (1.1, 0.4, 1.0)))


def test_sample_surface_decides_coincident_faces_by_geometry(monkeypatch):
    """A panel's face covered by the touching shelf is dropped whichever of the two coincident faces
    the ray caster reports: the caster's answer swapped between them gives the same points."""
    v, t = _shelf()
    lab = np.repeat([0, 1, 2], 12)
    pts, nrm, _ = sample_surface(v, t, lab, 0.01, 0)
    covered = (np.abs(pts[:, 0] - 0.1) < 1e-6) & (pts[:, 2] > 0.45) & (pts[:, 2] < 0.5)
    assert not covered.any()
    assert not ((np.abs(pts[:, 0] - 1.0) < 1e-6) & (pts[:, 2] > 0.45) & (pts[:, 2] < 0.5)).any()
    # the other answer: every hit on one of two coincident faces reported as the other one's
    cn, _ = triangle_normals(v, t)
    plane = np.round(np.c_[cn, np.einsum("tk,tk->t", cn, v[t[:, 0]])], 9)
    twin = np.arange(len(t))
    for i in range(len(t)):  # loop over a few dozen triangles
        same = np.flatnonzero(np.all(plane == -plane[i], 1))
        if len(same):
            twin[i] = same[0]
    assert (twin != np.arange(len(t))).any()
    cast_full = MeshRenderer.cast_full

    def swapped(self, o, d):
        th, prim = cast_full(self, o, d)
        return th, np.where(prim < len(t), twin[np.minimum(prim, len(t) - 1)], prim)

    monkeypatch.setattr(MeshRenderer, "cast_full", swapped)
    again, _, _ = sample_surface(v, t, lab, 0.01, 0)
    np.testing.assert_array_equal(again, pts)


def test_sample_surface_draws_are_keyed_per_triangle():
    """One triangle more changes no other triangle's samples (keyed draws, not a shared stream)."""
    v, t = box((0, 0, 0), (1, 1, 1))
    far_v, far_t = box((5, 5, 5), (5.5, 5.5, 5.5))
    a, _, _ = sample_surface(v, t, np.zeros(12), 0.05, 3, noise=0.002)
    vv, tt = merge((v, t), (far_v, far_t))
    b, _, lab = sample_surface(vv, tt, np.r_[np.zeros(12), np.ones(12)], 0.05, 3, noise=0.002)
    np.testing.assert_array_equal(b[lab == 0], a)


def test_render_depth_is_the_planes_not_the_casters(monkeypatch):
    """The depth image is the exact z of the hit triangle's plane: equal to the caster's t to its
    rounding (~1e-7), and unchanged when the caster's t moves by such a rounding (another CPU)."""
    v, t, lab = _room()
    r = MeshRenderer(v, t, lab)
    K = intrinsics(80, 60, 70.0)
    T = look_at((0.7, 0.6, 1.5), (3.0, 2.0, 0.5))
    depth, labels = r.render(K, T, 80, 60)
    K5 = K.copy()
    K5[:2, 2] += 0.5
    import open3d as o3d

    rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(o3d.core.Tensor(K5), o3d.core.Tensor(T), 80, 60)
    th = r.scene.cast_rays(rays)["t_hit"].numpy()
    hit = np.isfinite(th)
    np.testing.assert_array_equal(depth > 0, hit)
    np.testing.assert_allclose(depth[hit], th[hit], rtol=2e-6)
    cast = MeshRenderer._cast
    monkeypatch.setattr(MeshRenderer, "_cast", lambda self, rays: (lambda a: (a[0] * np.float32(1 + 3e-7), a[1]))(
        cast(self, rays)))
    d2, l2 = r.render(K, T, 80, 60)
    np.testing.assert_array_equal(d2, depth)
    np.testing.assert_array_equal(l2, labels)


def test_cast_returns_inf_on_miss():
    v, t = box((-1, -1, -1), (1, 1, 1))
    r = MeshRenderer(v, t, np.zeros(12))
    th = r.cast(np.array([[0, 0, 5.0], [0, 0, 5.0]]), np.array([[0, 0, -1.0], [0, 0, 1.0]]))
    assert th[0] == pytest.approx(4.0) and np.isinf(th[1])


def _room():
    """5 x 4 x 2.6 m closed-wall room (inward quads) with two boxes inside."""
    L = (5.0, 4.0, 2.6)
    c = np.array([[0, 0, 0], [L[0], 0, 0], [L[0], L[1], 0], [0, L[1], 0]], float)
    quads = [c, *[np.array([c[k], c[(k + 1) % 4], c[(k + 1) % 4] + [0, 0, L[2]], c[k] + [0, 0, L[2]]])
                  for k in range(4)]]
    qv = np.concatenate(quads)
    qt = np.concatenate([np.array([[0, 1, 2], [0, 2, 3]]) + 4 * k for k in range(5)])
    n, _ = triangle_normals(qv, qt)
    flip = np.einsum("tk,tk->t", n, np.array([2.5, 2.0, 1.3]) - qv[qt].mean(1)) < 0
    qt[flip] = qt[flip][:, ::-1]
    v, t = merge((qv, qt), box((1, 1, 0), (2, 1.8, 0.8)), box((3.5, 0.2, 0), (4.8, 0.8, 2.0)))
    return v, t, np.r_[np.zeros(10), np.full(24, 2)]


def test_camera_trajectory_room():
    v, t, lab = _room()
    r = MeshRenderer(v, t, lab)
    K = intrinsics(80, 60, 70.0)
    poses = camera_trajectory(v, 20, 3, width=80, height=60, K=K, renderer=r)
    assert len(poses) == 20
    eyes = np.array([-T[:3, :3].T @ T[:3, 3] for T in poses])
    assert (eyes[:, :2] >= 0.5 - 1e-9).all() and (eyes[:, :2] <= [4.5, 3.5]).all()
    assert (eyes[:, 2] >= 1.2 - 1e-9).all() and (eyes[:, 2] <= 1.8 + 1e-9).all()
    fwd = np.array([T[2, :3] for T in poses])
    assert (fwd[:, 2] < 0).all()  # handheld scans look slightly down
    for T in poses:
        depth, _ = r.render(K, T, 80, 60)
        assert np.count_nonzero(depth) >= 0.3 * depth.size
    # Ordered like a video: consecutive eyes are closer than random pairs.
    step = np.linalg.norm(np.diff(eyes, axis=0), axis=1).mean()
    pair = np.linalg.norm(eyes[:, None] - eyes[None], axis=-1).mean()
    assert step < 0.6 * pair
    # Deterministic for a seed.
    again = camera_trajectory(v, 20, 3, width=80, height=60, K=K, renderer=r)
    assert all(np.array_equal(a, b) for a, b in zip(poses, again))


def test_camera_trajectory_candidates_are_keyed(monkeypatch):
    """Candidate c's draws are keyed by c: a candidate rejected for a reason of its own (here its
    coverage made to fail) leaves every other pose as it was; the path takes one candidate more."""
    v, t, lab = _room()
    r = MeshRenderer(v, t, lab)
    K = intrinsics(80, 60, 70.0)
    poses = camera_trajectory(v, 12, 5, width=80, height=60, K=K, renderer=r)
    victim = poses[4]
    render = MeshRenderer.render

    def blind(self, K_, T_, w, h):
        d, lb = render(self, K_, T_, w, h)
        return (np.zeros_like(d), lb) if np.array_equal(T_, victim) else (d, lb)

    monkeypatch.setattr(MeshRenderer, "render", blind)
    again = camera_trajectory(v, 12, 5, width=80, height=60, K=K, renderer=r)
    key = lambda T: T.tobytes()
    before, after = {key(T) for T in poses}, {key(T) for T in again}
    assert key(victim) not in after and before - {key(victim)} <= after and len(after - before) == 1


def test_camera_trajectory_raises_when_impossible():
    v, t = box((0, 0, 0), (0.2, 0.2, 0.2))  # a small object, no room around the cameras
    r = MeshRenderer(v, t, np.zeros(12))
    K = intrinsics(32, 24, 60.0)
    with pytest.raises(ValueError, match="acceptable views"):
        camera_trajectory(v, 5, 0, width=32, height=24, K=K, renderer=r,
                          max_tries_factor=4)


SCANNET_PLY = SHARED / "data" / "scannet" / "scene0470_00" / "scene0470_00_vh_clean_2.labels.ply"  # ../shared


@pytest.mark.skipif(not SCANNET_PLY.exists(), reason=f"ScanNet scene0470_00 mesh not available ({SCANNET_PLY})")
def test_camera_trajectory_on_scannet_mesh():
    import open3d as o3d

    m = o3d.io.read_triangle_mesh(str(SCANNET_PLY))
    v, t = np.asarray(m.vertices), np.asarray(m.triangles)
    r = MeshRenderer(v, t, np.zeros(len(t)))
    K = intrinsics(160, 120, 70.0)
    poses = camera_trajectory(v, 40, 0, width=160, height=120, K=K, renderer=r)
    cov = [np.count_nonzero(r.render(K, T, 160, 120)[0]) / (160 * 120) for T in poses]
    assert len(poses) == 40 and min(cov) >= 0.3 and np.mean(cov) > 0.5


def test_vertex_normals_are_open3ds_area_weighted_rule_with_a_pca_fallback():
    """The one vertex-normal rule (data/meshes.py) equals open3d's compute_vertex_normals on a bumpy
    sheet; a vertex of no face gets a unit local-PCA normal, not zero."""
    import open3d as o3d

    g = np.stack(np.meshgrid(np.arange(12.0), np.arange(9.0), indexing="ij"), -1).reshape(-1, 2) * 0.1
    v = np.column_stack([g, 0.05 * np.sin(7 * g[:, 0]) * np.cos(5 * g[:, 1])])
    i = np.arange(11)[:, None] * 9 + np.arange(8)[None]
    t = np.concatenate([np.stack([i, i + 9, i + 1], -1).reshape(-1, 3), np.stack([i + 1, i + 9, i + 10], -1).reshape(-1, 3)])
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t.astype(np.int32)))
    m.compute_vertex_normals(normalized=True)
    n = vertex_normals(v, t)
    np.testing.assert_allclose(n, np.asarray(m.vertex_normals), atol=1e-6)
    lone = vertex_normals(np.vstack([v, [[0.55, 0.4, 0.0]]]), t)[-1]  # inside the sheet, in no face
    assert abs(np.linalg.norm(lone) - 1) < 1e-5 and abs(lone[2]) > 0.9
