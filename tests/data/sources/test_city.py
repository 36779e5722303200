"""Procedural outdoor city (diffuser_lab.data.sources.city): tiny cities, coarse points, few small views."""
import dataclasses

import numpy as np
import pytest

from diffuser_lab.data.sources.city import CityOptions
from diffuser_lab.data.geometry import visible_projection
from diffuser_lab.data.scene import IGNORE
from diffuser_lab.data.sources.city import CITYSCAPES19, block_mesh, block_points, make_city_scene
from diffuser_lab.data.taxonomy import load_taxonomy

C = {n: i for i, n in enumerate(CITYSCAPES19.names)}
# 40 m blocks, 0.4 m points, two street and two drone views (32-40 m up) of 96 x 72 per block; frames
# see 75 m, so a frame's blocks are its own and those up to two blocks away
TINY = dict(block_size=40.0, point_spacing=0.4, street_views=2, drone_views=2, image_width=96, image_height=72,
            view_distance=75.0, drone_height=[32.0, 40.0])


def tiny(**kw) -> CityOptions:
    return CityOptions(**{**TINY, **kw})


@pytest.fixture(scope="module")
def city():
    return make_city_scene(tiny(blocks_x=2, blocks_y=1))


def test_taxonomy_is_the_shipped_cityscapes19():
    shipped = load_taxonomy("cityscapes19")
    assert CITYSCAPES19.names == shipped.names
    assert np.array_equal(CITYSCAPES19.colors, shipped.colors)


def test_deterministic_and_a_block_whatever_the_extent(city):
    scene, _ = city
    again, _ = make_city_scene(tiny(blocks_x=2, blocks_y=1))
    for attr in ("points", "normals", "gt_labels"):
        assert np.array_equal(getattr(scene, attr), getattr(again, attr))
    assert scene.points.dtype == np.float32 and scene.gt_labels.dtype == np.int16
    # block (0, 0) comes first and is the same in a 1 x 1 and a 2 x 2 city, and alone
    one, _ = make_city_scene(tiny(blocks_x=1, blocks_y=1))
    p, _, lab = block_points(tiny(blocks_x=5, blocks_y=7), 0, 0)
    assert np.array_equal(one.points, scene.points[:one.n_points]) and np.array_equal(one.points, p)
    assert np.array_equal(one.gt_labels, lab)
    v1, t1, l1 = block_mesh(tiny(), 1, 0)
    v2, t2, l2 = block_mesh(tiny(blocks_x=9, blocks_y=9), 1, 0)
    assert np.array_equal(v1, v2) and np.array_equal(t1, t2) and np.array_equal(l1, l2)
    # block (1, 0) lies in its own cell (up to overhanging tree crowns) and differs from block (0, 0)
    assert v1[:, 0].min() > 40.0 - 4.0 and v1[:, 0].max() < 80.0 + 4.0
    other, _ = make_city_scene(tiny(blocks_x=1, blocks_y=1, seed=1))
    assert other.n_points != one.n_points or not np.array_equal(other.points, one.points)


def test_a_frame_is_the_same_whatever_the_extent():
    small, _ = make_city_scene(tiny(blocks_x=3, blocks_y=3, point_spacing=2.0))
    big, _ = make_city_scene(tiny(blocks_x=4, blocks_y=4, point_spacing=2.0))
    assert small.frames.names[:4] == big.frames.names[:4]
    for i in range(4):  # block (0, 0)'s frames: the blocks within 75 m are in both cities
        a, b = small.frames[i], big.frames[i]
        assert np.array_equal(a.T_cw, b.T_cw) and np.array_equal(a.depth, b.depth)
        assert np.array_equal(a.gt_labels, b.gt_labels)


def test_labels_present_and_plausible(city):
    scene, _ = city
    share = np.bincount(scene.gt_labels, minlength=19) / scene.n_points
    assert (scene.gt_labels >= 0).all() and share[C["sky"]] == 0 and share[C["train"]] == 0
    for name, lo, hi in (("road", 0.05, 0.4), ("sidewalk", 0.02, 0.25), ("building", 0.1, 0.7),
                         ("vegetation", 0.02, 0.4), ("terrain", 0.02, 0.4), ("car", 0.01, 0.2)):
        assert lo < share[C[name]] < hi, (name, share[C[name]])
    for name in ("pole", "person", "fence"):
        assert share[C[name]] > 0, name
    np.testing.assert_allclose(np.linalg.norm(scene.normals, axis=1), 1.0, atol=1e-5)
    # the road is at z = 0, the sidewalk and terrain on the 15 cm lot; the city is 80 x 40 m
    assert np.median(np.abs(scene.points[scene.gt_labels == C["road"], 2])) < 0.05
    assert (scene.points[:, :2].min(0) > -0.1).all() and (scene.points[:, :2].max(0) < [84, 44]).all()


def test_drone_and_street_views(city):
    scene, _ = city
    names = scene.frames.names
    assert len(names) == 8 and len(set(names)) == 8
    kinds = [n.rsplit("_", 1)[1] for n in names]
    assert kinds.count("street") == 4 and kinds.count("nadir") == 2 and kinds.count("oblique") == 2
    for f, kind in zip(scene.frames, kinds):
        eye = -f.T_cw[:3, :3].T @ f.T_cw[:3, 3]
        gaze = f.T_cw[2, :3]  # optical axis in world
        if kind == "street":
            assert 1.5 <= eye[2] <= 2.0 and abs(gaze[2]) < 0.25
        else:
            assert 32.0 <= eye[2] <= 40.0 and gaze[2] < -0.45
        assert f.depth.shape == (72, 96) and f.depth.dtype == np.float32 and f.gt_labels.dtype == np.int16
        hit = f.depth > 0
        assert hit.mean() > (0.3 if kind == "nadir" else 0.1), f.name  # a tiny city: obliques see past its edge
        assert ((f.gt_labels != IGNORE) & (f.gt_labels != C["sky"]) == hit).all()
        assert f.depth.max() <= 75.0 + 1e-3  # z-depth <= range <= view_distance


def test_frames_agree_with_the_points(city):
    scene, _ = city
    seen = agree = 0
    for f in scene.frames:
        idx, rows, cols = visible_projection(scene.points, f, depth_tol=0.1)
        seen += len(idx)
        agree += np.count_nonzero(f.gt_labels[rows, cols] == scene.gt_labels[idx])
    assert seen > 5000 and agree / seen > 0.9, (seen, agree / seen)


def test_sky_where_nothing_is_hit_looking_up(city):
    scene, _ = city
    street = [f for f in scene.frames if f.name.endswith("street")]
    assert any((f.gt_labels == C["sky"]).any() for f in street)
    off, _ = make_city_scene(tiny(blocks_x=1, blocks_y=1, sky=False))
    assert not any((f.gt_labels == C["sky"]).any() for f in off.frames)


def test_pipeline_diffuser_beats_bayesian():
    from tests.conftest import compose

    from diffuser_lab.runs.pipeline import run

    cfg = compose("scene=city", "record=off", "scene.options.blocks_x=2", "scene.options.blocks_y=1",
                  *(f"scene.options.{k}={v}" for k, v in TINY.items() if k != "street_views"),
                  "scene.options.street_views=4", "scene.options.drone_views=4")
    assert cfg.taxonomy.name == "cityscapes19" and cfg.scene.source == "city"
    res = run(cfg)
    assert res.scene.taxonomy.name == "cityscapes19"
    assert res.metrics["miou"] > res.baseline["bayesian"]["miou"] + 3


def test_realistic_city_predictions():
    from tests.conftest import compose

    cfg = compose("scene=city", "predictions=realistic_city")
    assert cfg.predictions.region_size == 4.0 and cfg.predictions.view_range_m == 60.0
    assert cfg.predictions.persistence == 0.95  # the rest is predictions=realistic
    assert compose("scene=city", "taxonomy=scannet20").taxonomy.name == "scannet20"
    assert compose().taxonomy.name == "scannet20"


def test_other_taxonomy_needs_a_mapping():
    from diffuser_lab.config import SceneConfig
    from diffuser_lab.data.scene import SCANNET20
    from diffuser_lab.data.sources import city

    with pytest.raises(ValueError, match="taxonomy=cityscapes19"):
        city.load(dataclasses.replace(SceneConfig(), source="city", options=tiny(blocks_x=1, blocks_y=1)), SCANNET20,
                  None)


def test_frames_alone_are_the_scenes_frames(city):
    """The ``frames`` entry (a tiled run's workers) gives the frames of ``load`` without sampling the cloud."""
    from diffuser_lab.config import SceneConfig
    from diffuser_lab.data.sources import city as source
    from diffuser_lab.runs.pipeline import load_frames

    scene, _ = city
    cfg = dataclasses.replace(SceneConfig(), source="city", options=tiny(blocks_x=2, blocks_y=1))
    frames = load_frames(cfg, CITYSCAPES19)
    assert list(frames.names) == list(scene.frames.names)
    for i in (0, len(frames) - 1):
        a, b = frames[i], scene.frames[i]
        assert np.array_equal(a.depth, b.depth) and np.array_equal(a.gt_labels, b.gt_labels)
    with pytest.raises(ValueError, match="taxonomy=cityscapes19"):
        from diffuser_lab.data.scene import SCANNET20
        source.frames(cfg, SCANNET20, None)
