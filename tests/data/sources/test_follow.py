"""A capture followed as a recorder writes it (``scene.options.follow``; docs/online.md, "Following a live
recorder"): a ROS 2 bag in MCAP storage (diffuser_lab/data/sources/rosbag.py) and a posed RGB-D folder
(rgbd_folder.py) written frame by frame at 30 Hz by another process (tests/recorder.py) while the online
protocol labels them: with ``follow_policy=all`` the labels are the closed capture's run's exactly; with
``newest`` every frame is used or skipped, every keyframe used, and the labels are those of the frames
used. Half-written files and MCAP chunks are waited for; wrong keys stop at start-up with one line."""
from __future__ import annotations

import json
import time

import numpy as np
import pytest
import recorder
from captures import NETWORK
from conftest import compose, run_cli

from diffuser_lab.config import ConfigError
from diffuser_lab.hooks import RunHooks
from diffuser_lab.runs.online import online

N = 45  # frames written (1.5 s at 30 Hz)
DETERMINISTIC = ["protocol=online", "online.map=growing", "online.rate=0", "online.finish=0",
                 "online.compare_batch=false", *NETWORK]
"""The online run whose labels depend on its frames alone (docs/online.md: no idle steps, no finishing pass)."""


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """The demo room's first ``N`` views at 64 x 48, saved for the recorder process."""
    return recorder.save(tmp_path_factory.mktemp("frames") / "frames.npz", recorder.demo_frames(N))


def _bag(path) -> list[str]:
    return ["scene=rosbag", f"scene.options.path={path}", "scene.options.world_frame=world"]


def _folder(root) -> list[str]:
    return ["scene=rgbd_folder", f"scene.options.root={root}", "scene.options.color_suffix=color.png"]


class Watch(RunHooks):
    """Whether the recorder was still writing when each frame was taken; ``delay`` seconds more per frame
    (a map slower than the sensor); ``gate``: the file that lets the recorder go on after frame 0
    (recorder.start), made once this run has taken it."""

    def __init__(self, proc, delay: float = 0.0, gate=None):
        self.proc, self.delay, self.gate, self.writing = proc, delay, gate, []

    def on_frame(self, index, frame):
        self.writing.append(self.proc.poll() is None)
        if self.gate is not None:
            self.gate.touch()
        time.sleep(self.delay)


def _used(res) -> list[int]:
    return [f["index"] for f in res.frames if not f.get("skipped")]


@pytest.mark.slow
def test_a_bag_followed_as_it_is_written_labels_as_the_closed_bag(tmp_path, frames):
    bag = tmp_path / "rec"  # a rosbag2 folder: ends once each MCAP footer and metadata.yaml are written
    # frames 20.. once the run has taken frame 0 (recorder.GATE_AT): a loaded start-up can outlast the 1.5 s
    proc = recorder.start("bag", frames, bag, gate=tmp_path / "go")
    watch = Watch(proc, gate=tmp_path / "go")
    live = online(compose(*_bag(bag), "scene.options.follow=true", "scene.options.follow_policy=all",
                          "scene.options.follow_timeout=10", *DETERMINISTIC), hooks=watch)
    assert proc.wait(10) == 0, proc.stderr.read()
    f = live.scene.frames.info["follow"]
    assert f["ended"] == "closed" and f["frames"] == f["used"] == N and f["skipped_behind"] == f["skipped_bad"] == 0
    assert sum(watch.writing) >= 5  # labelled while the recorder wrote (not all read at its close)
    closed = online(compose(*_bag(bag), *DETERMINISTIC))
    assert _used(live) == _used(closed) == list(range(N))
    np.testing.assert_array_equal(live.points, closed.points)
    np.testing.assert_array_equal(live.labels, closed.labels)
    assert (live.labels >= 0).mean() > 0.5


@pytest.mark.slow
def test_newest_first_skips_a_backlog_keeps_its_keyframes_and_labels_with_the_frames_used(tmp_path, frames):
    from diffuser_lab.data.frames import LazyFrames, keyframes
    from diffuser_lab.data.predictions import with_predictions
    from diffuser_lab.runs.pipeline import load_scene

    mcap = tmp_path / "rec" / "rec.mcap"  # the MCAP file alone: ends once its footer is written
    proc = recorder.start("bag", frames, tmp_path / "rec")
    kf = ["scene.keyframe_translation=1.5"]
    live = online(compose(*_bag(mcap), "scene.options.follow=true", "scene.options.follow_timeout=10", *kf,
                          *DETERMINISTIC), hooks=Watch(proc, delay=0.08))  # 12 frames a second against 30
    assert proc.wait(10) == 0, proc.stderr.read()
    f = live.scene.frames.info["follow"]
    used = _used(live)
    behind = [x["index"] for x in live.frames if x.get("skipped") == "behind"]
    assert f["ended"] == "closed" and f["policy"] == "newest" and f["frames"] == N
    assert f["used"] == len(used) and f["skipped_behind"] == len(behind) > 0 and f["skipped_bad"] == 0
    assert sorted(used + behind) == list(range(N))  # each frame written: used or skipped, once
    cfg = compose(*_bag(mcap), *DETERMINISTIC)
    scene = load_scene(cfg.scene)  # every frame (the keyframe keys of a closed bag would drop the others)
    key = keyframes(scene.frames, 1.5, None)
    assert len(key) < N and set(key) <= set(used)  # a keyframe is taken even from a backlog
    # the same frames in the same order, on the closed bag
    subset = LazyFrames.subset(scene.frames, used)
    closed = online(cfg, scene=scene, predicted=with_predictions(subset, cfg.predictions, scene.taxonomy))
    np.testing.assert_array_equal(live.labels, closed.labels)


@pytest.mark.slow
def test_the_command_line_follows_a_folder_as_it_is_written(tmp_path, frames):
    root = tmp_path / "seq"  # a folder has no end mark: the run ends follow_timeout after the last frame
    proc = recorder.start("folder", frames, root)
    r = run_cli(*_folder(root), "scene.options.follow=true", "scene.options.follow_policy=all",
                "scene.options.follow_timeout=1.5", *DETERMINISTIC, f"hydra.run.dir={tmp_path / 'run'}")
    assert r.returncode == 0, r.stderr
    assert proc.wait(10) == 0, proc.stderr.read()
    assert f"followed as written (all): {N} frames, {N} used, 0 skipped behind" in r.stdout
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert s["follow"]["ended"] == "idle" and s["follow"]["used"] == N and s["n_frames"] == N
    closed = online(compose(*_folder(root), *DETERMINISTIC))
    np.testing.assert_array_equal(np.load(tmp_path / "run" / "labels.npy"), closed.labels)


def test_a_half_written_folder_frame_is_waited_for_and_one_cut_short_is_a_bad_frame(tmp_path, frames, monkeypatch):
    from diffuser_lab.data.sources import rgbd_folder
    from diffuser_lab.runs.pipeline import load_scene

    monkeypatch.setattr(rgbd_folder, "LATE_S", 0.05)
    src = tmp_path / "whole"
    recorder.write_folder({k: v[:5] for k, v in np.load(frames).items()}, src, 1e6)
    root = tmp_path / "seq"
    root.mkdir()
    seq = load_scene(compose(*_folder(root), "scene.options.follow=true").scene).frames
    follow = seq.follow

    def put(name, cut=None):  # a file of the whole folder, or its first `cut` bytes (a recorder writing it)
        data = (src / name).read_bytes()
        (root / name).write_bytes(data if cut is None else data[:cut])

    def frame(i, pose_cut=None, depth_cut=None):
        put(f"frame-{i:06d}.color.png"), put(f"frame-{i:06d}.depth.png", depth_cut)
        put(f"frame-{i:06d}.pose.txt", pose_cut)

    assert not follow.poll() and len(seq) == 0 and "camera-intrinsics.txt does not exist" in follow.waiting
    put("camera-intrinsics.txt")
    frame(0)
    frame(1, pose_cut=40, depth_cut=100)  # half-written: waited for
    follow.poll()
    time.sleep(0.1)
    follow.poll()
    assert seq.names == ["frame-000000"] and len(seq) == 1
    frame(1)
    follow.poll()
    assert seq.names == ["frame-000000", "frame-000001"]
    np.testing.assert_array_equal(seq[1].depth, np.rint(np.load(frames)["depth"][1] * 1000) / 1000)
    frame(2, pose_cut=30)  # cut short: its pose never whole, while frame 3 is
    frame(3)
    follow.poll()
    assert len(seq) == 2  # a later frame is whole: frame 2 gets LATE_S more
    time.sleep(0.1)
    follow.poll()
    assert seq.names[2:] == ["frame-000002", "frame-000003"] and np.isnan(seq.poses[2]).all()
    with pytest.raises(ValueError, match=r"frame-000002\.\*: still incomplete 0.05 s after frame-000003 was whole "
                                         r"\(frame-000002.pose.txt \(.*\)\): cut short$"):
        seq[2]
    assert seq[3].name == "frame-000003" and seq.follow.info["frames_found"] == 4


def test_an_mcap_file_read_while_written_gives_whole_records_only(tmp_path, frames):
    from diffuser_lab.data.sources.rosbag import _McapTail

    bag = tmp_path / "rec"
    recorder.write_bag({k: v[:6] for k, v in np.load(frames).items()}, bag, 1e6)
    whole = (bag / "rec.mcap").read_bytes()
    ref = _McapTail(bag / "rec.mcap")
    want = [(m[0], m[2], bytes(m[3])) for m in ref.read()]
    assert ref.done and len(want) == 6 * 4
    grown, tail, got = tmp_path / "grown.mcap", None, []
    with open(grown, "wb") as fh:
        tail = _McapTail(grown)
        for cut in range(0, len(whole), 1009):  # loop over a file growing by 1 KB: any cut is a half record
            fh.write(whole[fh.tell(): cut])
            fh.flush()
            got += [(m[0], m[2], bytes(tail.raw(m[4]))) for m in tail.read()]
            assert not tail.done and got == want[: len(got)]
        fh.write(whole[fh.tell():])
    got += [(m[0], m[2], bytes(tail.raw(m[4]))) for m in tail.read()]
    assert tail.done and got == want


def test_follow_keys_are_checked_at_start_up(tmp_path):
    from diffuser_lab.data.capture import FollowPolicy
    from diffuser_lab.data.frames import FOLLOW_POLICIES
    from diffuser_lab.runs.resolve import resolve

    assert [p.value for p in FollowPolicy] == list(FOLLOW_POLICIES)  # the key's choices are the loop's

    def bad(*over, match):
        with pytest.raises(ConfigError, match=match):
            resolve(compose(*over))

    root = ["scene=rgbd_folder", f"scene.options.root={tmp_path}"]
    bad(*root, "scene.options.follow=true", match=r"^scene.options.follow=true: a capture is followed in "
                                                   r"protocol=online, not protocol=global_3d$")
    bad(*root, "scene.options.follow=true", "protocol=online", match=r"online.map=given: expected scene.options.cloud")
    bad(*root, "scene.options.follow_timeout=0", match=r"^scene.options.follow_timeout=0.0: expected > 0 seconds$")
    bad(*_bag(tmp_path / "rec.db3"), "scene.options.follow=true", "protocol=online", "online.map=growing",
        match=r"^scene.options.path='.*rec.db3': expected a rosbag2 folder of .mcap files")
    with pytest.raises(Exception, match="follow_policy"):
        compose(*root, "scene.options.follow_policy=oldest")
    r = run_cli(*root, "scene.options.follow=true", "protocol=single_frame", "record=off")
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        "diffuser-lab: error: scene.options.follow=true: a capture is followed in protocol=online, not "
        "protocol=single_frame"]
