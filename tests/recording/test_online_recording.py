"""Records of online runs (protocol=online): run.rrd on a frame timeline, run.mcap per frame, both
recorders (thread, process), inspection, a killed run."""
import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import ROOT, run_cli

from diffuser_lab.cli.inspect import main as inspect_main
from diffuser_lab.config import default_config
from diffuser_lab.hooks import RunHooks
from diffuser_lab.recording import make_hooks
from diffuser_lab.recording.mcap_read import read_run
from diffuser_lab.recording.online import FrameSchedule
from diffuser_lab.recording.rerun_log import class_ids
from diffuser_lab.runs.online import online

SMALL = {"protocol.name": "online", "scene.options.n_views": 6, "scene.options.image_width": 64,
         "scene.options.image_height": 48, "online.compare_batch": False, "online.rate": 0.0, "online.finish": 0}
# per-frame records compared bit for bit between runs: no idle steps (they follow the wall clock), no finishing pass
SMALL_CLI = ["protocol=online", "scene.options.n_views=6", "scene.options.image_width=64", "scene.options.image_height=48",
             "online.compare_batch=false", "online.rate=0", "online.finish=0"]
TIMING = {"latency_ms", "map_ms", "graph_ms", "evidence_ms", "steps_ms", "idle_ms", "sweep_residual", "error_bound"}
RERUN = str(Path(sys.executable).with_name("rerun"))
HAS_GROWING = importlib.util.find_spec("diffuser_lab.method.growing") is not None


class Capture(RunHooks):
    """Keeps each frame's labels and, at the last frame, the exact Z (``update.scores()``)."""

    def __init__(self, inner):
        self.inner, self.labels, self.index, self.Z = inner, {}, [], None

    def on_scene(self, scene):
        self.inner.on_scene(scene)

    def on_frame(self, index, frame):
        self.inner.on_frame(index, frame)

    def on_result(self, result):
        self.inner.on_result(result)

    # the finishing pass (online.finish), a diffusion the hooks observe
    def statistics(self):
        return self.inner.statistics()

    def on_statistics(self, table):
        self.inner.on_statistics(table)

    def wants(self, it):
        return self.inner.wants(it)

    def observe(self, it, Z, stats):
        self.inner.observe(it, Z, stats)

    def on_online_frame(self, frame, update):
        self.labels[update.index] = np.array(update.labels)
        self.index.append(update.index)
        self.Z = np.array(update.scores())
        self.inner.on_online_frame(frame, update)


def recorded_online(cfg, run_dir, process=False):
    hooks = make_hooks(cfg, run_dir, process=process)
    cap = Capture(hooks)
    try:
        res = online(cfg, hooks=cap)
    finally:
        hooks.close()
    return res, hooks, cap


def rrd_rows(path, entity, component):
    """{frame: list of values} of ``component`` of ``entity`` on the frame timeline."""
    from rerun.chunk import RrdReader

    out = {}
    for ch in RrdReader(path).stream():
        if ch.entity_path == entity and not ch.is_static:
            rb = ch.to_record_batch()
            if component not in rb.schema.names:
                continue
            for f, v in zip(rb.column("frame").to_pylist(), rb.column(component).to_pylist()):
                if v is not None:
                    out[f] = v
    return out


def rrd_blocks(path, kind, component):
    """{block entity: {frame: values}} of world/online/<kind>/<block> (rerun_log.ONLINE_BLOCK_ROWS)."""
    from rerun.chunk import RrdReader

    prefix = f"/world/online/{kind}/"
    paths = {ch.entity_path for ch in RrdReader(path).stream() if ch.entity_path.startswith(prefix)}
    return {p: rrd_rows(path, p, component) for p in sorted(paths)}


def map_at(blocks, frame):
    """The map's values at ``frame``: each block's latest entry at or before it, concatenated."""
    parts = [np.asarray(b[max(f for f in b if f <= frame)]) for b in blocks.values() if any(f <= frame for f in b)]
    return np.concatenate(parts) if parts else np.zeros(0)


def plain(frames):
    return [{k: v for k, v in f.items() if k not in TIMING} for f in frames]


@pytest.fixture(scope="module")
def thread_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("online_thread")
    cfg = default_config(**SMALL)
    res, hooks, cap = recorded_online(cfg, d)
    return SimpleNamespace(dir=d, res=res, hooks=hooks, cap=cap, cfg=cfg)


@pytest.fixture(scope="module")
def cli_runs(tmp_path_factory):
    base = tmp_path_factory.mktemp("online_cli")
    out = {}
    for mode, extra in (("both", []), ("off", []), ("rerun", ["online.rate=20"])):  # rerun: a frame budget of 50 ms
        d = base / mode
        p = run_cli(*SMALL_CLI, f"record={mode}", "output.quiet=true", f"hydra.run.dir={d}", *extra)
        assert p.returncode == 0, p.stderr
        out[mode] = d
    return out


@pytest.mark.slow
def test_mcap_one_message_per_frame_and_the_scheduled_states(thread_run):
    res, cap = thread_run.res, thread_run.cap
    n = len(res.frames)
    assert thread_run.hooks.files() == {"rrd": "run.rrd", "mcap": "run.mcap"}
    log = read_run(thread_run.dir / "run.mcap", z="all")
    assert log.complete and not log.truncated and log.online["map"] == "given"
    assert [f["index"] for f in log.frames] == cap.index == list(range(n))
    assert [f["count"] for f in log.frames] == list(range(1, n + 1))
    # everything of FrameStats and the metrics so far, as the run's own per-frame figures
    for got, want in zip(log.frames, res.frames):
        for k, v in want.items():
            assert got[k] == (pytest.approx(v) if isinstance(v, float) else v), k
    sched = FrameSchedule(None, "decades", n)
    kept = [i for i in range(n) if sched.next(i)[1]]
    assert log.z_iterations == kept == [0, 1, 4, 5] == thread_run.hooks.recorded
    assert log.z_dtype == {0: "q8", 1: "q8", 4: "q8", 5: "float32"}
    assert [f["state"] for f in log.frames] == ["q8", "q8", "", "", "q8", "float32"]
    np.testing.assert_array_equal(log.z[5], cap.Z)  # bit-equal to OnlineDiffuser.scores() after the last frame
    for i in kept[:-1]:  # q8 states: within 0.5/255 of each row's sum
        Z = log.z[i]
        assert Z.shape == cap.Z.shape and (Z.sum(1) > 0).any()
    assert log.summary["recorded_frames"] == kept and log.summary["protocol"] == "online"


@pytest.mark.slow
def test_mcap_map_cloud_and_cameras(thread_run):
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

    from diffuser_lab.recording.mcap_encode import TOPIC_ONLINE_LABELS, TOPIC_TF, decode_point_cloud
    from diffuser_lab.recording.mcap_read import RunLog, iter_run

    clouds, tfs = [], []
    for topic, data in iter_run(thread_run.dir / "run.mcap", RunLog(path=thread_run.dir)):
        if topic == TOPIC_ONLINE_LABELS:
            clouds.append(decode_point_cloud(PointCloud.FromString(data)))
        elif topic == TOPIC_TF:
            tfs.append(FrameTransform.FromString(data))
    assert len(tfs) == len(thread_run.res.frames)  # a camera per frame
    assert len(clouds) == 1  # record.clouds=decades: the last frame's only (6 frames)
    np.testing.assert_array_equal(clouds[0]["label"], thread_run.res.labels)
    pts = np.stack([clouds[0]["x"], clouds[0]["y"], clouds[0]["z"]], 1)
    np.testing.assert_array_equal(pts, thread_run.res.points)


@pytest.mark.slow
def test_rrd_frame_timeline_one_entry_per_frame(thread_run):
    path = thread_run.dir / "run.rrd"
    cap = thread_run.cap
    blocks = rrd_blocks(path, "labels", "Points3D:class_ids")
    assert list(blocks) == ["/world/online/labels/0000"]  # a given map: one block
    ids = blocks["/world/online/labels/0000"]
    assert sorted(ids) == cap.index
    for i in cap.index:
        np.testing.assert_array_equal(ids[i], class_ids(cap.labels[i]))
    pos = rrd_rows(path, "/world/online/labels/0000", "Points3D:positions")
    assert sorted(pos) == [0]  # a given map: positions once, class ids every frame
    np.testing.assert_array_equal(np.asarray(pos[0], np.float32), thread_run.res.points)
    bay = rrd_rows(path, "/world/online/bayesian/0000", "Points3D:class_ids")
    assert sorted(bay) == cap.index
    np.testing.assert_array_equal(bay[cap.index[-1]], class_ids(thread_run.res.bayesian_labels))
    assert sorted(rrd_rows(path, "/world/online/camera", "Transform3D:translation")) == cap.index
    assert sorted(rrd_rows(path, "/world/online/camera/labels", "SegmentationImage:buffer")) == cap.index
    miou = rrd_rows(path, "/metrics/diffuser_miou", "Scalars:scalars")
    assert sorted(miou) == cap.index
    assert miou[cap.index[-1]][0] == pytest.approx(thread_run.res.frames[-1]["diffuser_miou"])
    for e in ("/metrics/bayesian_miou", "/metrics/latency_ms", "/metrics/points_k", "/metrics/changed"):
        assert sorted(rrd_rows(path, e, "Scalars:scalars")) == cap.index, e
    from rerun.chunk import RrdReader

    assert RrdReader(path).blueprints()
    p = subprocess.run([RERUN, "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr


@pytest.mark.slow
def test_process_and_thread_recorders_give_the_same_frames(thread_run, cli_runs):
    a = read_run(thread_run.dir / "run.mcap", z="all")
    b = read_run(cli_runs["both"] / "run.mcap", z="all")
    assert b.complete and len(b.frames) == len(a.frames) > 0
    assert plain(b.frames) == plain(a.frames)
    assert b.z_iterations == a.z_iterations
    np.testing.assert_array_equal(b.z[b.z_iterations[-1]], a.z[a.z_iterations[-1]])
    s = json.loads((cli_runs["both"] / "summary.json").read_text())
    assert s["records"] == {"rrd": "run.rrd", "mcap": "run.mcap"}
    ids = rrd_rows(cli_runs["both"] / "run.rrd", "/world/online/labels/0000", "Points3D:class_ids")
    assert sorted(ids) == [f["index"] for f in b.frames]


@pytest.mark.slow
def test_process_recorder_in_a_library_call(thread_run, tmp_path):
    from diffuser_lab.recording import process

    if not process.available():
        pytest.skip("no fork")
    res, hooks, cap = recorded_online(thread_run.cfg, tmp_path, process=True)
    assert isinstance(hooks.lane, process.ProcessLane) and hooks.files() == {"rrd": "run.rrd", "mcap": "run.mcap"}
    log = read_run(tmp_path / "run.mcap", z="last")
    np.testing.assert_array_equal(log.z[log.z_iterations[-1]], cap.Z)
    assert hooks.recorded == log.z_iterations


@pytest.mark.slow
def test_record_off_gives_the_same_labels(cli_runs):
    off, both = cli_runs["off"], cli_runs["both"]
    assert not (off / "run.rrd").exists() and not (off / "run.mcap").exists()
    np.testing.assert_array_equal(np.load(off / "labels.npy"), np.load(both / "labels.npy"))


@pytest.mark.slow
def test_inspect_online_summary_at_and_to_rrd(cli_runs, tmp_path, capsys):
    d = cli_runs["both"]
    assert inspect_main([str(d)]) == 0
    out = capsys.readouterr().out
    assert "online, given map" in out and "6 of 6 frames" in out and "latency   median" in out
    assert "states    4 kept: frames 0, 1, 4, 5" in out and "final mIoU" in out
    s = json.loads((d / "summary.json").read_text())
    assert f"final mIoU {s['metrics']['miou']:.1f}" in out
    assert inspect_main([str(d), "--at", "last", "--out", str(tmp_path / "z.npy")]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "z.npy"), read_run(d / "run.mcap", z="last").z[5])
    capsys.readouterr()
    assert inspect_main([str(d), "--at", "2"]) == 2
    assert "frame 2 was not recorded" in capsys.readouterr().err
    assert inspect_main([str(d), "--to-rrd", str(tmp_path / "x.rrd")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "online run" in err[0] and "run.rrd" in err[0]
    assert not (tmp_path / "x.rrd").exists()
    assert inspect_main([str(d), "--foxglove-layout", str(tmp_path / "layout.json")]) == 0
    layout = (tmp_path / "layout.json").read_text()
    json.loads(layout)
    assert "/online/labels" in layout and "/diffuser_lab/online/frame.diffuser_miou" in layout
    assert "/diffuser_lab/metrics" not in layout and "/diffusion/labels" not in layout


class _Frame(SimpleNamespace):
    pass


def test_growing_map_records_synthetic(tmp_path, monkeypatch):
    """The recorders on a growing map, driven by hand (no growing map implementation needed):
    positions re-logged on the frames that add points only, Z states as the map grows, ground
    truth of the map, the last state exact."""
    from diffuser_lab.data.taxonomy import resolve_taxonomy
    from diffuser_lab.runs.online import OnlineResult, OnlineUpdate
    from diffuser_lab.method.online import FrameStats

    from diffuser_lab.recording import rerun_log

    monkeypatch.setattr(rerun_log, "ONLINE_BLOCK_ROWS", 64)  # 150 points: blocks of 64, 64, 22
    cfg = default_config(**{**SMALL, "online.map": "growing", "record.interval": 2})
    tax = resolve_taxonomy(cfg)
    rng = np.random.default_rng(0)
    sizes = [0, 40, 40, 90, 150]  # map points after each frame: the first adds none, the third none
    all_pts = rng.random((150, 3)).astype(np.float32)
    all_gt = rng.integers(-1, tax.num_classes, 150).astype(np.int16)
    scene = SimpleNamespace(name="synthetic", n_points=150, points=all_pts, colors=None, gt_labels=all_gt,
                            taxonomy=tax, frames=[None] * len(sizes))
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    hooks = make_hooks(cfg, tmp_path)
    hooks.on_scene(scene)
    Zs, labels = {}, {}
    for i, n in enumerate(sizes):
        Z = rng.random((n, tax.num_classes)).astype(np.float32)
        lab = np.argmax(Z, 1).astype(np.int16) if n else np.zeros(0, np.int16)
        Zs[i], labels[i] = Z, lab
        st = FrameStats(index=i, name=f"f{i}", latency_ms=1.0 + i, points=n,
                        new_points=n - (sizes[i - 1] if i else 0), changed=i)
        T = np.eye(4)
        T[0, 3] = 0.1 * i
        frame = _Frame(name=f"f{i}", shape=(48, 64), labels=rng.integers(0, 5, (48, 64)).astype(np.int16),
                       probs=None, K=K, T_cw=T)
        upd = OnlineUpdate(index=i, stats=st, points=all_pts[:n], labels=lab, bayesian=lab, gt=all_gt[:n],
                           metrics={"diffuser_miou": 10.0 * i, "bayesian_miou": 5.0 * i}, scores=lambda Z=Z: Z.copy())
        hooks.on_frame(i, frame)
        hooks.on_online_frame(frame, upd)
    res = OnlineResult(scene=scene, mode="growing", points=all_pts, labels=labels[4], bayesian_labels=labels[4],
                       gt=all_gt, frames=[], metrics=None, bayesian=None)
    hooks.on_result(res)
    hooks.close()
    assert hooks.files() == {"rrd": "run.rrd", "mcap": "run.mcap"}
    log = read_run(tmp_path / "run.mcap", z="all")
    assert [f["index"] for f in log.frames] == [0, 1, 2, 3, 4] and [f["points"] for f in log.frames] == sizes
    assert log.z_iterations == [0, 1, 3, 4]  # counts 1, 2, 4 (every 2nd) and the last
    assert [log.z[i].shape[0] for i in log.z_iterations] == [0, 40, 90, 150]
    np.testing.assert_array_equal(log.z[4], Zs[4])
    path = tmp_path / "run.rrd"
    pos = rrd_blocks(path, "labels", "Points3D:positions")
    # each block's positions again only on the frames that added rows to it
    assert {p: sorted(v) for p, v in pos.items()} == {"/world/online/labels/0000": [1, 3],
                                                      "/world/online/labels/0001": [3, 4],
                                                      "/world/online/labels/0002": [4]}
    for f, n in enumerate(sizes):
        np.testing.assert_array_equal(np.asarray(map_at(pos, f), np.float32).reshape(-1, 3), all_pts[:n])
    ids = rrd_blocks(path, "labels", "Points3D:class_ids")
    assert sorted(ids["/world/online/labels/0000"]) == [1, 2, 3, 4]  # frame 0: an empty map
    for f in range(1, 5):
        np.testing.assert_array_equal(map_at(ids, f), class_ids(labels[f]))
    gt = rrd_blocks(path, "ground_truth", "Points3D:class_ids")
    np.testing.assert_array_equal(map_at(gt, 4), class_ids(all_gt))
    wrong = rrd_rows(path, "/world/online/wrong", "Points3D:positions")
    want = all_pts[(labels[4] != all_gt) & (all_gt >= 0) & (labels[4] >= 0)]
    assert 0 < len(want) < 150
    np.testing.assert_array_equal(np.asarray(wrong[4], np.float32), want)
    cam = rrd_rows(path, "/world/online/camera", "Transform3D:translation")
    assert cam[3][0][0] == pytest.approx(-0.3)  # T_wc = inv(T_cw): the camera moves


def test_last_frame_skipped_keeps_the_last_taken_frames_state_exact(tmp_path):
    """Frames after the last one taken were skipped: its Z is written again, exact, at the end."""
    from diffuser_lab.data.taxonomy import resolve_taxonomy
    from diffuser_lab.method.online import FrameStats
    from diffuser_lab.runs.online import OnlineResult, OnlineUpdate

    cfg = default_config(**SMALL)
    tax = resolve_taxonomy(cfg)
    pts = np.random.default_rng(1).random((30, 3)).astype(np.float32)
    scene = SimpleNamespace(name="s", n_points=30, points=pts, colors=None, gt_labels=None, taxonomy=tax,
                            frames=[None] * 4)
    hooks = make_hooks(cfg, tmp_path)
    hooks.on_scene(scene)
    Z = np.random.default_rng(2).random((30, tax.num_classes)).astype(np.float32)
    lab = np.argmax(Z, 1).astype(np.int16)
    for i in range(3):  # frame 3 (the last) skipped: no hook call for it
        frame = _Frame(name=str(i), shape=(48, 64), labels=None, probs=np.random.default_rng(i).random((48, 64, 4)),
                       K=np.eye(3), T_cw=np.eye(4))
        hooks.on_online_frame(frame, OnlineUpdate(index=i, stats=FrameStats(index=i, name=str(i), points=30), points=pts,
                                                  labels=lab, bayesian=lab, gt=None, metrics={},
                                                  scores=lambda: Z.copy()))
    hooks.on_result(OnlineResult(scene=scene, mode="given", points=pts, labels=lab, bayesian_labels=lab, gt=None,
                                 frames=[], metrics=None, bayesian=None))
    hooks.close()
    log = read_run(tmp_path / "run.mcap", z="all")
    assert log.z_iterations == [0, 1, 2] and log.z_dtype[2] == "float32"
    np.testing.assert_array_equal(log.z[2], Z)
    assert log.frames[0]["diffuser_miou"] is None  # no ground truth: NaN -> None


@pytest.mark.slow
def test_the_finishing_pass_is_recorded_as_the_runs_end(tmp_path):
    """online.finish moves Z after the last frame: run.mcap ends with that state, exact, and its cloud."""
    from diffuser_lab.method.diffusion import labels_from_scores

    cfg = default_config(**{**SMALL, "online.finish": 5000})
    res, hooks, cap = recorded_online(cfg, tmp_path)
    fin = res.settings["finish"]
    assert fin["steps"] > 0, fin
    log = read_run(tmp_path / "run.mcap", z="all")
    last = log.z_iterations[-1]
    assert last == cap.index[-1] and log.z_dtype[last] == "float32"
    assert not np.array_equal(log.z[last], cap.Z)  # not the last frame's state: the finished one
    np.testing.assert_array_equal(labels_from_scores(log.z[last]), res.labels)
    # run.rrd (issue 50 item 4): the pass's steps on the frame timeline after the last frame, its
    # scalars at every step, the map's labels on its 1-2-5 steps and, at its last step, labels.npy's
    rrd, steps = tmp_path / "run.rrd", fin["steps"]
    after = [last + s for s in range(1, steps + 1)]
    res_log = rrd_rows(rrd, "/metrics/finish_residual_log10", "Scalars:scalars")
    assert sorted(res_log) == after
    assert res_log[after[-1]][0] == pytest.approx(np.log10(fin["residual"]), rel=1e-6)
    miou = rrd_rows(rrd, "/metrics/diffuser_miou", "Scalars:scalars")
    assert sorted(miou)[-steps:] == after and miou[after[-1]][0] == pytest.approx(res.metrics["miou"], abs=1e-9)
    changed = rrd_rows(rrd, "/metrics/changed", "Scalars:scalars")
    assert sum(changed[t][0] for t in after) >= fin["changed"]  # per step; some may change back
    ids = rrd_rows(rrd, "/world/online/labels/0000", "Points3D:class_ids")
    assert [t for t in sorted(ids) if t > last] == [last + s for s in (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000,
                                                                     2000) if s < steps] + [after[-1]]
    np.testing.assert_array_equal(ids[after[-1]], class_ids(res.labels))


@pytest.mark.slow
@pytest.mark.skipif(not HAS_GROWING, reason="diffuser_lab.method.growing is not there yet")
def test_growing_map_cli(tmp_path):
    d = tmp_path / "grow"
    p = run_cli(*SMALL_CLI, "online.map=growing", "output.quiet=true", f"hydra.run.dir={d}")
    assert p.returncode == 0, p.stderr
    log = read_run(d / "run.mcap", z="all")
    s = json.loads((d / "summary.json").read_text())
    assert log.complete and len(log.frames) == s["n_frames"] - s["n_frames_skipped"]
    pts = [f["points"] for f in log.frames]
    assert pts == sorted(pts) and pts[-1] == s["n_points_diffused"]
    last = log.z_iterations[-1]
    assert log.z_dtype[last] == "float32" and log.z[last].shape[0] == pts[-1]
    pos = rrd_blocks(d / "run.rrd", "labels", "Points3D:positions")
    grew = [f["index"] for f in log.frames if f["new_points"] > 0]
    assert sorted(set().union(*[set(v) for v in pos.values()])) == grew
    last = log.frames[-1]["index"]
    assert len(map_at(pos, last)) == pts[-1]
    ids = rrd_blocks(d / "run.rrd", "labels", "Points3D:class_ids")
    np.testing.assert_array_equal(map_at(ids, last), class_ids(np.load(d / "labels.npy")))
    assert inspect_main([str(d)]) == 0


@pytest.mark.slow
def test_killed_online_run_leaves_readable_records(tmp_path):
    psutil = pytest.importorskip("psutil")
    run_dir = tmp_path / "run"
    env = dict(os.environ)
    env.pop("HYDRA_FULL_ERROR", None)
    # 1000 steps a frame and no early stop: a few hundred ms per frame on the demo, 120 frames: the run
    # is far from its end when its recorder (which may lag on a busy machine) has written 3 frames
    proc = subprocess.Popen([sys.executable, "-m", "diffuser_lab", "protocol=online", "scene.options.n_views=120",
                             "scene.options.point_spacing=0.08", "online.steps=1000", "solver.tol=0", "record.interval=1",
                             f"hydra.run.dir={run_dir}"], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    mcap = run_dir / "run.mcap"
    recorders = []
    try:
        deadline = time.time() + 120
        n = 0
        while time.time() < deadline and n < 3:  # another process's file: looked at 3 times a second
            time.sleep(0.3)
            if mcap.is_file() and mcap.stat().st_size > 8:  # past the magic bytes
                n = len(read_run(mcap).frames)
        assert n >= 3, "the run did not record 3 frames"
        assert proc.poll() is None, "the run ended before it could be killed"
        recorders = psutil.Process(proc.pid).children()  # the forked recording process
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    assert recorders, "the run records in a child process"
    # the recording process sees the run's end of the pipe close, finishes the files and exits
    _, alive = psutil.wait_procs(recorders, timeout=60)
    assert not alive, "the recording process did not finish after the run was killed"
    log = read_run(mcap, z="all")
    assert log.complete and log.summary is None and len(log.frames) >= 3
    idx = [f["index"] for f in log.frames]
    assert idx == list(range(len(idx))) and log.z_iterations == idx[: len(log.z_iterations)]
    assert len(log.z_iterations) >= len(idx) - 1 and log.z[log.z_iterations[-1]].shape[1] == 20
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a run.rrd closed in order has its footer
        ids = rrd_rows(run_dir / "run.rrd", "/world/online/labels/0000", "Points3D:class_ids")
    assert len(ids) >= 3 and sorted(ids) == list(range(len(ids)))
    p = subprocess.run([sys.executable, "-m", "diffuser_lab.cli.inspect", str(run_dir)], capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 0 and "did not finish" in p.stdout and "Traceback" not in p.stderr, p.stderr


@pytest.mark.slow
@pytest.mark.parametrize("process", [False, True])
def test_a_failing_online_record_never_stops_the_run(thread_run, tmp_path, monkeypatch, process):
    from diffuser_lab.recording import online as online_rec

    calls = []

    def boom(frame, update, *a, **kw):
        calls.append(update.index)
        if update.index == 2:
            raise RuntimeError("no space left")
        return real(frame, update, *a, **kw)

    real = online_rec.frame_record
    monkeypatch.setattr(online_rec, "frame_record", boom)
    res, hooks, cap = recorded_online(thread_run.cfg, tmp_path, process=process)
    np.testing.assert_array_equal(res.labels, thread_run.res.labels)  # the same run, to the end
    errors = hooks.files()["errors"]
    assert set(errors) == {"rerun", "mcap"} and "no space left" in errors["mcap"]
    assert calls == [0, 1, 2]  # switched off after the failure
    log = read_run(tmp_path / "run.mcap")
    assert log.complete and [f["index"] for f in log.frames] == [0, 1]  # what came before stays readable


@pytest.mark.slow
def test_online_layout_has_its_app_id_a_legend_and_its_plots(cli_runs):
    from rrd_layout import check_layout, static_column

    from diffuser_lab.data.taxonomy import load_taxonomy
    from diffuser_lab.recording.rerun_log import APP_ONLINE, UNLABELED_ID

    rrd = cli_runs["both"] / "run.rrd"
    gt = np.asarray(static_column(rrd, "/world/scene/ground_truth", "Points3D:class_ids"))
    tax = load_taxonomy(json.loads((cli_runs["both"] / "summary.json").read_text())["taxonomy"])
    v = check_layout(rrd, APP_ONLINE, tax, gt[gt != UNLABELED_ID], {
        "mIoU so far [%]": ["/metrics/diffuser_miou", "/metrics/bayesian_miou"],
        "map points [thousands]": ["/metrics/points_k"],
        "latency against the frame budget [ms]": ["/metrics/latency_ms", "/metrics/budget_ms", "/metrics/latency/**"]})
    assert v["tabs"][0] == "online: labels"
    assert rrd_rows(rrd, "/metrics/budget_ms", "Scalars:scalars") == {}  # online.rate=0: no frame budget
    # each frame's latency and its parts beside the sensor's frame budget (1 / online.rate)
    rrd = cli_runs["rerun"] / "run.rrd"
    summary = json.loads((cli_runs["rerun"] / "summary.json").read_text())
    frames = {f["index"]: f for f in summary["online"]["frames"] if not f.get("skipped")}
    budget = rrd_rows(rrd, "/metrics/budget_ms", "Scalars:scalars")
    rate = summary["online"]["rate_hz"]
    assert rate == 20 and sorted(budget) == sorted(frames)
    assert all(v == [pytest.approx(1000.0 / rate)] for v in budget.values()), budget
    for part in ("map_ms", "graph_ms", "evidence_ms", "steps_ms"):
        got = rrd_rows(rrd, f"/metrics/latency/{part}", "Scalars:scalars")
        assert {f: v[0] for f, v in got.items()} == pytest.approx({i: f[part] for i, f in frames.items()}), part
    lat = rrd_rows(rrd, "/metrics/latency_ms", "Scalars:scalars")
    assert all(sum(frames[i][p] for p in ("map_ms", "graph_ms", "evidence_ms", "steps_ms")) <= v[0] + 1e-6
               for i, v in lat.items())  # the parts add up to at most the frame's latency


def test_online_blocks_only_fill_and_get_added():
    """run.rrd's blocks of a growing map (issue 50: small blocks first, so a frame re-logs few
    positions; doubling sizes, so 64 blocks, the errors tab's overrides, hold ~1M rows): contiguous,
    and those of a smaller map are the larger map's, the last one cut."""
    from diffuser_lab.recording.rerun_log import (ONLINE_BLOCK_ROWS, ONLINE_BLOCKS_PER_SIZE, ONLINE_MAX_BLOCKS,
                                                  online_blocks)

    assert online_blocks(0) == []
    big = online_blocks(3_000_000)
    assert big[0] == (0, ONLINE_BLOCK_ROWS) and all(a[1] == b[0] for a, b in zip(big, big[1:]))
    sizes = [hi - lo for lo, hi in big[:-1]]
    assert sizes[ONLINE_BLOCKS_PER_SIZE] == 2 * sizes[ONLINE_BLOCKS_PER_SIZE - 1]
    assert big[ONLINE_MAX_BLOCKS - 1][1] == 983_040 and sizes[ONLINE_MAX_BLOCKS] == sizes[ONLINE_MAX_BLOCKS - 1]
    for n in (1, 4095, 4096, 4097, 70_000, 983_041):
        small = online_blocks(n)
        assert small[:-1] == big[:len(small) - 1] and small[-1][0] == big[len(small) - 1][0] and small[-1][1] == n
