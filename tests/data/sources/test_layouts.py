"""File layouts as config keys (issue 17, item 3): posed RGB-D folders with any file names, depth
encodings and pose conventions, ScanNet without colour, the prediction file pattern, TUM RGB-D.
Fixtures are written under tmp_path by tests/datasets.py."""
import json
import os

import numpy as np
import pytest
from conftest import SHARED, run_cli
from datasets import H, NYU, W, _save_u16, encode_depth, make_world, write_lab_layout, write_scannet, write_tum

from omegaconf import OmegaConf

from diffuser_lab.config import Config, ConfigError, default_config, to_object
from diffuser_lab.data.mapping import load_mapping
from diffuser_lab.data.predictions import with_predictions
from diffuser_lab.data.images import read_depth_png, resize_nearest
from diffuser_lab.data.prediction_files import DEFAULT_PATTERNS
from diffuser_lab.data.scene import IGNORE, SCANNET20
from diffuser_lab.data.poses import associate, rigid_inverse
from diffuser_lab.data.sources.rgbd_folder import load_rgbd_folder
from diffuser_lab.data.sources.scannet import ScannetOptions, load_scannet
from diffuser_lab.data.sources.tum import load_tum, read_tum_trajectory
from diffuser_lab.runs.pipeline import load_scene

SEVEN_SCENES = SHARED / "data" / "7scenes_sample"

# Every name of the lab layout differs from the defaults; the keys that read it.
RENAMED = dict(intrinsics_file="K.txt", prefix="img_", color="rgb.png", depth="z.png", pose="T.txt",
               segm=None, label="gt.png")
KEYS = dict(intrinsics_file="K.txt", frame_prefix="img_", color_suffix="rgb.png", depth_suffix="z.png",
            pose_suffix="T.txt", label_suffix="gt.png", depth_scale=1000.0, depth_bit_shift=3,
            depth_shift_kind="plain", invalid_depth=(0,), mapping="nyu40_to_scannet20", voxel_size=0.2)


def _scene_cfg(scene: dict):
    """A validated Config whose scene section is ``scene`` (as a scene YAML would give it), its
    options typed and checked as the resolve step does."""
    from diffuser_lab.runs.resolve import with_options

    return with_options(to_object(OmegaConf.merge(OmegaConf.structured(Config), {"scene": scene})))


@pytest.fixture(scope="module")
def world():
    return make_world()


def _same_frame(f, world, i, tol):
    np.testing.assert_allclose(f.K, world["K"], atol=1e-9)
    np.testing.assert_allclose(f.T_cw, world["poses"][i], atol=1e-7)
    assert np.abs(f.depth - world["views"][i][0]).max() <= tol


def test_every_file_name_is_a_key(tmp_path, world):
    root = write_lab_layout(tmp_path, world, **RENAMED)
    s = load_rgbd_folder(root, **KEYS)
    assert s.frames.names == [f"img_{i:06d}" for i in range(4)]
    for i in range(4):  # loop over frames
        f = s.frames[i]
        _same_frame(f, world, i, 0.0005 + 1e-6)
        assert f.rgb is not None and f.rgb.shape == (H, W, 3)
        assert f.gt_labels is not None and (f.gt_labels >= 0).mean() > 0.9
    # the same folder read with one key left at its default fails, naming what it looked for
    with pytest.raises(FileNotFoundError, match=r"camera-intrinsics\.txt does not exist"):
        load_rgbd_folder(root, **{**KEYS, "intrinsics_file": "camera-intrinsics.txt"})
    with pytest.raises(FileNotFoundError, match=r"no frame-XXXXXX\.z\.png files.*frame_prefix"):
        load_rgbd_folder(root, **{**KEYS, "frame_prefix": "frame-"})
    with pytest.raises(FileNotFoundError, match=r"no img_XXXXXX\.depth\.png files.*depth_suffix"):
        load_rgbd_folder(root, **{**KEYS, "depth_suffix": "depth.png"})
    with pytest.raises(ValueError, match=r"4 z\.png, 0 pose\.txt and 4 rgb\.png files"):
        load_rgbd_folder(root, **{**KEYS, "pose_suffix": "pose.txt"})
    with pytest.warns(UserWarning, match=r"no img_XXXXXX\.color\.jpg colour images.*color_suffix=null"):
        grey = load_rgbd_folder(root, **{**KEYS, "color_suffix": "color.jpg"})
    assert grey.frames[0].rgb is None and (grey.colors == 128).all()  # neutral grey cloud
    assert load_rgbd_folder(root, **{**KEYS, "label_suffix": None}).frames[0].gt_labels is None
    assert load_rgbd_folder(root, **{**KEYS, "color_suffix": None}).frames[0].rgb is None


def test_depth_shift_kinds_against_hand_computed_metres(tmp_path):
    # plain: the camera writes (units << 3) | flags; metres = (raw >> 3) / 1e4
    raw = np.array([[0, 40005, 9879, 65529, 1]], np.uint16)  # (5000 << 3) | 5, (1234 << 3) | 7, (8191 << 3) | 1
    np.testing.assert_array_equal(encode_depth([[0, 0.5, 0.1234, 0.8191]], 1e4, 3, "plain", flags=5)[0, 1:],
                                  [40005, 9877, 65533])
    _save_u16(tmp_path / "plain.png", raw)
    got = read_depth_png(tmp_path / "plain.png", 1e4, 3, (0,), "plain")
    np.testing.assert_allclose(got, [[0.0, 0.5, 0.1234, 0.8191, 0.0]], rtol=1e-6)
    # circular (SUN3D): millimetres rotated left by 3 bits; 9000 mm >= 8192 wraps its top bits around
    mm = np.array([[1500, 9000, 20000]], np.uint32)
    stored = np.array([[12000, 6465, 28930]], np.uint16)  # hand-computed rotl3 of 1500, 9000, 20000
    np.testing.assert_array_equal(encode_depth(mm / 1000.0, 1000.0, 3, "circular"), stored)
    _save_u16(tmp_path / "circ.png", stored)
    np.testing.assert_allclose(read_depth_png(tmp_path / "circ.png", 1000.0, 3, (0,), "circular"),
                               [[1.5, 9.0, 20.0]], rtol=1e-6)
    # the wrong kind gives other metres: a plain shift of 6465 is 808 units, not 9000
    wrong = read_depth_png(tmp_path / "circ.png", 1000.0, 3, (0,), "plain")
    np.testing.assert_allclose(wrong, [[1.5, 0.808, 3.616]], rtol=1e-6)
    with pytest.raises(ValueError, match="depth shift kind 'rot'"):
        read_depth_png(tmp_path / "circ.png", 1000.0, 3, (0,), "rot")


def test_both_pose_conventions_give_the_same_cloud(tmp_path, world):
    kw = dict(prefix="frame-", color="color.png", segm=None)
    c2w = write_lab_layout(tmp_path, world, name="c2w", **kw)
    w2c = write_lab_layout(tmp_path, world, name="w2c", world_to_camera=True, **kw)
    load = dict(intrinsics_file="camera-intrinsics.color.txt", color_suffix="color.png", depth_bit_shift=3,
                depth_shift_kind="plain", voxel_size=0.05)
    a = load_rgbd_folder(c2w, **load)
    b = load_rgbd_folder(w2c, pose_convention="world_to_camera", **load)
    for i in range(4):  # loop over frames
        np.testing.assert_allclose(a.frames[i].T_cw, b.frames[i].T_cw, atol=1e-9)
        _same_frame(b.frames[i], world, i, 0.0005 + 1e-6)
    np.testing.assert_allclose(a.points, b.points, atol=1e-5)
    assert a.n_points > 500
    wrong = load_rgbd_folder(w2c, **load)  # read as camera-to-world: the inverse poses
    assert np.abs(wrong.frames[0].T_cw - world["poses"][0]).max() > 0.1
    with pytest.raises(ValueError, match="pose convention 'c2w'"):
        load_rgbd_folder(c2w, pose_convention="c2w", **load)


def test_config_keys_reach_the_loader(tmp_path, world):
    root = write_lab_layout(tmp_path, world, **RENAMED)
    keys = {"source": "rgbd_folder", "options": {
        "root": str(root), "intrinsics_file": "K.txt", "frame_prefix": "img_", "color_suffix": "rgb.png",
        "depth_suffix": "z.png", "pose_suffix": "T.txt", "label_suffix": "gt.png", "depth_bit_shift": 3,
        "depth_shift_kind": "plain", "invalid_depth": [0], "pose_convention": "camera_to_world",
        "mapping": "nyu40_to_scannet20", "cloud_voxel": 0.2}}
    cfg = _scene_cfg(keys)
    s = load_scene(cfg.scene)
    assert len(s.frames) == 4 and s.frames[3].gt_labels is not None
    _same_frame(s.frames[3], world, 3, 0.0005 + 1e-6)
    for bad, match in (({"depth_shift_kind": "rotate"}, "depth_shift_kind"),
                       ({"pose_convention": "c2w"}, "pose_convention"),
                       ({"depth_suffix": "*.png"}, r"scene\.options\.depth_suffix")):
        with pytest.raises(Exception, match=match):
            _scene_cfg({**keys, "options": {**keys["options"], **bad}})


def test_scannet_without_color_and_renamed_files(tmp_path, world):
    root = write_scannet(tmp_path, world)
    for p in (root / "color").iterdir():
        p.unlink()
    (root / "color").rmdir()
    (root / "depth").rename(root / "depth_mm")
    layout = ScannetOptions(root=str(root), depth="depth_mm/{frame}.png")
    s = load_scannet(root, frame_step=1, layout=layout)
    assert s.frames.names == ["0", "1", "3"] and s.frames.info["has_color"] is False
    f = s.frames[0]
    assert f.rgb is None and f.gt_labels is not None
    _same_frame(f, world, 0, 0.0005 + 1e-6)
    assert s.colors is not None and (s.colors == [100, 150, 200]).all()  # the mesh's own colours
    pred = with_predictions(s.frames, default_config(**{"predictions.source": "gt"}).predictions, s.taxonomy)
    np.testing.assert_array_equal(pred[1].labels, s.frames[1].gt_labels)
    with pytest.raises(FileNotFoundError, match=r"no depth/\{frame\}\.png depth images"):
        load_scannet(root)  # the default name no longer exists
    with pytest.raises(ConfigError, match=r"scene\.options\.depth"):
        _scene_cfg({"source": "scannet", "options": {"root": str(root), "depth": "depth/x.png"}})


def test_prediction_file_pattern_key(tmp_path, world):
    root = write_lab_layout(tmp_path, world, prefix="frame-", color="color.png", segm="segm.png")
    s = load_rgbd_folder(root, intrinsics_file="camera-intrinsics.color.txt", color_suffix="color.png",
                         depth_bit_shift=3, depth_shift_kind="plain", voxel_size=0.2)
    cfg = default_config(**{"predictions.source": "files", "predictions.folder": str(root),
                            "predictions.mapping": "nyu40_to_scannet20", "predictions.pattern": "{name}.segm.png"})
    assert cfg.predictions.pattern == ["{name}.segm.png"]  # one string = a list of one
    frames = with_predictions(s.frames, cfg.predictions, s.taxonomy)
    m = load_mapping("nyu40_to_scannet20", SCANNET20)
    for i in range(4):  # loop over frames
        want = m.apply(resize_nearest(NYU[world["views"][i][2]], (H, W)))[0]
        np.testing.assert_array_equal(frames[i].labels, want)
    assert (frames[0].labels != IGNORE).mean() > 0.9
    # the default search order does not know .segm.png
    assert default_config().predictions.pattern == list(DEFAULT_PATTERNS)
    dflt = default_config(**{"predictions.source": "files", "predictions.folder": str(root)})
    with pytest.raises(FileNotFoundError, match=r"tried frame-000000\.png, frame-000000\.label\.png.*predictions\.pattern"):
        with_predictions(s.frames, dflt.predictions, s.taxonomy)[0]
    # a list is searched in order; a pattern without {name} is refused
    two = default_config(**{"predictions.source": "files", "predictions.folder": str(root),
                            "predictions.mapping": "nyu40_to_scannet20",
                            "predictions.pattern": ["{name}.npy", "{name}.segm.png"]})
    np.testing.assert_array_equal(with_predictions(s.frames, two.predictions, s.taxonomy)[2].labels,
                                  frames[2].labels)
    with pytest.raises(ConfigError, match=r"predictions\.pattern='segm\.png'"):
        default_config(**{"predictions.pattern": "segm.png"})


def test_tum_association_and_quaternion_poses(tmp_path, world):
    # nearest timestamp within max_diff, one-to-one; too far = -1
    t = np.array([0.0, 0.1, 0.2, 0.3])
    np.testing.assert_array_equal(associate(t, np.array([0.005, 0.099, 0.15, 0.31]), 0.02), [0, 1, -1, 3])
    np.testing.assert_array_equal(associate(np.array([0.0, 0.01]), np.array([0.008]), 0.02), [-1, 0])
    np.testing.assert_array_equal(associate(np.array([0.0, 0.01]), np.array([0.008]), 0.02, one_to_one=False),
                                  [0, 0])
    # a hand-made pose: 90 degrees about z, scalar-last quaternion
    (tmp_path / "gt.txt").write_text(f"# t tx ty tz qx qy qz qw\n5.0 1 2 3 0 0 {np.sin(np.pi / 4)} {np.cos(np.pi / 4)}\n")
    ts, T = read_tum_trajectory(tmp_path / "gt.txt")
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert ts.tolist() == [5.0]
    np.testing.assert_allclose(T[0, :3, :3], R, atol=1e-12)
    np.testing.assert_allclose(T[0, :3, 3], [1, 2, 3])
    (tmp_path / "bad.txt").write_text("5.0 1 2 3 0 0 0.5 0.5\n")
    with pytest.raises(ValueError, match=r"bad\.txt: pose at t=5\.000000 has quaternion norm 0\.7071"):
        read_tum_trajectory(tmp_path / "bad.txt")

    root, exp = write_tum(tmp_path, world)
    s = load_tum(root, voxel_size=0.05)
    assert s.frames.names == exp["rgb_stems"]  # frames named after their RGB image
    assert s.frames.info["n_frames_found"] == 6 and s.frames.info["n_no_rgb"] == 1
    assert s.frames.info["n_no_pose"] == 1
    np.testing.assert_allclose(s.frames.info["timestamps"], exp["t_depth"])
    assert s.frames[0].K[0, 0] == 520.9 and s.frames[0].K[1, 2] == 249.7  # fr2 from the folder name
    exact = load_tum(root, intrinsics=tuple(world["K"][[0, 1, 0, 1], [0, 1, 2, 2]]), voxel_size=0.05,
                     frame_step=2)
    assert exact.frames.names == exp["rgb_stems"][::2]
    for k, v in enumerate(exp["views"][::2]):  # loop over frames
        _same_frame(exact.frames[k], world, v, 0.5 / 5000 + 1e-6)
        assert exact.frames[k].rgb.shape == (H, W, 3)
    # at 4 ms the poses (3 ms away) still match, the RGB images (5 ms) do not: nothing is left
    with pytest.raises(ValueError, match=r"none of the 6 depth images .*\(1 without pose, 5 without RGB\)"):
        load_tum(root, max_time_diff=0.004, voxel_size=0.05)
    assert load_tum(root, rgb_list=None, voxel_size=0.05, max_frames=2).frames.names[0] == f"{exp['t_depth'][0]:.6f}"


def test_tum_pose_is_the_trajectory_at_the_depth_time(tmp_path, world):
    """A second sample 7 ms after each depth image (10 ms after the first, 1 cm further along x): the
    frame's pose is the trajectory interpolated at its time (0.3 cm), not the nearest sample's."""
    root, exp = write_tum(tmp_path, world)
    lines = (root / "groundtruth.txt").read_text().splitlines()
    extra = []
    for ln in lines[2:]:
        v = [float(x) for x in ln.split()]
        v[0] += 0.010
        v[1] += 0.01
        extra.append(f"{v[0]:.6f} " + " ".join(f"{x:.9f}" for x in v[1:]))
    (root / "groundtruth.txt").write_text("\n".join(lines + extra) + "\n")
    s = load_tum(root, voxel_size=0.05, max_frames=2)
    for k, v in enumerate(exp["views"][:2]):
        c_interp = rigid_inverse(s.frames[k].T_cw)[:3, 3]
        c_sample = rigid_inverse(world["poses"][v])[:3, 3]
        np.testing.assert_allclose(c_interp - c_sample, [0.003, 0, 0], atol=1e-6)


def test_tum_through_config(tmp_path, world):
    root, exp = write_tum(tmp_path, world)
    cfg = _scene_cfg({"source": "tum", "options": {"root": str(root), "camera": "fr1", "cloud_voxel": 0.05}})
    s = load_scene(cfg.scene)
    assert len(s.frames) == 4 and s.frames[0].K[0, 0] == 517.3 and s.n_points > 100
    with pytest.raises(ConfigError, match=r"scene\.options\.fx/fy/cx/cy"):
        _scene_cfg({"source": "tum", "options": {"root": str(root), "fx": 500.0}})
    from diffuser_lab.runs.resolve import default_config as resolved

    with pytest.raises(ConfigError, match=r"scene\.options\.root is required"):
        resolved(**{"scene.source": "tum"})


@pytest.mark.skipif(not SEVEN_SCENES.is_dir(), reason=f"real 7-Scenes sample absent ({SEVEN_SCENES})")
def test_real_7scenes_through_renamed_links(tmp_path):
    """The real frames, linked (not copied) under other names, load through the keys as the originals."""
    os.symlink(SEVEN_SCENES / "camera-intrinsics.txt", tmp_path / "intrinsics.K")
    for i in range(0, 1000, 250):  # four frames (the sample holds every 10th: frame-000000 ... 000990)
        for src, dst in (("color.jpg", "c.jpg"), ("depth.png", "d.png"), ("pose.txt", "p.txt")):
            os.symlink(SEVEN_SCENES / f"frame-{i:06d}.{src}", tmp_path / f"shot{i:04d}.{dst}")
    kw = dict(intrinsics_file="intrinsics.K", frame_prefix="shot", color_suffix="c.jpg", depth_suffix="d.png",
              pose_suffix="p.txt", depth_shift_kind="plain", voxel_size=0.05)
    linked = load_rgbd_folder(tmp_path, **kw)
    orig = load_rgbd_folder(SEVEN_SCENES, frame_step=25, voxel_size=0.05)
    assert linked.frames.names == ["shot0000", "shot0250", "shot0500", "shot0750"] and len(orig.frames) == 4
    for k in range(4):  # loop over frames
        a, b = linked.frames[k], orig.frames[k]
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.T_cw, b.T_cw)
        np.testing.assert_array_equal(a.rgb, b.rgb)
        assert 0.5 < np.median(a.depth[a.depth > 0]) < 5.0  # millimetres read as metres correctly
    np.testing.assert_allclose(linked.points, orig.points, atol=1e-6)
    # read as world-to-camera, the same files are used as they stand (not inverted)
    w2c = load_rgbd_folder(tmp_path, pose_convention="world_to_camera", **kw)
    np.testing.assert_array_equal(w2c.frames[1].T_cw, np.loadtxt(SEVEN_SCENES / "frame-000250.pose.txt"))


@pytest.mark.slow
def test_cli_end_to_end_on_the_issue_layout(tmp_path, world):
    """The issue's layout (frame-XXXXXX.color.png / .depth.png as (raw >> 3) / 1e3 here / .pose.txt /
    .segm.png network ids, camera-intrinsics.color.txt) through conf/scene/my_rgbd_lab.yaml."""
    root = write_lab_layout(tmp_path, world, label="label.png")
    out = tmp_path / "run"
    r = run_cli("scene=my_rgbd_lab", f"scene.options.root={root}", "scene.options.depth_scale=1000",
                "scene.options.label_suffix=label.png", "scene.options.mapping=nyu40_to_scannet20",
                "scene.options.cloud_voxel=0.1", "predictions=files", f"predictions.folder={root}",
                "predictions.pattern='{name}.segm.png'", "predictions.mapping=nyu40_to_scannet20",
                "record=off", "solver.max_iter=30", f"hydra.run.dir={out}")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "error" not in r.stderr.lower() and "wrong unit" not in r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "ok" and summary["n_frames"] == 4 and summary["scene"] == "lab"
    assert summary["predictions_stats"]["label_files"] == 4  # every frame's .segm.png was read
    # the fixture's network ids are the truth: mapped and resized, they score 100 in 2D against label.png
    assert summary["predictions_2d"]["miou"] == 100.0
    assert summary["coverage_evidence"] > 90 and summary["n_unlabeled"] == 0
    assert np.load(out / "labels.npy").shape == (summary["n_points"],)
    assert "4 frames" in r.stdout and "2D predictions          100.0" in r.stdout
