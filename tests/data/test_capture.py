"""The capture core (diffuser_lab/data/capture.py): frames at one resolution with K scaled to it, the
cloud from a file / the format / the depth, depth rendered when frames have none, ground truth carried
from the frames' label images, and the summary's capture line."""
import dataclasses

import numpy as np
import pytest
from datasets import make_world

from diffuser_lab.data.capture import (CaptureOptions, CapturedFrame, capture_scene, carry_frame_labels,
                                      check_stated_size)
from diffuser_lab.data.clouds import read_cloud, write_las
from diffuser_lab.data.geometry import scaled_intrinsics
from diffuser_lab.data.render import MeshRenderer, sample_surface
from diffuser_lab.data.scene import IGNORE, SCANNET20, Frame
from diffuser_lab.data.poses import rigid_inverse
from diffuser_lab.data.visibility import CloudDepth, MeshDepth


@pytest.fixture(scope="module")
def world():
    return make_world()


def _frames(world, *, depth=True, labels=True, k_scale=1):
    """The world's views as a format would find them; K given for a k_scale x larger image."""
    out = []
    H, W = world["views"][0][0].shape
    for i, (d, lab, _) in enumerate(world["views"]):  # loop over 4 views
        K = scaled_intrinsics(world["K"], (H, W), (H * k_scale, W * k_scale))
        out.append(CapturedFrame(f"v{i}", world["poses"][i], K, K_size=(H * k_scale, W * k_scale),
                                 depth=(lambda d=d: d) if depth else None,
                                 labels=(lambda lab=lab: lab) if labels else None,
                                 size=None if depth else (H, W)))
    return out


def test_intrinsics_scaled_to_the_frames_resolution(world):
    s = capture_scene("w", _frames(world, k_scale=3), CaptureOptions(), SCANNET20)
    np.testing.assert_allclose(s.frames[0].K, world["K"], atol=1e-9)  # K for 3x the size, scaled back
    assert s.frames.info["visibility"] == "depth images"
    assert "back-projected" in s.frames.info["cloud"]


def test_ground_truth_carried_from_the_frames(world):
    s = capture_scene("w", _frames(world), CaptureOptions(), SCANNET20)
    stats = s.frames.info["gt_from_frames"]
    assert s.gt_labels is not None and stats["points_labelled"] == int((s.gt_labels != IGNORE).sum()) > 0
    # the rule: the label most seeing pixels hold; on a rendered world the views agree almost always
    assert stats["vote_agreement"] > 0.97
    # against the mesh's own labels at the points (ray cast straight back at each point)
    r = MeshRenderer(world["verts"], world["tris"], world["tri_lab"])
    pts = s.points[s.gt_labels != IGNORE]
    centre = rigid_inverse(world["poses"][0])[:3, 3]
    dirs = pts - centre
    t, prim = r.cast_full(np.broadcast_to(centre, dirs.shape), dirs)
    truth = r._label_lut[prim]
    assert (truth == s.gt_labels[s.gt_labels != IGNORE]).mean() > 0.9


def test_carry_rule_majority_and_ties():
    pts = np.array([[0, 0, 1.0], [0.5, 0, 1.0]], np.float32)
    K = np.array([[10, 0, 5], [0, 10, 5], [0, 0, 1.0]])
    depth = np.ones((11, 11), np.float32)
    f = lambda lab: Frame("f", K, np.eye(4), depth, gt_labels=np.full((11, 11), lab, np.int16))  # noqa: E731
    labels, st = carry_frame_labels(pts, [f(3), f(3), f(1)], 20)
    assert labels.tolist() == [3, 3] and st["points_disagreeing"] == 2 and abs(st["vote_agreement"] - 2 / 3) < 1e-9
    labels, _ = carry_frame_labels(pts, [f(4), f(2)], 20)
    assert labels.tolist() == [2, 2]  # a tie: the lower class id
    labels, st = carry_frame_labels(pts, [Frame("f", K, np.eye(4), depth * 3, gt_labels=np.full((11, 11), 1, np.int16))], 20)
    assert labels.tolist() == [IGNORE, IGNORE] and st["points_labelled"] == 0  # depth check failed: no vote


def test_no_depth_renders_it_from_the_cloud_or_the_mesh(world, tmp_path):
    ref = capture_scene("w", _frames(world), CaptureOptions(cloud_stride=1), SCANNET20)
    cloud = {"points": ref.points, "source": "given"}
    s = capture_scene("w", _frames(world, depth=False), CaptureOptions(), SCANNET20, cloud=cloud)
    assert s.frames.info["visibility"].startswith("depth rendered from the cloud")
    d_real, d_cloud = world["views"][1][0], s.frames[1].depth
    both = (d_real > 0) & (d_cloud > 0)
    assert both.mean() > 0.8 and (np.abs(d_real[both] - d_cloud[both]) < 0.05).mean() > 0.8  # metres
    mesh = tmp_path / "room.ply"
    import open3d as o3d
    o3d.io.write_triangle_mesh(str(mesh), o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(world["verts"].astype(np.float64)), o3d.utility.Vector3iVector(world["tris"])))
    s = capture_scene("w", _frames(world, depth=False), CaptureOptions(mesh=str(mesh)), SCANNET20, cloud=cloud)
    assert "mesh room.ply" in s.frames.info["visibility"]
    np.testing.assert_allclose(s.frames[2].depth, world["views"][2][0], atol=1e-4)  # the same ray caster
    with pytest.raises(ValueError, match="frames have no depth images and no cloud is given"):
        capture_scene("w", _frames(world, depth=False), CaptureOptions(), SCANNET20)
    with pytest.raises(ValueError, match="visibility=depth expected them"):
        capture_scene("w", _frames(world, depth=False), CaptureOptions(visibility="depth"), SCANNET20, cloud=cloud)


def test_cloud_depth_closes_a_sampled_surface_and_keeps_the_front(world):
    pts, _, _ = sample_surface(world["verts"], world["tris"], world["tri_lab"], 0.03, 0)
    render = CloudDepth(pts)
    assert 0.01 < render.median_spacing < 0.05
    d = render(world["K"], world["poses"][0], world["views"][0][0].shape)
    real = world["views"][0][0]
    both = (real > 0) & (d > 0)
    assert both.sum() > 0.9 * (real > 0).sum()
    assert (np.abs(d[both] - real[both]) < 0.05).mean() > 0.9  # within the depth check's tolerance
    m = MeshDepth(world["verts"], world["tris"])(world["K"], world["poses"][0], real.shape)
    np.testing.assert_allclose(m, real, atol=1e-4)


def test_las_round_trip_and_errors(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.uniform(-5, 5, (500, 3)).astype(np.float32) + np.float32([1000, 2000, 30])  # a georeferenced offset
    lab = rng.integers(-1, 20, 500)
    for suffix in ("las", "laz"):  # loop over the two encodings
        files = write_las(tmp_path / f"c.{suffix}", pts, lab, SCANNET20.names, SCANNET20.colorize(lab))
        back = read_cloud(files[0])
        assert np.abs(back["points"] - pts).max() < 2e-3 and (back["labels"] == lab).all()
        assert (back["colors"] == SCANNET20.colorize(lab)).all() and back["source"] == f"c.{suffix}"
    import laspy
    las = laspy.read(str(tmp_path / "c.las"))
    assert (np.asarray(las.classification) == np.where(lab >= 0, lab + 1, 0)).all()
    assert b'"1": "wall"' in las.header.vlrs[-1].record_data
    (tmp_path / "t.laz").write_bytes((tmp_path / "c.laz").read_bytes()[:300])
    with pytest.raises(ValueError, match=r"t\.laz: LAS header says .* the file has 300 bytes"):  # truncated
        read_cloud(tmp_path / "t.laz")
    with pytest.raises(ValueError, match=r"c\.xyz: point cloud of unknown type \.xyz"):
        read_cloud(tmp_path / "c.xyz")


def test_a_laz_cloud_is_the_points_to_label(world, tmp_path):
    ref = capture_scene("w", _frames(world), CaptureOptions(), SCANNET20)
    path = write_las(tmp_path / "scan.laz", ref.points, ref.gt_labels, SCANNET20.names)[0]
    s = capture_scene("w", _frames(world, depth=False, labels=False), CaptureOptions(cloud=str(path)), SCANNET20)
    assert np.abs(s.points - ref.points).max() < 1e-4 and (s.gt_labels == ref.gt_labels).all()
    assert s.frames.info["cloud"] == f"{len(ref.points):,} points from scan.laz"


def test_a_stated_size_is_the_image_or_a_downscale_that_keeps_its_aspect(world):
    """Issue 52 item 4: the size a format states for K against the image it describes."""
    assert check_stated_size((480, 640), (480, 640), "t.json", "a.png") == ""
    for image, factor in (((240, 320), "1/2"), ((192, 256), "1/2.5"), ((121, 161), "1/3.975")):  # images_2, 7.5x, odd
        assert f"scaled by {factor} to the {image[1]}x{image[0]} images" in check_stated_size((480, 640), image, "t.json", "a.png")
    for image in ((480, 480), (960, 1280), (1, 640), (478, 640)):  # aspect changed, an upscale, a row short
        with pytest.raises(ValueError, match=rf"^t\.json: K is stated for 640x480 \(W x H\) images, a\.png is "
                                             rf"{image[1]}x{image[0]}: expected that size or a downscale"):
            check_stated_size((480, 640), image, "t.json", "a.png")
    # through the capture builder: K for a 2x larger image is scaled and said; one for another aspect is refused
    s = capture_scene("w", _frames(world, k_scale=2), CaptureOptions(), SCANNET20, cloud={"points": world["verts"]})
    f = s.frames[0]
    np.testing.assert_allclose(f.K, world["K"], atol=1e-9)
    assert "scaled by 1/2" in s.frames.info["intrinsics"]
    bad = [dataclasses.replace(cf, K_size=(cf.K_size[0], cf.K_size[1] + 7), K_from="cam.yaml")
           for cf in _frames(world, k_scale=2)]
    with pytest.raises(ValueError, match=r"^cam\.yaml: K is stated for .* frame v0's depth image is 80x60"):
        capture_scene("w", bad, CaptureOptions(), SCANNET20, cloud={"points": world["verts"]}).frames[0]
