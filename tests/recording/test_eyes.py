"""Where run.rrd's 3D views open (recording/eyes.py): the overview eye looks down into the scene
from above one side, the scene whole in view; up from tilted cameras; the online blueprint has
a view riding the moving camera."""
import numpy as np
import pytest

from diffuser_lab.recording.eyes import FOV_Y_DEG, overview_eye, overview_geometry, scene_up
from diffuser_lab.recording.rerun_log import FOLLOW_CAMERA, blueprint, online_blueprint


def room(n=20_000, size=(6.0, 5.0, 2.5), seed=0):
    """(n, 3) points of a floor and four walls, no ceiling (the demo room's shell), metres."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(0, 1, (n, 3)) * size
    side = rng.integers(0, 5, n)  # 0 floor, 1-4 walls
    p[side == 0, 2] = 0.0
    p[side == 1, 0], p[side == 2, 0] = 0.0, size[0]
    p[side == 3, 1], p[side == 4, 1] = 0.0, size[1]
    return p.astype(np.float32)


def look_at(C, target, up):
    """(4, 4) world->camera T_cw of an OpenCV camera at C looking at target (y down = -up)."""
    z = (target - C) / np.linalg.norm(target - C)
    x = np.cross(-up, z)  # x = y cross z, y ~ -up
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])  # rows: the camera's axes in world
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, -R @ C
    return T


def check_oblique(pts, pos, target, up):
    lo, hi = pts.min(0), pts.max(0)
    assert np.all(target >= lo) and np.all(target <= hi)  # the look target is inside the cloud's box
    v = pos - target
    elev = np.degrees(np.arcsin(v @ up / np.linalg.norm(v)))
    assert 35.0 <= elev <= 75.0, elev
    assert pos @ up > (pts @ up).max()  # above the whole cloud (over the walls' tops)
    # every corner of the box between the 2nd and 98th percentiles in front of the eye, inside its
    # (square) field of view, and not so far off that the scene is a speck
    lo, hi = np.percentile(pts, [2, 98], axis=0)
    fwd = -v / np.linalg.norm(v)
    right = np.cross(fwd, up) / np.linalg.norm(np.cross(fwd, up))
    cam_up = np.cross(right, fwd)
    corners = np.array(np.meshgrid(*zip(lo, hi), indexing="ij")).reshape(3, -1).T
    rays = corners - pos
    depth = rays @ fwd
    assert np.all(depth > 0)
    tan = np.maximum(np.abs(rays @ right), np.abs(rays @ cam_up)) / depth
    half = np.tan(np.radians(0.5 * FOV_Y_DEG))
    assert tan.max() < half and tan.max() > 0.7 * half


def test_room_eye_looks_down_into_it_from_above_one_side():
    pts = room()
    pos, target, up = overview_geometry(pts)
    np.testing.assert_allclose(up, [0, 0, 1])
    check_oblique(pts, pos, target, up)
    # the eye is over one side of the room, not straight over its middle (an oblique view)
    assert np.linalg.norm((pos - target)[:2]) > 1.0


def test_a_few_stray_points_do_not_move_the_eye():
    pts = room()
    far = np.vstack([pts, [[500.0, -300.0, 90.0]] * 20])  # 0.1 % outliers
    a, b = overview_geometry(pts), overview_geometry(far)
    np.testing.assert_allclose(a[1], b[1], atol=0.1)
    assert np.linalg.norm(b[0] - b[1]) < 1.2 * np.linalg.norm(a[0] - a[1])


def test_city_scale_and_the_blueprint_component():
    rng = np.random.default_rng(1)
    city = rng.uniform([0, 0, 0], [400, 300, 40], (50_000, 3))
    pos, target, up = overview_geometry(city)
    check_oblique(city, pos, target, up)
    eye = overview_eye(city)
    import rerun.blueprint as rrb

    # the blueprint component carries the geometry: an orbital eye at pos looking at target, up up
    for comp, want in ((eye.position, pos), (eye.look_target, target), (eye.eye_up, up)):
        np.testing.assert_allclose(comp.as_arrow_array().to_pylist()[0], want, rtol=1e-6)
    assert eye.kind.as_arrow_array().to_pylist() == [rrb.Eye3DKind.Orbital.value]
    assert overview_eye(np.zeros((0, 3))) is None  # nothing to frame: Rerun's own eye


def test_up_from_tilted_cameras():
    # a capture whose world is y-up (z points at the viewer): cameras looking around horizontally
    up = np.array([0.0, 1.0, 0.0])
    C = np.array([[np.cos(a), 1.5, np.sin(a)] for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)])
    T = np.stack([look_at(c, np.array([0.0, 1.2, 0.0]) + 3 * (c - [0, 1.5, 0]), up) for c in C])
    np.testing.assert_allclose(scene_up(T), up, atol=1e-6)
    # cameras tilted 20 degrees about x still agree on up
    t = np.radians(20)
    tilt = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    T2 = T.copy()
    T2[:, :3, :3] = np.einsum("ij,fjk->fik", tilt, T[:, :3, :3])
    assert scene_up(T2) @ up > np.cos(np.radians(25))
    # cameras that disagree (half of them upside down): +z
    T3 = T.copy()
    T3[::2, :3, :3] = np.diag([-1, -1, 1]) @ T[::2, :3, :3]
    np.testing.assert_allclose(scene_up(T3), [0, 0, 1])
    # the eye over a y-up room looks down along -y
    pts = room()[:, [0, 2, 1]]
    pos, target, eye_up = overview_geometry(pts, T)
    np.testing.assert_allclose(eye_up, up, atol=1e-6)
    check_oblique(pts, pos, target, eye_up)


def test_without_points_the_cameras_give_the_extent():
    up = np.array([0.0, 0.0, 1.0])
    C = np.array([[x, y, 1.5] for x in (1.0, 5.0) for y in (1.0, 4.0)])
    T = np.stack([look_at(c, np.array([3.0, 2.5, 1.0]), up) for c in C])
    pos, target, _ = overview_geometry(None, T)
    np.testing.assert_allclose(target, [3.0, 2.5, 1.5], atol=0.2)
    assert pos[2] > 1.5


def views3d(bp):
    """The Spatial3DViews of a blueprint (walks its containers)."""
    import rerun.blueprint as rrb

    out, todo = [], [bp.root_container]
    while todo:
        c = todo.pop()
        if isinstance(c, rrb.Spatial3DView):
            out.append(c)
        todo.extend(getattr(c, "contents", None) or [])
    return out


def eye_of(view):
    """The EyeControls3D a Spatial3DView was given (its ``properties``), or None."""
    return (view.properties or {}).get("EyeControls3D")


@pytest.mark.parametrize("has_gt", [True, False])
def test_online_blueprint_has_a_view_through_the_moving_camera(has_gt):
    eye = overview_eye(room())
    views = views3d(online_blueprint(has_gt, growing=True, eye=eye))
    follow = [v for v in views if eye_of(v) is not None and eye_of(v).tracking_entity is not None]
    assert len(follow) == 1
    assert str(eye_of(follow[0]).tracking_entity.as_arrow_array()[0]) == FOLLOW_CAMERA
    # the label image would fill that view: its contents leave it out
    assert "/world/online/camera/**" not in [str(q) for q in follow[0].contents]
    # every other 3D view opens on the overview eye
    others = [v for v in views if v is not follow[0]]
    assert others and all(eye_of(v) is eye for v in others)


def test_batch_blueprint_every_view_opens_on_the_eye():
    eye = overview_eye(room())
    views = views3d(blueprint([("chair", "world/scores/chair")], eye))
    assert len(views) == 8 and all(eye_of(v) is eye for v in views)
    assert all(eye_of(v) is None for v in views3d(blueprint()))
