"""Replica as NICE-SLAM ships it (issue 27, item 3): the 7-Scenes frames written as traj.txt +
results/frameNNNNNN.jpg + results/depthNNNNNN.png (6553.5 units per metre) + cam_params.json
label the same points as the posed RGB-D folder; the camera file's place and keys; bad input."""
import json
import shutil

import numpy as np
import pytest
from captures import agreement, labels_of, needs_7scenes, seven_frames, write_rgbd_reference
from conftest import compose, run_cli
from PIL import Image

from diffuser_lab.data.poses import rigid_inverse
from diffuser_lab.runs.pipeline import load_scene

SCALE = 6553.5


def write_replica(parent, frames, *, camera="parent", labels=False):
    """NICE-SLAM's layout: parent/Replica/cam_params.json (``camera="parent"``; ``"root"``: in the
    sequence folder; None: none), parent/Replica/room0/traj.txt (row-major camera-to-world, OpenCV
    axes) and results/ (colour copied, depth at 6553.5 units per metre). Returns the sequence folder."""
    root = parent / "Replica" / "room0"
    (root / "results").mkdir(parents=True)
    K = frames[0]["K"]
    cam = {"camera": {"w": 640, "h": 480, "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "scale": SCALE}}
    if camera:
        (root.parent if camera == "parent" else root).joinpath("cam_params.json").write_text(json.dumps(cam))
    lines = []
    for i, f in enumerate(frames):  # loop over frames
        lines.append(" ".join(repr(float(v)) for v in f["c2w"].reshape(-1)))
        shutil.copy(f["color_path"], root / "results" / f"frame{i:06d}.jpg")
        raw = np.rint(f["depth"] * SCALE)
        Image.fromarray(np.where(raw <= 65535, raw, 0).astype(np.uint16)).save(root / "results" / f"depth{i:06d}.png")
        if labels:
            Image.fromarray(np.full((480, 640), i % 3, np.uint8)).save(root / "results" / f"semantic{i:06d}.png")
    (root / "traj.txt").write_text("\n".join(lines) + "\n")
    return root


@pytest.fixture(scope="module")
def seven():
    return seven_frames(5, 20)


@needs_7scenes
def test_replica_agrees_with_the_rgbd_folder(tmp_path, seven):
    """The reference reads the same depth values: 7-Scenes' millimetres at Replica's 1/6553.5 m
    steps (the rounding alone moves ~0.6% of the 2 cm voxels' centroids by over 1 mm)."""
    root = write_replica(tmp_path, seven)
    ref = write_rgbd_reference(tmp_path / "ref", seven)
    for i, f in enumerate(seven):  # loop over frames: the reference's depth at Replica's precision
        shutil.copy(root / "results" / f"depth{i:06d}.png", ref / f"{f['name']}.depth.png")
    ref_pts, ref_lab, _ = labels_of("scene=rgbd_folder", f"scene.options.root={ref}", "scene.options.cloud_stride=8",
                                    f"scene.options.depth_scale={SCALE}", "scene.options.invalid_depth=[0]")
    pts, lab, res = labels_of("scene=replica", f"scene.options.root={root}", "scene.options.cloud_stride=8")
    assert agreement(ref_pts, ref_lab, pts, lab) >= 0.999 and agreement(pts, lab, ref_pts, ref_lab) >= 0.999
    assert res.scene.frames.names == [f"frame{i:06d}" for i in range(len(seven))]
    assert res.scene.name == "room0" and res.scene.frames.info["depth_scale"] == SCALE
    f = res.scene.frames[1]
    np.testing.assert_allclose(f.T_cw, rigid_inverse(seven[1]["c2w"]), atol=1e-9)
    np.testing.assert_allclose(f.K, seven[1]["K"], atol=1e-12)
    valid = seven[1]["depth"] > 0
    assert np.abs(f.depth[valid] - seven[1]["depth"][valid]).max() < 0.5 / SCALE + 1e-6


@needs_7scenes
def test_camera_file_place_keys_and_labels(tmp_path, seven):
    few = seven[:2]
    root = write_replica(tmp_path, few, camera="root", labels=True)
    s = load_scene(compose("scene=replica", f"scene.options.root={root}",
                           "scene.options.labels='results/semantic{frame:06d}.png'").scene)
    assert [int(np.unique(s.frames[i].gt_labels)[0]) for i in range(2)] == [0, 1]
    assert s.gt_labels is not None and s.frames.info["camera"].endswith("room0/cam_params.json")
    # keys override the file: fx, and the depth scale (the depth doubles)
    s2 = load_scene(compose("scene=replica", f"scene.options.root={root}", "scene.options.fx=400",
                            "scene.options.depth_scale=3276.75").scene)
    assert s2.frames[0].K[0, 0] == 400 and s2.frames[0].K[1, 1] == few[0]["K"][1, 1]
    valid = s2.frames[0].depth > 0
    np.testing.assert_allclose(s2.frames[0].depth[valid], 2 * s.frames[0].depth[valid], rtol=1e-6)
    # no camera file: every value from keys
    (root / "cam_params.json").unlink()
    with pytest.raises(ValueError, match=r"no cam_params\.json in .*room0 or .*Replica: no camera value fx; "
                                         r"set scene\.options\.fx \(NICE-SLAM's Replica: 600\.0\)"):
        load_scene(compose("scene=replica", f"scene.options.root={root}").scene)
    K = few[0]["K"]
    keys = [f"scene.options.{k}={v}" for k, v in dict(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], w=640, h=480,
                                                      depth_scale=SCALE).items()]
    s3 = load_scene(compose("scene=replica", f"scene.options.root={root}", *keys).scene)
    np.testing.assert_allclose(s3.frames[0].K, K)
    with pytest.raises(FileNotFoundError, match=r"Replica camera file .*mine\.json does not exist"):
        load_scene(compose("scene=replica", f"scene.options.root={root}", "scene.options.camera=mine.json").scene)


@pytest.fixture
def tiny(tmp_path):
    """Two 24x32 frames, a camera file in the root: no 7-Scenes needed."""
    root = tmp_path / "Replica" / "office0"
    (root / "results").mkdir(parents=True)
    (root / "cam_params.json").write_text(json.dumps({"camera": {"w": 32, "h": 24, "fx": 30, "fy": 30, "cx": 15.5,
                                                                 "cy": 11.5, "scale": SCALE}}))
    for i in range(2):  # loop over frames
        Image.fromarray(np.full((24, 32, 3), 100, np.uint8)).save(root / "results" / f"frame{i:06d}.jpg")
        Image.fromarray(np.full((24, 32), 9830, np.uint16)).save(root / "results" / f"depth{i:06d}.png")
    eye = " ".join(["1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1"])
    (root / "traj.txt").write_text(f"{eye}\n{eye}\n")
    return root


def test_malformed_replica(tiny):
    s = load_scene(compose("scene=replica", f"scene.options.root={tiny}").scene)
    assert len(s.frames) == 2 and abs(float(np.median(s.frames[0].depth)) - 1.5) < 1e-3
    traj = tiny / "traj.txt"
    good = traj.read_text()
    eye = good.splitlines()[0]
    cases = [
        (f"{eye}\n1 0 0\n", r"traj\.txt: line 2 has 3 values, expected 16 finite numbers"),
        (f"{eye}\n{eye.replace('1', 'x', 1)}\n", r"traj\.txt: line 2 is not 16 numbers"),
        (f"{eye.replace('1', '2', 1)}\n", r"traj\.txt: line 1: pose is not a rigid transform"),
        (f"{eye.replace('0', 'nan', 1)}\n", r"traj\.txt: line 1 has 16 values \(non-finite\)"),
        ("\n\n", r"traj\.txt: no poses"),
    ]
    for text, pattern in cases:  # loop over malformed trajectories
        traj.write_text(text)
        with pytest.raises(ValueError, match=pattern):
            load_scene(compose("scene=replica", f"scene.options.root={tiny}").scene)
    # a pose without a depth image is skipped with a warning; a depth image without colour is an error
    traj.write_text(good + eye + "\n")
    with pytest.warns(UserWarning, match=r"1 of 3 poses of traj\.txt have no depth image"):
        assert len(load_scene(compose("scene=replica", f"scene.options.root={tiny}").scene).frames) == 2
    (tiny / "results" / "frame000001.jpg").unlink()
    with pytest.raises(FileNotFoundError, match=r"frame 1 has depth depth000001\.png but no colour image"):
        load_scene(compose("scene=replica", f"scene.options.root={tiny}").scene)
    (tiny / "cam_params.json").write_text('{"camera": {"w": 32')
    with pytest.raises(ValueError, match=r"cam_params\.json: not valid JSON"):
        load_scene(compose("scene=replica", f"scene.options.root={tiny}").scene)
    with pytest.raises(ValueError, match=r"scene\.options\.color=.*expected a path relative to root with a \{frame\}"):
        compose("scene=replica", f"scene.options.root={tiny}", "scene.options.color=results/rgb.jpg")


def test_bad_trajectory_is_one_cli_line(tiny, tmp_path):
    (tiny / "traj.txt").write_text("1 0 0 0\n")
    r = run_cli("scene=replica", f"scene.options.root={tiny}", "record=off", f"hydra.run.dir={tmp_path / 'out'}")
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("diffuser-lab: error:")]
    assert r.returncode != 0 and len(lines) == 1, r.stderr[-2000:]
    assert "traj.txt: line 1 has 4 values, expected 16 finite numbers" in lines[0] and "Traceback" not in r.stderr
