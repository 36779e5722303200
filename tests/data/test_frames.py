"""The one lazy frame sequence and the one frame loop (diffuser_lab/data/frames.py, issue 52): the loop's
read-ahead hands out the frames of one thread, in order, bounded; parts a loop does not read are not read;
keyframes are picked from the poses alone; a ScanNet export read ahead gives the run of one thread."""
from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from diffuser_lab.data.frames import FrameLoop, LazyFrames, keyframes, poses_of, read_ahead, without
from diffuser_lab.data.render import look_at
from diffuser_lab.data.scene import Frame


class Source:
    """A sequence whose frame i is a seeded function of i alone, read slowly (sleeps release the GIL),
    counting the reads under way (the bound) and the threads that made them."""

    def __init__(self, n: int, bad: tuple = (), delay: float = 0.002):
        self.n, self.bad, self.delay = n, set(bad), delay
        self.lock = threading.Lock()
        self.busy = self.most = 0
        self.threads: set[str] = set()
        self.reads: list[int] = []

    def load(self, i: int, skip: frozenset = frozenset()) -> Frame:
        with self.lock:
            self.busy += 1
            self.most = max(self.most, self.busy)
            self.threads.add(threading.current_thread().name)
            self.reads.append(i)
        try:
            time.sleep(self.delay * (1 + i % 3))  # out of order: later frames may finish first
            if i in self.bad:
                raise ValueError(f"frame {i}.png: damaged")
            rng = np.random.default_rng([7, i])
            return Frame(name=str(i), K=np.eye(3), T_cw=np.eye(4), depth=rng.random((4, 5), dtype=np.float32),
                         rgb=None if "rgb" in skip else rng.integers(0, 255, (4, 5, 3), dtype=np.uint8))
        finally:
            with self.lock:
                self.busy -= 1

    def frames(self) -> LazyFrames:
        return LazyFrames([str(i) for i in range(self.n)], self.load, parts=("rgb",))


def _played(loop: FrameLoop, window: bool = False) -> list:
    out = []
    for i, f in loop:  # loop over the targets
        out.append((i, f.depth.copy(), None if f.rgb is None else f.rgb.copy()))
        if window:
            out.append([g.name for g in loop.window_frames(i)])
    return out


def _same(a: list, b: list) -> bool:
    if len(a) != len(b):
        return False
    for x, y in zip(a, b):  # loop over what two loops handed out
        if isinstance(x, list):
            if x != y:
                return False
        elif x[0] != y[0] or not np.array_equal(x[1], y[1]) or not np.array_equal(x[2], y[2]):
            return False
    return True


def test_read_ahead_gives_the_frames_of_one_thread_in_order_and_bounded():
    one = _played(FrameLoop(Source(40).frames(), "one", read_ahead=0))
    src = Source(40)
    ahead = _played(FrameLoop(src.frames(), "ahead", read_ahead=6))
    assert _same(one, ahead) and [x[0] for x in ahead] == list(range(40))
    assert src.most <= 6 and len(src.threads) >= 2 and sorted(src.reads) == list(range(40))  # each read once
    # the run's setting (scene.read_ahead) reaches a loop that does not say
    with read_ahead(0):
        src = Source(10)
        _played(FrameLoop(src.frames(), "setting"))
        assert src.threads == {threading.current_thread().name}
    assert FrameLoop([Frame("a", np.eye(3), np.eye(4), np.zeros((2, 2), np.float32))], "a list").read_ahead == 0


def test_read_ahead_with_windows_and_targets_left_without_them():
    """The single-frame protocol's pattern: every 3rd target with a window of 5; targets whose window the
    caller does not read (it skipped them) leave no stale read behind."""
    targets = list(range(0, 30, 3))
    one = _played(FrameLoop(Source(30).frames(), "one", targets=targets, window=5, read_ahead=0), window=True)
    src = Source(30)
    ahead = _played(FrameLoop(src.frames(), "ahead", targets=targets, window=5, read_ahead=4), window=True)
    assert _same(one, ahead) and src.most <= 4
    src = Source(30)
    loop = FrameLoop(src.frames(), "some windows", targets=targets, window=5, read_ahead=4)
    seen = []
    for i, f in loop:  # every other target reads its window
        seen.append([g.name for g in loop.window_frames(i)] if i % 2 == 0 else f.name)
        assert len(loop._pending) <= 4
    assert seen == [[str(j) for j in loop.window_of(i)] if i % 2 == 0 else str(i) for i in targets]


def test_a_bad_frame_stops_or_is_skipped_where_one_thread_does():
    for ahead in (0, 5):  # each setting the same
        with pytest.raises(ValueError, match="frame 7.png: damaged"):
            for _ in FrameLoop(Source(20, bad=(7, 12)).frames(), "stop", read_ahead=ahead):
                pass
        skipped = []
        with pytest.warns(UserWarning, match="frame 7 skipped: frame 7.png: damaged"):
            got = [i for i, _ in FrameLoop(Source(20, bad=(7, 12)).frames(), "skip", skip_bad=True, read_ahead=ahead,
                                           on_skip=lambda i, msg: skipped.append(i))]
        assert skipped == [7, 12] and got == [i for i in range(20) if i not in (7, 12)]
    # a loop left early gives its threads back
    src = Source(50)
    for i, _ in FrameLoop(src.frames(), "early", read_ahead=8):
        if i == 3:
            break
    assert src.busy == 0 and len(src.reads) < 20


def test_without_a_part_it_is_not_read_and_what_follows_the_frames_keeps():
    src = Source(12)
    frames = src.frames()
    poses = [look_at((0.1 * i, 0, 1), (0.1 * i, 3, 1)) for i in range(12)]
    frames.poses = poses
    mapped = LazyFrames.mapped(frames, lambda i, f: Frame(f.name + "p", f.K, f.T_cw, f.depth + i, rgb=f.rgb))
    sub = LazyFrames.subset(mapped, [1, 4, 9])
    lean = without(sub, "rgb")
    assert [f.rgb is None for f in lean] == [True] * 3 and [f.name for f in lean] == ["1p", "4p", "9p"]
    assert all(np.array_equal(a.depth, b.depth) for a, b in zip(lean, sub))
    assert lean.source_index == [1, 4, 9] and [p is poses[k] for p, k in zip(poses_of(lean), (1, 4, 9))] == [True] * 3
    assert without(sub[1:], "rgb")[0].name == "4p" and sub[1:][0].rgb is not None
    # a source that cannot leave it out: dropped after the read
    plain = LazyFrames(3, lambda i: src.load(i))
    assert plain.without("rgb")[0].rgb is None and plain[0].rgb is not None
    with pytest.raises(ValueError, match="expected some of rgb"):
        plain.without("depth")


def test_keyframes_keep_a_frame_when_the_camera_moved_or_turned_enough():
    # a camera walking 1 cm and panning 1 degree a frame, then standing still, then turning in place
    poses = []
    for k in range(100):  # loop over 100 poses
        walk, turn = min(k, 40) * 0.01, np.deg2rad(min(k, 40) + max(k - 70, 0) * 2.0)
        eye = np.array([walk, 0.0, 1.0])
        poses.append(look_at(eye, eye + [np.sin(turn), np.cos(turn), 0.0]))
    frames = [Frame(str(k), np.eye(3), T, np.zeros((2, 2), np.float32)) for k, T in enumerate(poses)]
    assert keyframes(frames, None, None) == list(range(100))
    kept = keyframes(frames, 0.1, None)  # by translation alone: every 10th while walking, nothing after
    assert kept == [0, 10, 20, 30, 40]
    kept = keyframes(frames, None, 10.0)  # by rotation: every 10 degrees, then every 5th frame turning 2 a frame
    assert kept[:5] == [0, 10, 20, 30, 40] and kept[5:] == [75, 80, 85, 90, 95]
    assert keyframes(frames, 0.1, 10.0) == kept  # either criterion
    # no poses up front: read through the loop (the same answer)
    lazy = LazyFrames(100, lambda i: frames[i])
    assert poses_of(lazy) is None and keyframes(lazy, None, 10.0) == kept


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    """A ScanNet export of 24 frames at sensor rate (the demo room, 7 views swept back and forth; the
    generator tests/benchmarks/test_frame_rate.py uses at 1,000 and 5,000 frames)."""
    from datasets import write_scannet_sequence

    return write_scannet_sequence(tmp_path_factory.mktemp("seq"), 24, n_views=7)


def _run(export: Path, *over: str):
    from conftest import compose

    from diffuser_lab.runs.pipeline import run
    from diffuser_lab.runs.report import summary
    from diffuser_lab.runs.resolve import resolve

    cfg = resolve(compose("scene=scannet", f"scene.options.root={export}", "scene.options.frame_step=1",
                          "predictions=files", f"predictions.folder={export.parent / 'predictions'}", "record=off",
                          "solver.max_iter=30", "output.labels_ply=false", *over))
    res = run(cfg)
    return res, json.loads(json.dumps(summary(res, cfg)))


@pytest.mark.slow
def test_a_scannet_export_read_ahead_is_the_run_of_one_thread_and_keyframes_thin_it(export):
    (one, s1), (ahead, s2) = _run(export, "scene.read_ahead=0"), _run(export, "scene.read_ahead=4")
    assert np.array_equal(one.labels, ahead.labels) and s1["metrics"] == s2["metrics"]
    assert np.array_equal(one.evidence.mass, ahead.evidence.mass) and s1["predictions_stats"] == s2["predictions_stats"]
    assert s2["predictions_stats"]["label_files"] == 24 and all(f.rgb is None for f in ahead.frames)  # colour unread
    assert "keyframes" not in s1
    kf, s = _run(export, "scene.keyframe_translation=0.3", "scene.keyframe_rotation_deg=40")
    info = s["keyframes"]
    # the keyframe rule (checked by hand above) on the export's own poses (pose/<i>.txt: camera to world):
    # 0.17 m and 17 degrees a frame: every second frame, 12 of 24 (measured 2026-12-07)
    T_cw = [np.linalg.inv(np.loadtxt(export / "pose" / f"{i}.txt")) for i in range(24)]
    want = keyframes([Frame(str(i), np.eye(3), T, np.zeros((2, 2), np.float32)) for i, T in enumerate(T_cw)], 0.3, 40.0)
    assert info["kept_frames"] == [str(i) for i in want] and info["kept"] == len(want) == 12 and info["of"] == 24
    assert s["n_frames"] == info["kept"]
    assert info["kept_frames"][0] == "0" and info["translation_m"] == 0.3 and info["rotation_deg"] == 40
    # each kept frame keeps its own predictions: the same evidence as the run over those frames alone
    assert kf.predictions_stats["label_files"] == info["kept"]


# ------------------------------------------------------------------ a capture followed as it is written


def _followed(bursts: list, policy: str, translation=None, timeout: float = 5.0):
    """A :class:`Follow` whose k-th poll makes the frames of ``bursts[k]`` complete (closed after the last
    burst); frame j's camera stands at x = ``xs[j]`` (metres) so a keyframe rule can mark it."""
    from diffuser_lab.data.frames import Follow, KeyframeRule

    xs = [0.0, 0.1, 0.6, 0.7, 0.8, 1.2, 1.3, 1.9, 2.0]
    polls = iter(bursts)

    def poll() -> bool:
        burst = next(polls, None)
        for j in burst or []:  # loop over the frames this poll finds complete
            T = np.eye(4)
            T[0, 3] = -xs[j]
            follow.add(f"frame-{j:06d}", T, j)
        return burst is None

    follow = Follow(poll, "test capture", timeout=timeout, policy=policy)
    follow.rule = KeyframeRule(translation, None)
    src = Source(len(xs))
    return follow, LazyFrames(0, lambda i, skip: src.load(follow.items[i], skip), follow=follow, parts=("rgb",))


def test_a_followed_capture_is_taken_newest_first_keeping_keyframes_or_every_frame_in_order():
    bursts = [[0], [1, 2, 3, 4], [5], [], [6, 7, 8]]  # frames as the polls find them complete
    follow, frames = _followed(bursts, "newest", translation=0.5)  # keyframes: 0, 2, 5, 7 (x moved >= 0.5 m)
    skipped = []
    loop = FrameLoop(LazyFrames.mapped(frames, lambda i, f: f), "follow",  # a derived sequence follows too
                     on_skip=lambda i, why: skipped.append((i, why)))
    taken = [(i, f.name) for i, f in loop]
    # the newest waiting frame first, then the waiting keyframes; the other waiting frames skipped as behind
    assert [i for i, _ in taken] == [0, 4, 2, 5, 8, 7] and skipped == [(1, "behind"), (3, "behind"), (6, "behind")]
    assert all(name == str(i) for i, name in taken) and frames.names[4] == "frame-000004"  # each index is its frame
    assert {k: follow.info[k] for k in ("frames", "used", "skipped_behind", "skipped_bad", "keyframes_from_backlog",
                                        "ended")} == {"frames": 9, "used": 6, "skipped_behind": 3, "skipped_bad": 0,
                                                      "keyframes_from_backlog": 2, "ended": "closed"}
    # ended: a fixed sequence of the frames found, read as any other (no policy: every frame)
    assert len(frames) == 9 and [i for i, _ in FrameLoop(frames, "again")] == list(range(9))

    follow, frames = _followed(bursts, "all")
    assert [i for i, _ in FrameLoop(frames, "follow")] == list(range(9)) and follow.info["skipped_behind"] == 0
    follow, frames = _followed(bursts, "newest")  # no keyframe rule: a backlog is skipped whole
    assert [i for i, _ in FrameLoop(frames, "follow")] == [0, 4, 5, 8]


def test_a_followed_capture_ends_when_no_frame_comes_and_says_what_it_waited_for():
    follow, frames = _followed([[0, 1]] + [[]] * 10_000, "all", timeout=0.2)
    t0 = time.monotonic()
    assert [i for i, _ in FrameLoop(frames, "follow")] == [0, 1]
    assert follow.ended == "idle" and 0.2 <= time.monotonic() - t0 < 2.0
    follow, frames = _followed([[]] * 10_000, "all", timeout=0.1)
    follow.waiting = "test capture/frame-XXXXXX.depth.png"
    with pytest.raises(ValueError, match=r"^test capture: no complete frame within scene.options.follow_timeout=0.1 s "
                                         r"\(waiting for test capture/frame-XXXXXX.depth.png\)$"):
        list(FrameLoop(frames, "follow"))
