"""protocol=online: the online Diffuser (diffuser_lab/method/online.py) and its runner
(diffuser_lab/runs/online.py) on a given cloud: evidence frame by frame equal to the batch
evidence, determinism, a frame that sees nothing, bad frames, the discount that keeps the result
at the early-stopped batch instead of drifting towards the fixed point, the numpy path, the CLI."""
from __future__ import annotations

import dataclasses
import json
import os

import numpy as np
import pytest

from conftest import SHARED, run_cli
from diffuser_lab.config import default_config
from diffuser_lab.data.predictions import with_predictions
from diffuser_lab.data.scene import Frame
from diffuser_lab.method import evidence as evidence_mod
from diffuser_lab.method.diffusion import labels_from_scores
from diffuser_lab.method.online import OnlineDiffuser, discount
from diffuser_lab.runs.online import online
from diffuser_lab.runs.pipeline import load_scene, run
from diffuser_lab.runs.work import work_cloud

SMALL = {"scene.options.n_views": 10, "scene.options.point_spacing": 0.08, "protocol.name": "online",
         "record.mode": "off"}


def _cfg(**kw):
    return default_config(**{**SMALL, **kw})


@pytest.fixture(scope="module")
def demo():
    cfg = _cfg()
    scene = load_scene(cfg.scene)
    frames = with_predictions(scene.frames, cfg.predictions, scene.taxonomy)
    frames = [frames[i] for i in range(len(frames))]
    pts, nrm, _ = work_cloud(scene, cfg.scene.voxel_size)
    return cfg, scene, frames, pts, nrm


def _play(cfg, scene, frames, pts, nrm, backend="auto", reps=1):
    od = OnlineDiffuser(cfg, scene.taxonomy, points=pts, normals=nrm, backend=backend)
    for _ in range(reps):
        for f in frames:
            od.add_frame(f)
    od.close()
    return od


def test_discount_keeps_half_the_weight_before_half_the_horizon():
    g = discount(200)
    assert g ** 100 == pytest.approx(0.5)
    assert discount(10) < g < 1.0


def test_evidence_frame_by_frame_equals_batch_evidence(demo):
    cfg, scene, frames, pts, nrm = demo
    od = _play(cfg, scene, frames, pts, nrm)
    batch = evidence_mod.accumulate(pts, frames, scene.taxonomy.num_classes, depth_tol=cfg.evidence.depth_tol)
    # the map's rows are the work points in the graph's order
    np.testing.assert_array_equal(od.mass[: od.n], batch.mass[od.order])
    np.testing.assert_array_equal(od.links[: od.n], batch.links[od.order])
    # the online Bayesian baseline after the last frame is the batch one
    np.testing.assert_array_equal(od.bayesian_labels, labels_from_scores(batch.mass)[od.order])
    assert [h.seen for h in od.history] == batch.points_per_frame


def test_online_run_is_deterministic(demo):
    cfg, scene, frames, pts, nrm = demo
    a = _play(cfg, scene, frames, pts, nrm)
    b = _play(cfg, scene, frames, pts, nrm)
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.scores(), b.scores())
    assert [h.changed for h in a.history] == [h.changed for h in b.history]


def test_a_frame_that_sees_nothing_changes_nothing(demo):
    cfg, scene, frames, pts, nrm = demo
    od = OnlineDiffuser(cfg, scene.taxonomy, points=pts, normals=nrm)
    for f in frames[:4]:
        od.add_frame(f)
    Z, lab = od.scores(), od.labels.copy()
    away = np.asarray(frames[4].T_cw).copy()
    away[2, 3] -= 100.0  # the camera 100 m back along its axis: the whole room is behind it
    od.add_frame(dataclasses.replace(frames[4], T_cw=away))
    st = od.history[-1]
    assert st.seen == 0 and st.steps == 0 and st.changed == 0
    np.testing.assert_array_equal(od.scores(), Z)
    np.testing.assert_array_equal(od.labels, lab)
    od.close()


@pytest.mark.slow
def test_numpy_path_agrees_with_the_compiled_one(demo):
    cfg, scene, frames, pts, nrm = demo
    for solver in ("jacobi", "gmres"):
        c = dataclasses.replace(cfg, online=dataclasses.replace(cfg.online, solver=solver))
        a = _play(c, scene, frames, pts, nrm, backend="auto")
        b = _play(c, scene, frames, pts, nrm, backend="scipy")
        assert np.mean(a.labels == b.labels) >= 0.999, solver
        za, zb = a.scores(), b.scores()
        assert np.abs(za - zb).max() <= 1e-3 * np.abs(za).max(), solver


def _many_class_frames(frames, classes: int, seed: int = 0):
    """The frames with 2D labels spread over ``classes`` classes (each true class split at random
    into look-alikes), so that more than one 32-class block of Z is active."""
    rng = np.random.default_rng(seed)
    out = []
    for f in frames:
        split = rng.integers(0, classes // 20, size=f.labels.shape)
        lab = np.where(f.labels >= 0, (f.labels.astype(np.int64) * (classes // 20) + split) % classes, -1)
        out.append(dataclasses.replace(f, labels=lab.astype(np.int16)))
    return out


TORCH_MISSING = ("torch is not installed: the test extra leaves it out (PyPI's default torch is a multi-GB "
                 "CUDA build); `pip install torch` (a CPU build will do) and this runs")


def _torch_missing() -> bool:
    import importlib.util

    return importlib.util.find_spec("torch") is None


@pytest.fixture(scope="module")
def many_online(demo):
    """60 classes over the demo's first 6 frames, and the scipy path's online run of them."""
    from diffuser_lab.data.taxonomy import Taxonomy

    cfg, scene, frames, pts, nrm = demo
    tax = Taxonomy(name="many", names=tuple(f"c{i}" for i in range(60)), colors=np.zeros((60, 3), np.uint8))
    many = _many_class_frames(frames[:6], 60)

    def play(backend="auto", device=None, region=True, **solver):
        c = dataclasses.replace(cfg, solver=dataclasses.replace(cfg.solver, **solver),
                                online=dataclasses.replace(cfg.online, region=region))
        od = OnlineDiffuser(c, tax, points=pts, normals=nrm, backend=backend, device=device)
        for f in many:
            od.add_frame(f)
        od.close()
        return od

    ref = {True: play("scipy"), False: play("scipy", region=False)}  # with a frame's region, every row
    assert len(ref[True].system.active) > 32
    return play, ref


@pytest.mark.slow
@pytest.mark.parametrize("name", ["numba", "numba-sparse", "scipy-sparse",
                                  pytest.param("torch", marks=pytest.mark.skipif(_torch_missing(), reason=TORCH_MISSING))])
def test_every_backend_runs_the_online_system(many_online, name):
    """The online Diffuser is a user of the one diffusion core: the compiled backend for more than
    32 active classes (several class blocks), the sparse class set and torch (on the CPU) give the
    numpy/scipy path's result (the compiled backend with each frame's region; the others, which step
    every row, as the numpy/scipy path stepping every row)."""
    play, refs = many_online
    kw = {"numba": dict(backend="numba"), "numba-sparse": dict(backend="numba", sparse_classes="on", classes_per_point=60),
          "scipy-sparse": dict(backend="scipy", sparse_classes="on", classes_per_point=60),
          "torch": dict(backend="torch", device="cpu")}[name]
    od = play(**kw)
    ref = refs[name == "numba"]
    zr = ref.scores()
    assert od.backend_name == name, (od.backend_name, name)
    assert np.mean(od.labels == ref.labels) >= 0.999, name
    assert np.abs(od.scores() - zr).max() <= 1e-3 * np.abs(zr).max(), name


FEW = {"online.rate": 0.0, "online.finish": 0}  # each frame's steps only: no idle steps, no finishing pass


def test_final_labels_match_the_batch_diffuser(demo):
    cfg, scene, frames, pts, nrm = demo
    res = online(_cfg(**FEW), scene=scene)
    b = res.batch
    # The hardest case for a few steps per frame: 10 frames in all (100 Jacobi steps, fewer than the
    # batch's 200), each seeing a small part of a coarse (8 cm) cloud whose unseen points the batch
    # reaches over long chains (measured 2026-12-07: 84.7% equal with each frame's region, 86.0% with
    # every row stepped; GMRES 95.1%; full-size figures: docs/online.md)
    assert b["equal_labels"] >= 83.5, b
    every = online(_cfg(**FEW, **{"online.region": False}), scene=scene).batch
    assert every["equal_labels"] >= 85.0 and every["equal_labels"] - b["equal_labels"] <= 2.5, (every, b)
    g = online(_cfg(**{"online.solver": "gmres", "online.steps": 8, **FEW}), scene=scene)
    assert g.batch["equal_labels"] >= 94.0 and g.batch["equal_labels"] > b["equal_labels"], g.batch
    assert abs(g.metrics["miou"] - b["diffuser"]["miou"]) <= 1.5, (g.metrics["miou"], b)
    # the online Bayesian on a given cloud is exactly the batch one on the same frames
    assert res.bayesian["miou"] == pytest.approx(b["bayesian"]["miou"])
    assert len(res.frames) == len(frames) and res.latency_ms["frames"] == len(frames)
    # each frame's mIoU is of the labels it left: the last one's are the run's (no finishing pass here),
    # and the first frames, seeing little of the room, score less
    assert res.frames[-1]["diffuser_miou"] == pytest.approx(res.metrics["miou"])
    assert res.frames[0]["diffuser_miou"] < res.frames[-1]["diffuser_miou"]


def test_idle_steps_fill_the_sensors_frame_time_and_the_finishing_pass_reaches_the_batch(demo):
    """online.rate: what a frame's update leaves of 1 / rate seconds goes to extra steps on every
    row, reported apart from its latency, each giving the error bound; online.final: after the last
    frame, the batch iteration on the map (batch: its labels exactly) or steps of the discounted one
    until one changes Z by <= solver.tol (settle). Each moves the map towards the batch result the
    few steps per frame only track."""
    cfg, scene, frames, pts, nrm = demo
    few = online(_cfg(**FEW), scene=scene)
    idle = online(_cfg(**{"online.rate": 10.0, "online.finish": 0}), scene=scene)
    done = online(_cfg(**{"online.rate": 0.0}), scene=scene)  # the finishing pass alone
    settle = online(_cfg(**{"online.rate": 0.0, "online.final": "settle"}), scene=scene)
    assert all(f["idle_steps"] == 0 for f in few.frames) and not few.settings["finish"]
    steps = [f["idle_steps"] for f in idle.frames]
    assert sum(steps) > 0, steps
    for f in idle.frames:  # the update's latency excludes the idle steps; both fit the 100 ms slot (a chunk's slack)
        assert f["latency_ms"] + f["idle_ms"] <= 100.0 + 25.0, f
        assert (f["idle_ms"] > 0) == (f["idle_steps"] > 0), f
        if f["idle_steps"]:  # gamma r / (1 - gamma) of the last idle step's relative change r
            g = idle.settings["gamma"]
            assert f["error_bound"] == pytest.approx(g * f["sweep_residual"] / (1 - g)), f
    fin = done.settings["finish"]
    assert fin["final"] == "batch" and 0 < fin["steps"] <= cfg.solver.max_iter, fin
    fs = settle.settings["finish"]
    assert fs["final"] == "settle" and fs["steps"] > 0 and fs["residual"] <= cfg.solver.tol, fs
    eq = {k: r.batch["equal_labels"] for k, r in (("few", few), ("idle", idle), ("finish", done), ("settle", settle))}
    # measured: 84.7, 97-99 (as far as the machine's idle time takes it), 100 (the batch's own labels) and
    # 99.0% equal to the batch labels
    assert eq["few"] < eq["idle"] and eq["few"] < eq["settle"] and eq["settle"] >= 97.0, eq
    assert eq["finish"] == 100.0 and done.metrics["miou"] == pytest.approx(done.batch["diffuser"]["miou"]), eq
    # the latency summary is the updates' alone, as before
    assert done.latency_ms["frames"] == len(frames)


def test_the_discount_stops_the_drift_towards_the_fixed_point(demo):
    """Frames played again and again (15 times): the discounted iteration stays at the batch labels; the
    undiscounted one (discount=1, the paper's iteration warm-started) keeps smoothing."""
    cfg, scene, frames, pts, nrm = demo
    batch = run(dataclasses.replace(cfg, protocol=dataclasses.replace(cfg.protocol, name="global_3d")), scene=scene)
    want = labels_from_scores(batch.diffusion.Z)
    eq = {}
    for disc in (None, 1.0):  # every row stepped every frame: the discount alone
        c = dataclasses.replace(cfg, online=dataclasses.replace(cfg.online, discount=disc, region=False))
        od = _play(c, scene, frames, pts, nrm, reps=15)
        eq[disc] = float(np.mean(od.labels[od.map_index] == want))
    # measured (equal labels after 1, 2, 5, 10, 15 passes): discounted 87.8, 93.9, 97.7, 98.7, 98.7%;
    # undiscounted 86.9, 94.4, 96.7, 93.4, 92.5%: it passes the batch result and goes on smoothing
    assert eq[None] >= 0.98, eq
    assert eq[1.0] < eq[None] - 0.03, eq


def test_bad_frames_are_skipped_or_stop_the_run(demo):
    _, scene, _, _, _ = demo
    pcfg = _cfg(**{"predictions.source": "gt"})
    bad = [scene.frames[i] for i in range(len(scene.frames))]
    bad[2] = dataclasses.replace(bad[2], depth=np.zeros_like(bad[2].depth))
    T = np.asarray(bad[5].T_cw).copy()
    T[:3, :3] *= 2.0  # not a rotation
    bad[5] = dataclasses.replace(bad[5], T_cw=T)
    sc = dataclasses.replace(scene, frames=bad)
    frames = bad
    with pytest.warns(UserWarning) as rec:
        res = online(pcfg, scene=sc)
    msgs = [str(w.message) for w in rec]
    assert any("frame 2 skipped" in m and "no valid depth" in m for m in msgs), msgs
    assert any("frame 5 skipped" in m and "not a rigid transform" in m for m in msgs), msgs
    skipped = [f["index"] for f in res.frames if f["skipped"]]
    assert skipped == [2, 5]
    assert res.latency_ms["frames"] == len(frames) - 2
    stop = _cfg(**{"predictions.source": "gt", "online.bad_frames": "stop"})
    with pytest.raises(ValueError, match="no valid depth"):
        online(stop, scene=sc)


@pytest.mark.slow
def test_cli_online_run_writes_its_folder(tmp_path):
    r = run_cli("protocol=online", "scene.options.n_views=6", "scene.options.point_spacing=0.08", "record=off",
                f"hydra.run.dir={tmp_path / 'run'}")
    assert r.returncode == 0, r.stderr
    assert "diffuser-lab online" in r.stdout and "per frame [ms]" in r.stdout
    assert "final labels equal to the batch Diffuser's" in r.stdout
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert s["status"] == "ok" and s["protocol"] == "online" and len(s["online"]["frames"]) == 6
    assert 50 < s["batch"]["equal_labels"] <= 100  # six tiny views: a mechanics check (figures: docs/online.md)
    labels = np.load(tmp_path / "run" / "labels.npy")
    assert labels.shape == (s["n_points"],)


@pytest.mark.skipif(not (SHARED / "data" / "scannet" / "scene0470_00").is_dir(),
                    reason=f"real ScanNet scene absent: {SHARED / 'data' / 'scannet' / 'scene0470_00'} not found")
@pytest.mark.slow
def test_scannet0470_given_map_keeps_the_batch_result():
    """The issue's accuracy targets on the real scene (its latency targets: the benchmark)."""
    from conftest import compose

    cfg = compose("scene=scannet0470", "protocol=online", "record=off")
    res = online(cfg)
    assert res.batch["equal_labels"] >= 99.0, res.batch
    assert abs(res.metrics["miou"] - res.batch["diffuser"]["miou"]) <= 0.5, (res.metrics, res.batch)


# ------------------------------------------------------------------------------ growing map

GROW = {"online.map": "growing", "scene.options.n_views": 8, "online.voxel_size": 0.06}


def _grow_play(cfg, frames, backend="auto"):
    from diffuser_lab.data.scene import SCANNET20

    od = OnlineDiffuser(cfg, SCANNET20, backend=backend)
    for f in frames:
        od.add_frame(f)
    od.close()
    return od


@pytest.fixture(scope="module")
def grow_demo():
    cfg = _cfg(**GROW)
    scene = load_scene(cfg.scene)
    frames = with_predictions(scene.frames, cfg.predictions, scene.taxonomy)
    return cfg, scene, [frames[i] for i in range(len(frames))]


def test_growing_evidence_equals_batch_evidence(grow_demo, monkeypatch):
    """By default (``online.revisit=null``: every earlier frame kept) every map point has the evidence
    of every frame, as the batch pipeline computes it on the final cloud, although the frames whose
    view box misses a frame's new points are never projected (:class:`FrameStore`); with the last 2
    frames alone (``online.revisit=2``, the old default's kind) late points miss evidence."""
    from diffuser_lab.method.online import FrameStore

    cfg, scene, frames = grow_demo
    asked, used = [], []
    seeing = FrameStore.seeing

    def counted(self, points):
        out = seeing(self, points)
        asked.append(len(self))
        used.append(len(out))
        return out

    monkeypatch.setattr(FrameStore, "seeing", counted)
    od = _grow_play(cfg, frames)
    batch = evidence_mod.accumulate(np.ascontiguousarray(od.points), frames, scene.taxonomy.num_classes,
                                    depth_tol=cfg.evidence.depth_tol)
    np.testing.assert_array_equal(od.evidence(), batch.mass)
    np.testing.assert_array_equal(od.bayesian_labels, labels_from_scores(batch.mass))
    assert od.n == od.graph.n and sum(h.new_points for h in od.history) == od.n
    assert od.store.dropped == 0 and len(od.store) == len(frames)
    assert sum(used) < sum(asked), (used, asked)  # some frames were skipped by their view box
    few = _grow_play(dataclasses.replace(cfg, online=dataclasses.replace(cfg.online, revisit=2)), frames)
    assert few.store.dropped == len(frames) - 2
    assert few.links.sum() < od.links.sum()


def test_frame_store_keeps_within_its_limits():
    from diffuser_lab.method.online import FrameStore

    K = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
    f = Frame(name="f", K=K, T_cw=np.eye(4), depth=np.full((48, 64), 2.0, np.float32),
              labels=np.zeros((48, 64), np.int16))
    size = f.depth.nbytes + f.labels.nbytes
    st = FrameStore(None, 2.5 * size, depth_tol=0.05)
    for i in range(4):
        st.add(dataclasses.replace(f, name=str(i)))
    assert [x.name for x in st.frames] == ["2", "3"] and st.dropped == 2 and st.bytes == 2 * size
    assert st.frames[0].rgb is None
    # the view box: points in front of the camera at 2 m are seen, points behind it or far to the side not
    near = np.array([[0.0, 0.0, 2.0], [0.1, 0.1, 1.98]], np.float32)
    assert len(st.seeing(near)) == 2
    assert st.seeing(np.array([[0.0, 0.0, -1.0]], np.float32)) == []
    assert st.seeing(np.array([[5.0, 0.0, 2.0]], np.float32)) == []
    st2 = FrameStore(1, 1e12, depth_tol=0.05)
    st2.add(f)
    st2.add(f)
    assert len(st2) == 1 and st2.dropped == 1
    assert FrameStore(0, 1e12, 0.05).seeing(near) == []


def test_growing_run_is_deterministic_and_kept_in_blocks(grow_demo):
    """The same frames give the same map bit for bit; the map is never re-sorted: each frame's new
    points are one block of rows (appended), in the Morton order of their voxels."""
    from diffuser_lab.backends.voxel_map import voxel_keys

    cfg, scene, frames = grow_demo
    a = _grow_play(cfg, frames)
    b = _grow_play(cfg, frames)
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.scores(), b.scores())
    assert a.system.order is None  # the system's rows are the map's points
    ends = np.cumsum([h.new_points for h in a.history])
    sizes = np.diff(np.r_[0, ends])
    assert ends[-1] == a.n and (sizes > 0).sum() >= 5
    keys = voxel_keys(a.points, cfg.online.voxel_size)
    for lo, hi in zip(np.r_[0, ends[:-1]], ends):  # each block ascending by its voxels' Morton keys
        assert np.all(np.diff(keys[lo:hi]) > 0), (lo, hi)
    assert not np.all(np.diff(keys) > 0)  # and the map as a whole is not (no re-sort)


def test_growing_numpy_path_agrees(grow_demo):
    cfg, scene, frames = grow_demo
    a = _grow_play(cfg, frames[:5])
    b = _grow_play(cfg, frames[:5], backend="scipy")
    np.testing.assert_array_equal(a.points, b.points)
    assert np.mean(a.labels == b.labels) >= 0.999


def test_a_coarse_growing_map_only_grows_and_stays_near_the_batch_run(grow_demo):
    """A small stand-in (8 frames, 6 cm voxels): the map only grows, and its labels stay near the
    batch run's on the final cloud. The documented targets are checked at full size below
    (test_the_documented_accuracy_targets_at_full_size)."""
    cfg, scene, frames = grow_demo
    res = online(cfg, scene=scene)
    assert res.mode == "growing" and res.points.shape[0] == res.frames[-1]["points"]
    assert [f["points"] for f in res.frames] == sorted(f["points"] for f in res.frames)  # it only grows
    assert res.batch["equal_labels"] >= 92.0, res.batch
    assert abs(res.metrics["miou"] - res.batch["diffuser"]["miou"]) <= 3.0, (res.metrics, res.batch)


@pytest.mark.slow
def test_cli_bad_frame_skips_or_stops_and_keeps_the_records(tmp_path):
    """A posed RGB-D folder whose frame 2 has no valid depth (every pixel 65535): skipped with one
    warning line, or (online.bad_frames=stop) one error line, exit 1, and the records of frames 0-1
    readable. (A pose that is not rigid stops the rgbd_folder loader itself, before any frame.)"""
    from datasets import _save_u16, make_world, write_rgbd

    root = write_rgbd(tmp_path, make_world())
    depth = root / "frame-000002.depth.png"
    from PIL import Image

    h, w = np.asarray(Image.open(depth)).shape
    _save_u16(depth, np.full((h, w), 65535))
    args = ["scene=rgbd_folder", f"scene.options.root={root}", "protocol=online", "predictions=model",
            "predictions.model._target_=tests.toy_networks.grey_levels", "predictions.cache_dir=null",
            "scene.options.cloud_voxel=0.05"]
    r = run_cli(*args, f"hydra.run.dir={tmp_path / 'skip'}")
    assert r.returncode == 0, r.stderr
    warn = [ln for ln in r.stderr.splitlines() if "online: frame 2 skipped" in ln]
    assert len(warn) == 1 and "frame-000002" in warn[0] and "no valid depth" in warn[0], r.stderr
    s = json.loads((tmp_path / "skip" / "summary.json").read_text())
    assert s["status"] == "ok" and s["n_frames_skipped"] == 1
    r = run_cli(*args, "online.bad_frames=stop", f"hydra.run.dir={tmp_path / 'stop'}")
    assert r.returncode == 1
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("diffuser-lab: error:")]
    assert len(errors) == 1 and "frame-000002" in errors[0] and "no valid depth" in errors[0], r.stderr
    s = json.loads((tmp_path / "stop" / "summary.json").read_text())
    assert s["status"] == "failed" and "no valid depth" in s["error"]
    from diffuser_lab.recording.mcap_read import read_run

    log = read_run(tmp_path / "stop" / "run.mcap")
    assert [f["index"] for f in log.frames] == [0, 1], log.frames  # the frames before the stop, whole
    i = subprocess_inspect(tmp_path / "stop")
    assert i.returncode == 0 and "frames" in i.stdout, i.stdout + i.stderr


def subprocess_inspect(run_dir):
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "diffuser_lab.cli.inspect", str(run_dir)], capture_output=True,
                          text=True, timeout=300)


def test_online_run_keeps_blas_on_one_thread_while_it_plays(demo):
    """BLAS's spinning workers took the Jacobi threads' core between frames (docs/online.md): the
    run limits BLAS to one thread while the frames play and gives the caller's limit back after."""
    threadpoolctl = pytest.importorskip("threadpoolctl")
    from diffuser_lab.hooks import RunHooks

    def blas_threads():
        return [p["num_threads"] for p in threadpoolctl.threadpool_info() if p["user_api"] == "blas"]

    seen = []

    class Hooks(RunHooks):
        def on_frame(self, i, frame):
            seen.append(blas_threads())

    cfg, scene, *_ = demo
    with threadpoolctl.threadpool_limits(2, user_api="blas"):  # the caller's limit (the suite's workers have 1)
        before = blas_threads()
        online(dataclasses.replace(cfg, online=dataclasses.replace(cfg.online, compare_batch=False)), scene=scene,
               hooks=Hooks())
        assert seen and all(s and max(s) == 1 for s in seen), seen
        assert blas_threads() == before
    assert max(before) == 2 or len(os.sched_getaffinity(0)) == 1, before  # BLAS ran on 2 threads before the run


ACCURACY_TARGETS = {  # issue 57's accuracy targets; their latency: tests/benchmarks/test_online_targets.py
    "scannet0470-given": (["scene=scannet0470"], SHARED / "data" / "scannet" / "scene0470_00"),
    "scannet0470-growing": (["scene=scannet0470", "online.map=growing"], SHARED / "data" / "scannet" / "scene0470_00"),
    "7scenes-growing": (["scene=rgbd_folder", f"scene.options.root={SHARED / 'data' / '7scenes_sample'}",
                         "online.map=growing", "predictions=model",
                         "predictions.model._target_=tests.toy_networks.grey_levels", "predictions.cache_dir=null"],
                        SHARED / "data" / "7scenes_sample"),
    "demo-growing": (["online.map=growing"], None),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(ACCURACY_TARGETS))
def test_the_documented_accuracy_targets_at_full_size(case):
    """Issue 57's targets on the sequences it states them for (not a smaller stand-in): final labels
    equal to the batch Diffuser's (on the same frames; a growing map: on its final cloud) on >= 99 %
    of the points, and where there is ground truth the final mIoU within 0.5 of the batch run's and
    no class the batch labels (IoU >= 10) below half its batch IoU online."""
    from conftest import compose

    args, data = ACCURACY_TARGETS[case]
    if data is not None and not data.is_dir():
        pytest.skip(f"real data absent: {data} not found")
    res = online(compose(*args, "protocol=online", "record=off"))
    b = res.batch
    assert b["equal_labels"] >= 99.0, b
    if res.metrics is None:
        return
    assert abs(res.metrics["miou"] - b["diffuser"]["miou"]) <= 0.5, (res.metrics["miou"], b)
    mine, theirs = res.metrics["per_class_iou"], b["diffuser"]["per_class_iou"]
    lost = {c: (mine.get(c, 0.0), v) for c, v in theirs.items() if v >= 10 and mine.get(c, 0.0) < v / 2}
    assert not lost, lost
    # the labels the frames left (before the final pass) track the batch's: measured 2026-12-07
    # demo 84.5 vs 81.3 (the early stop of the batch smooths the picture class away), scene0470 (growing)
    # 88.7 vs 88.9, (given) 88.8 vs 89.7
    assert abs(res.frames[-1]["diffuser_miou"] - b["diffuser"]["miou"]) <= 4.0, (res.frames[-1], b)
