"""Records of a run (issue 4): run.rrd (Rerun) and run.mcap (MCAP) as observers, replay, inspection."""
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import SMALL_DEMO, run_cli

from diffuser_lab.cli.inspect import main as inspect_main
from diffuser_lab.config import default_config
from diffuser_lab.method.diffusion import labels_from_scores
from diffuser_lab.recording import make_hooks
from diffuser_lab.recording.mcap_encode import TOPIC_Z
from diffuser_lab.recording.mcap_read import read_run
from diffuser_lab.recording.rerun_log import UNLABELED_ID
from diffuser_lab.runs.pipeline import run

RERUN = str(Path(sys.executable).with_name("rerun"))


def rrd_class_ids(path: Path) -> dict:
    """{diffusion_step: (M,) class ids} of world/diffusion/labels, read with rerun's own reader."""
    from rerun.chunk import RrdReader

    out = {}
    for ch in RrdReader(path).stream():
        if ch.entity_path == "/world/diffusion/labels" and not ch.is_static:
            rb = ch.to_record_batch()
            for step, ids in zip(rb.column("diffusion_step").to_pylist(), rb.column("Points3D:class_ids").to_pylist()):
                out[step] = np.asarray(ids)
    return out


def as_class_ids(labels: np.ndarray) -> np.ndarray:
    return np.where(labels < 0, UNLABELED_ID, np.asarray(labels, np.int64))  # int16 would wrap 65535 to -1


def recorded(cfg, scene, run_dir):
    hooks = make_hooks(cfg, run_dir)
    try:
        res = run(cfg, scene=scene, hooks=hooks)
    finally:
        hooks.close()
    return res, hooks


@pytest.fixture(scope="module")
def cli_runs(tmp_path_factory):
    """The same small demo run from the command line, recorded (both, interval 10) and not."""
    base = tmp_path_factory.mktemp("rec")
    out = {}
    for mode in ("both", "off"):
        d = base / mode
        p = run_cli(*SMALL_DEMO, f"record={mode}", "output.quiet=true", f"hydra.run.dir={d}")
        assert p.returncode == 0, p.stderr
        out[mode] = d
    return out


@pytest.mark.slow
def test_round_trip_last_z_is_the_solvers_and_gives_the_labels(cli_runs):
    d = cli_runs["both"]
    s = json.loads((d / "summary.json").read_text())
    assert s["records"] == {"rrd": "run.rrd", "mcap": "run.mcap"}
    log = read_run(d / "run.mcap", z="all")
    assert log.complete and not log.truncated
    assert log.z_iterations == [1, 2, 5, 10, 20, 50, 60]  # the 1-2-5 log steps, first and last
    assert [m["iteration"] for m in log.metrics] == log.z_iterations
    assert log.z_dtype == {**{it: "q8" for it in log.z_iterations[:-1]}, 60: "float32"}
    Z = log.z[60]
    assert Z.dtype == np.float32 and Z.shape == (s["n_points"], s["n_classes"])
    labels = np.load(d / "labels.npy")
    np.testing.assert_array_equal(labels_from_scores(Z), labels)
    assert log.metrics[-1]["miou"] == pytest.approx(s["metrics"]["miou"], abs=1e-9)
    assert log.summary["diffusion"]["iterations"] == 60
    assert "graph:" in log.config_yaml and "scene.options.n_views=10" in log.overrides


def test_library_final_z_exact_also_after_early_convergence(small_demo_scene, tmp_path):
    # a loose tolerance stops the diffusion between two recorded iterations: the last one is
    # then recorded from the returned Z
    cfg = default_config(**{"solver.max_iter": 200, "solver.tol": 0.02, "record.interval": 10})
    res, hooks = recorded(cfg, small_demo_scene, tmp_path)
    it = res.diffusion.iterations
    assert res.diffusion.converged and it % 10 != 0 and it < 200
    log = read_run(tmp_path / "run.mcap", z=[it])
    assert log.z_iterations == [1] + list(range(10, it, 10)) + [it] == hooks.recorded
    np.testing.assert_array_equal(log.z[it], res.diffusion.Z)  # exactly, float32
    np.testing.assert_array_equal(labels_from_scores(log.z[it]), res.labels)
    assert sorted(rrd_class_ids(tmp_path / "run.rrd")) == log.z_iterations


@pytest.mark.parametrize("mode", ["background", "background-slow", "in-line"])
def test_every_recorded_z_and_label_cloud_is_that_iterations(small_demo_scene, tmp_path, monkeypatch, mode):
    # the solver reuses one buffer for what observers see, the recording thread a few for the
    # Z states it has queued (background-slow: a slow recorder makes the run wait for them),
    # and the MCAP recorder its message buffers: each recorded iteration must still hold its
    # own Z, and the per-iteration cloud its own labels and colours
    import time

    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

    from diffuser_lab import recording
    from diffuser_lab.hooks import RunHooks
    from diffuser_lab.recording.mcap_encode import TOPIC_LABELS, decode_point_cloud
    from diffuser_lab.recording.mcap_read import iter_run
    from diffuser_lab.recording.mcap_write import McapRecorder

    monkeypatch.setattr(recording, "ASYNC", mode != "in-line")
    if mode == "background-slow":
        slow = McapRecorder.log_step
        monkeypatch.setattr(McapRecorder, "log_step", lambda self, step, **kw: (time.sleep(0.03), slow(self, step, **kw)))

    # record=full's precision: every Z state float32, a cloud per recorded iteration
    cfg = default_config(**{"solver.max_iter": 40, "record.interval": 5, "record.z_precision": "float32",
                            "record.clouds": "all"})

    class Copies(RunHooks):
        def __init__(self):
            self.z = {}

        def wants(self, it):
            return it == 1 or it % 5 == 0

        def observe(self, it, Z, stats):
            self.z[it] = np.array(Z)

    copies = Copies()
    run(cfg, scene=small_demo_scene, hooks=copies)
    recorded(cfg, small_demo_scene, tmp_path)
    log = read_run(tmp_path / "run.mcap", z="all")
    assert log.z_iterations == sorted(copies.z) == [1, 5, 10, 15, 20, 25, 30, 35, 40]
    for it, Z in copies.z.items():
        np.testing.assert_array_equal(log.z[it], Z, err_msg=f"iteration {it}")
    tax = small_demo_scene.taxonomy
    colors = np.vstack([tax.colors, [[70, 70, 70]]])
    clouds = [decode_point_cloud(PointCloud.FromString(data))
              for topic, data in iter_run(tmp_path / "run.mcap", log) if topic == TOPIC_LABELS]
    assert len(clouds) == len(copies.z)
    for (it, Z), c in zip(sorted(copies.z.items()), clouds):
        lab = labels_from_scores(Z)
        np.testing.assert_array_equal(c["label"], lab)
        rgb = np.stack([c["red"], c["green"], c["blue"]], 1)
        np.testing.assert_array_equal(rgb, colors[lab], err_msg=f"iteration {it}")  # -1: unlabeled grey
        assert (c["alpha"] == 255).all()


@pytest.mark.parametrize("voxels", [False, True])
def test_compiled_step_statistics_equal_numpy(small_demo_scene, voxels):
    """StepTracker's one compiled pass gives numpy's labels, changes, mIoU, accuracy, wrong
    points and coverage (confidence up to float32 summation order), with and without a voxel
    grid between the diffused and the original points, and without ground truth."""
    from diffuser_lab.backends import numba as nb
    from diffuser_lab.backends import records
    from diffuser_lab.recording import steps

    if not nb.available():
        pytest.skip("numba not importable or DIFFUSER_LAB_NUMBA=0")
    cfg = default_config(**{"solver.max_iter": 30, "scene.voxel_size": 0.1 if voxels else 0.0})
    zs = {}
    res = run(cfg, scene=small_demo_scene, observer=lambda it, Z, st: zs.__setitem__(it, np.array(Z)))
    sc = res.scene
    to_work = steps.original_to_work(res.work_points, sc.points) if voxels else None
    for gt in (sc.gt_labels, None):
        fused = steps.StepTracker(len(res.work_points), sc.taxonomy.names, gt, to_work)
        plain = steps.StepTracker(len(res.work_points), sc.taxonomy.names, gt, to_work)
        for it in (1, 2, 10, 30):
            a = fused.step(it, zs[it], 0.5)
            assert records.compiled()
            with pytest.MonkeyPatch.context() as mp:  # the numpy twin
                mp.setattr(nb, "available", lambda: False)
                b = plain.step(it, zs[it], 0.5)
            np.testing.assert_array_equal(a.labels, b.labels)
            np.testing.assert_allclose(a.confidence, b.confidence, atol=1e-6)
            assert (a.n_changed, a.miou, a.accuracy, a.coverage) == (b.n_changed, b.miou, b.accuracy, b.coverage)
            assert a.mean_confidence == pytest.approx(b.mean_confidence, abs=1e-6)
            if gt is None:
                assert a.wrong is None and b.wrong is None
            else:
                np.testing.assert_array_equal(a.wrong, b.wrong)
                assert a.wrong.any() and a.miou > 0


def test_z_state_bytes_is_the_protobuf_serialisation():
    from diffuser_lab.recording import schema
    from diffuser_lab.recording.mcap_encode import decode_z, z_state_bytes

    Z = np.random.default_rng(0).random((50, 7), dtype=np.float32) * 1e-3
    pool = bytearray(10_000)  # larger than needed: reused, only the filled part is the message
    for dtype, out, major in (("float32", None, True), ("float32", pool, False), ("float16", pool, True),
                              ("float16", None, False)):
        mv = z_state_bytes(12, Z, dtype, out, class_major=major)
        msg = schema.ZState.FromString(bytes(mv))
        stored = Z if dtype == "float32" else (Z / Z.max()).astype("<f2")
        data = (stored.T if major else stored).tobytes()
        expect = schema.ZState(iteration=12, n_points=50, n_classes=7, dtype=dtype, data=data, scale=msg.scale,
                               class_major=major)
        assert bytes(mv) == expect.SerializeToString()
        assert msg.scale == (1.0 if dtype == "float32" else pytest.approx(float(Z.max())))
        Zd = decode_z(msg)
        assert Zd.shape == Z.shape and Zd.flags.c_contiguous
        if dtype == "float32":
            np.testing.assert_array_equal(Zd, Z)
        else:
            np.testing.assert_allclose(Zd, Z, rtol=1e-3, atol=1e-3 * Z.max())
    empty = schema.ZState.FromString(bytes(z_state_bytes(3, np.zeros((0, 4), np.float32), "float32")))
    assert (empty.iteration, empty.n_points, empty.n_classes, empty.data) == (3, 0, 4, b"")


def test_point_cloud_bytes_is_the_protobuf_serialisation():
    from diffuser_lab.recording.mcap_encode import _cloud_dtype, point_cloud, point_cloud_bytes

    buf = np.zeros(300, _cloud_dtype())
    buf["x"], buf["label"], buf["red"] = np.arange(300) * 0.5, np.arange(300) % 7 - 1, 200
    pool = bytearray(100_000)
    for out in (None, pool, bytearray(10)):  # new, reused (larger), too small (replaced)
        assert bytes(point_cloud_bytes(buf, 1_234_567_890_123, out)) == \
            point_cloud(buf, 1_234_567_890_123).SerializeToString()
    assert bytes(point_cloud_bytes(buf[:0], 5)) == point_cloud(buf[:0], 5).SerializeToString()


def test_float16_and_voxel_grid(small_demo_scene, tmp_path):
    cfg = default_config(**{"solver.max_iter": 30, "scene.voxel_size": 0.12, "record.z_precision": "float16",
                            "record.interval": 7})
    res, _ = recorded(cfg, small_demo_scene, tmp_path)
    log = read_run(tmp_path / "run.mcap", z="last")
    assert log.z_iterations == [1, 7, 14, 21, 28, 30]
    Z, Zs = log.z[30], res.diffusion.Z
    assert Z.shape == Zs.shape == (res.work_points.shape[0], small_demo_scene.taxonomy.num_classes)
    assert Z.shape[0] < small_demo_scene.n_points and log.info.original_to_work  # transfer indices stored
    np.testing.assert_allclose(Z, Zs, rtol=2e-3, atol=2e-3 * Zs.max())
    assert np.mean(labels_from_scores(Z) == labels_from_scores(Zs)) > 0.99
    # mIoU so far is scored on the original points: the last equals the run's
    assert log.metrics[-1]["miou"] == pytest.approx(res.metrics["miou"], abs=1e-9)
    ids = rrd_class_ids(tmp_path / "run.rrd")
    np.testing.assert_array_equal(ids[30], as_class_ids(labels_from_scores(Zs)))  # work cloud


@pytest.mark.slow
def test_rrd_reads_back_with_rerun_and_holds_class_ids_per_iteration(cli_runs):
    d = cli_runs["both"]
    ids = rrd_class_ids(d / "run.rrd")
    assert sorted(ids) == [1, 2, 5, 10, 20, 50, 60]
    np.testing.assert_array_equal(ids[60], as_class_ids(np.load(d / "labels.npy")))
    assert not np.array_equal(ids[1], ids[60])  # the labels spread
    from rerun.chunk import RrdReader

    reader = RrdReader(d / "run.rrd")
    assert reader.recordings() and reader.blueprints()  # a default blueprint ships with the data
    paths = {ch.entity_path for ch in reader.stream()}
    assert {"/world", "/world/scene/points", "/world/scene/ground_truth", "/world/cameras/0000",
            "/world/depth/0000", "/world/cameras/0000/labels", "/world/evidence/bayesian",
            "/world/diffusion/confidence", "/world/diffusion/wrong", "/metrics/miou",
            "/metrics/residual_log10", "/metrics/changed_per_iter_log10"} <= paths
    p = subprocess.run([RERUN, "rrd", "verify", str(d / "run.rrd")], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    depth = next(ch for ch in reader.stream() if ch.entity_path == "/world/depth/0000").to_record_batch()
    assert depth.column("DepthImage:meter").to_pylist() == [[1000.0]]  # uint16 millimetres
    cam = next(ch for ch in reader.stream() if ch.entity_path == "/world/cameras/0000").to_record_batch()
    assert {"Pinhole:image_from_camera", "Pinhole:resolution", "Transform3D:mat3x3",
            "Transform3D:translation"} <= set(cam.schema.names)


def test_depth_mm():
    from diffuser_lab.recording.rerun_log import depth_mm

    d = np.array([[0.0, 1.2344, 1.2346, np.nan], [-1.0, np.inf, 65.535, 70.0]], np.float32)
    out = depth_mm(d)
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, [[0, 1234, 1235, 0], [0, 0, 65535, 0]])


@pytest.mark.slow
def test_rerun_reads_the_mcap(cli_runs):
    path = cli_runs["both"] / "run.mcap"
    p = subprocess.run([RERUN, "mcap", "info", str(path)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert "/diffuser_lab/z" in p.stdout and "diffuser_lab.ZState" in p.stdout and "zstd" in p.stdout
    from rerun.chunk import McapReader

    cols: dict = {}
    for ch in McapReader(path).stream():
        cols.setdefault(ch.entity_path, set()).update(ch.to_record_batch().schema.names)
    # the foxglove PointCloud becomes Rerun points; our protobuf messages decode by reflection
    assert "Points3D:positions" in cols["/diffusion/labels"] and "Points3D:colors" in cols["/diffusion/labels"]
    assert any("IterationMetrics" in c for c in cols["/diffuser_lab/metrics"])


@pytest.mark.slow
def test_schema_in_the_file_decodes_without_this_package(cli_runs):
    """What another tool does: build the message class from the schema record alone."""
    from google.protobuf import descriptor_pb2, descriptor_pool
    from google.protobuf.message_factory import GetMessageClass
    from mcap.reader import make_reader

    with open(cli_runs["both"] / "run.mcap", "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages(topics=[TOPIC_Z]):
            assert schema.encoding == "protobuf" and channel.message_encoding == "protobuf"
            pool = descriptor_pool.DescriptorPool()
            for f in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
                pool.Add(f)
            msg = GetMessageClass(pool.FindMessageTypeByName(schema.name)).FromString(message.data)
            assert msg.dtype == "q8" and msg.class_major  # an intermediate state: row sums x 8-bit shares
            shares = np.frombuffer(msg.data, "u1").reshape(msg.n_classes, msg.n_points).T
            Z = shares * (np.frombuffer(msg.row_sums, "<f4") / 255.0)[:, None]
            assert Z.shape[1] == 20 and (Z.sum(1) > 0).any()
            labels = np.frombuffer(msg.labels, "<i2")
            assert labels.shape == (msg.n_points,) and (labels[Z.sum(1) > 0] >= 0).all()
            break
        else:
            pytest.fail("no Z message")


@pytest.mark.slow
def test_truncated_mcap_gives_its_leading_iterations_with_a_warning(cli_runs, tmp_path, capsys):
    full = cli_runs["both"] / "run.mcap"
    cut = tmp_path / "run.mcap"
    data = full.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    assert inspect_main([str(tmp_path)]) == 0
    out, err = capsys.readouterr()
    assert "warning" in err and "truncated" in err
    assert "TRUNCATED" in out and "did not finish" in out
    log_full, log_cut = read_run(full, z="all"), read_run(cut, z="all")
    assert log_cut.truncated and 0 < len(log_cut.z_iterations) < len(log_full.z_iterations)
    assert log_cut.z_iterations == log_full.z_iterations[: len(log_cut.z_iterations)]
    for it in log_cut.z_iterations:
        np.testing.assert_array_equal(log_cut.z[it], log_full.z[it])
        assert f"\n{it:6d}  " in out  # a table row per complete iteration
    last = log_cut.z_iterations[-1]
    assert inspect_main([str(cut), "--at", "last", "--out", str(tmp_path / "z.npy")]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "z.npy"), log_full.z[last])


@pytest.mark.slow
def test_inspect_summary_table_and_z(cli_runs, tmp_path, capsys):
    d = cli_runs["both"]
    assert inspect_main([str(d)]) == 0
    out = capsys.readouterr().out
    assert "demo_room_seed0" in out and "method diffuser" in out and "7 iterations" in out
    assert "mIoU" in out and "residual" in out and "changed" in out and "wall, floor" in out
    assert inspect_main([str(d / "run.mcap"), "--at", "20", "--out", str(tmp_path / "z.npy")]) == 0
    z20 = np.load(tmp_path / "z.npy")
    np.testing.assert_array_equal(z20, read_run(d / "run.mcap", z=[20]).z[20])
    capsys.readouterr()
    assert inspect_main([str(d), "--at", "15"]) == 2
    assert "not recorded" in capsys.readouterr().err
    assert inspect_main([str(tmp_path / "nothing")]) == 2


@pytest.mark.slow
def test_to_rrd_relogs_the_run_from_its_mcap_alone(cli_runs, tmp_path):
    src = cli_runs["both"]
    only = tmp_path / "mcap_only"
    only.mkdir()
    shutil.copy(src / "run.mcap", only / "run.mcap")
    out = tmp_path / "replay.rrd"
    assert inspect_main([str(only), "--to-rrd", str(out)]) == 0
    live, replay = rrd_class_ids(src / "run.rrd"), rrd_class_ids(out)
    assert sorted(live) == sorted(replay)
    for it in live:
        np.testing.assert_array_equal(live[it], replay[it])


@pytest.mark.slow
def test_record_off_writes_nothing_and_labels_match(cli_runs):
    off, both = cli_runs["off"], cli_runs["both"]
    assert not (off / "run.rrd").exists() and not (off / "run.mcap").exists()
    assert json.loads((off / "summary.json").read_text())["records"] == {}
    np.testing.assert_array_equal(np.load(off / "labels.npy"), np.load(both / "labels.npy"))


@pytest.mark.parametrize("method", ["bayesian", "direct"])
def test_methods_without_diffusion_record_the_static_part(method, small_demo_scene, tmp_path, capsys):
    cfg = default_config(**{"method.name": method})
    res, hooks = recorded(cfg, small_demo_scene, tmp_path)
    assert hooks.files() == {"rrd": "run.rrd", "mcap": "run.mcap"} and hooks.recorded == []
    log = read_run(tmp_path / "run.mcap")
    assert log.complete and log.z_iterations == [] and log.info.n_work_points == small_demo_scene.n_points
    assert rrd_class_ids(tmp_path / "run.rrd") == {}
    assert inspect_main([str(tmp_path)]) == 0
    assert "no diffusion" in capsys.readouterr().out


def test_a_failing_recorder_is_switched_off_and_the_run_goes_on(small_demo_scene, tmp_path, monkeypatch, caplog):
    from diffuser_lab.recording import mcap_write

    def boom(self, step, final=False):
        raise OSError("disk full")

    monkeypatch.setattr(mcap_write.McapRecorder, "log_step", boom)
    cfg = default_config(**{"solver.max_iter": 20})
    res, hooks = recorded(cfg, small_demo_scene, tmp_path)
    files = hooks.files()
    assert files["rrd"] == "run.rrd" and "mcap" not in files and "disk full" in files["errors"]["mcap"]
    assert sorted(rrd_class_ids(tmp_path / "run.rrd")) == [1, 2, 5, 10, 20]
    plain = run(cfg, scene=small_demo_scene)
    np.testing.assert_array_equal(res.labels, plain.labels)


def test_make_hooks_off_is_harmless(tmp_path):
    hooks = make_hooks(default_config(**{"record.mode": "off"}), tmp_path / "x")
    assert hooks.files() == {} and not hooks.wants(1)
    hooks.close()
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_view_opens_the_rrd_or_a_relogged_mcap(cli_runs, tmp_path, monkeypatch):
    from diffuser_lab.cli import inspect as inspect_run

    calls = []
    monkeypatch.setattr(inspect_run.subprocess, "call", lambda cmd: calls.append(cmd) or 0)
    assert inspect_main([str(cli_runs["both"]), "--view"]) == 0
    assert calls[-1][-1] == str(cli_runs["both"] / "run.rrd") and calls[-1][0].endswith("rerun")
    only = tmp_path / "mcap_only"
    only.mkdir()
    shutil.copy(cli_runs["both"] / "run.mcap", only / "run.mcap")
    assert inspect_main([str(only), "--view"]) == 0
    assert calls[-1][-1].endswith("replay.rrd") and Path(calls[-1][-1]).is_file()


def test_iterations_are_recorded_while_the_recorders_are_still_opening(small_demo_scene, tmp_path, monkeypatch):
    """The recorders open on the recording thread; a diffusion that starts before they are
    open still gets every configured iteration recorded (they are queued, not skipped)."""
    import time

    from diffuser_lab.recording.recorders import Recorders

    slow_open = Recorders._open_mcap
    monkeypatch.setattr(Recorders, "_open_mcap", lambda self, ov: (time.sleep(1.0), slow_open(self, ov)))
    cfg = default_config(**{"solver.max_iter": 30, "record.interval": 10, "record.mode": "mcap"})
    res, hooks = recorded(cfg, small_demo_scene, tmp_path)
    assert hooks.recorded == [1, 10, 20, 30]
    log = read_run(tmp_path / "run.mcap", z="last")
    assert log.z_iterations == [1, 10, 20, 30]
    np.testing.assert_array_equal(log.z[30], res.diffusion.Z)
