"""What the default record keeps (issue 19): the 1-2-5 schedule, intermediate Z in 8-bit row
shares within their stated error, the run's own labels beside them, the last Z exact, and at most
300 recorded bytes (run.rrd + run.mcap) per diffused point. Wall-time ratios: the benchmark
tests/benchmarks/test_recording_budget.py."""
import json

import numpy as np
import pytest
from conftest import SHARED, run_cli

from diffuser_lab.cli.inspect import main as inspect_main
from diffuser_lab.config import default_config
from diffuser_lab.hooks import RunHooks
from diffuser_lab.method.diffusion import labels_from_scores
from diffuser_lab.recording import make_hooks
from diffuser_lab.recording.mcap_read import read_run
from diffuser_lab.recording.schedule import recorded, schedule, with_cloud
from diffuser_lab.runs.pipeline import run

BUDGET = 300  # recorded bytes per diffused point
SCANNET = SHARED / "data" / "scannet" / "scene0470_00" / "scene0470_00_vh_clean_2.labels.ply"


def test_schedule():
    assert schedule(200) == [1, 2, 5, 10, 20, 50, 100, 200]
    assert schedule(1000) == [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000]
    assert schedule(7) == [1, 2, 5, 7]
    assert schedule(45, 10) == [1, 10, 20, 30, 40, 45]
    assert not recorded(3, None, 200) and recorded(3, 3, 200) and recorded(200, None, 200)
    assert len(schedule(100_000)) == 16  # grows with the log of the iterations
    clouds = [i for i in schedule(2000) if with_cloud(i, "decades", i == 2000)]
    assert clouds == [100, 1000, 2000]
    assert all(with_cloud(i, "all", False) for i in schedule(200))


@pytest.mark.parametrize("compiled", [True, False])
def test_shares_round_trip_within_the_stated_error(compiled, monkeypatch):
    from diffuser_lab.backends import numba as nb
    from diffuser_lab.recording import schema
    from diffuser_lab.recording.mcap_encode import decode_z, z_precision_text, z_state_bytes

    if compiled and not nb.available():
        pytest.skip("numba not importable")
    if not compiled:
        monkeypatch.setattr(nb, "available", lambda: False)
    rng = np.random.default_rng(1)
    # scores over many magnitudes, some rows all zero (points nothing reached)
    Z = (rng.random((5000, 20)) ** 4 * 10.0 ** rng.uniform(-8, 0, (5000, 1))).astype(np.float32)
    Z[::17] = 0
    labels = labels_from_scores(Z)
    for dtype, levels in (("q8", 255), ("q16", 65535)):
        msg = schema.ZState.FromString(bytes(z_state_bytes(7, Z, dtype, labels=labels)))
        assert msg.dtype == dtype and msg.iteration == 7
        Zd = decode_z(msg)
        rows = Z.sum(1, dtype=np.float64)
        err = np.abs(Zd.astype(np.float64) - Z).max(1)
        # half a step of the row's sum, plus float32 rounding of the product
        assert (err <= rows * (0.5 / levels + 1e-6)).all(), dtype
        assert (Zd[::17] == 0).all()
        np.testing.assert_array_equal(np.frombuffer(msg.labels, "<i2"), labels)  # the exact Z's labels
        assert f"1/{levels} steps" in z_precision_text(dtype)
    exact = schema.ZState.FromString(bytes(z_state_bytes(9, Z, "float32", labels=labels)))
    np.testing.assert_array_equal(decode_z(exact), Z)
    assert exact.labels == b""  # exact states carry no labels: they are Z's argmax


class _Copies(RunHooks):
    def __init__(self, interval=None, max_iter=0):
        self.z, self.interval, self.max_iter = {}, interval, max_iter

    def wants(self, it):
        return recorded(it, self.interval, self.max_iter)

    def observe(self, it, Z, stats):
        self.z[it] = np.array(Z)


def test_default_record_intermediate_q8_last_exact(small_demo_scene, tmp_path):
    cfg = default_config(**{"solver.max_iter": 60})
    copies = _Copies(max_iter=60)
    run(cfg, scene=small_demo_scene, hooks=copies)
    hooks = make_hooks(cfg, tmp_path)
    try:
        res = run(cfg, scene=small_demo_scene, hooks=hooks)
    finally:
        hooks.close()
    log = read_run(tmp_path / "run.mcap", z="all")
    assert log.z_iterations == sorted(copies.z) == [1, 2, 5, 10, 20, 50, 60]
    for it in log.z_iterations[:-1]:
        Z = copies.z[it]
        assert log.z_dtype[it] == "q8"
        err = np.abs(log.z[it].astype(np.float64) - Z).max(1)
        assert (err <= Z.sum(1, dtype=np.float64) * (0.5 / 255 + 1e-6)).all(), it
        assert np.mean(labels_from_scores(log.z[it]) == labels_from_scores(Z)) > 0.99
    assert log.z_dtype[60] == "float32"
    np.testing.assert_array_equal(log.z[60], res.diffusion.Z)  # exactly, float32


def test_converged_on_a_recorded_iteration_keeps_the_last_z_exact(small_demo_scene, tmp_path, capsys):
    base = {"solver.max_iter": 300, "solver.tol": 0.01}
    it = run(default_config(**base), scene=small_demo_scene).diffusion.iterations
    assert it < 300
    cfg = default_config(**{**base, "record.interval": it})  # so the converged iteration is recorded
    hooks = make_hooks(cfg, tmp_path)
    try:
        res = run(cfg, scene=small_demo_scene, hooks=hooks)
    finally:
        hooks.close()
    assert res.diffusion.iterations == it and hooks.recorded == [1, it]
    log = read_run(tmp_path / "run.mcap", z="all")
    assert log.z_iterations == [1, it] and log.z_dtype[it] == "float32"  # the exact copy, written last
    np.testing.assert_array_equal(log.z[it], res.diffusion.Z)
    assert inspect_main([str(tmp_path), "--at", str(it), "--out", str(tmp_path / "z.npy")]) == 0
    assert "float32: exact" in capsys.readouterr().out
    assert inspect_main([str(tmp_path), "--at", "1"]) == 0
    assert "q8: row sums exact, shares Z_ic / sum_c Z_ic in 1/255 steps" in capsys.readouterr().out


def _bytes_per_point(run_dir) -> float:
    s = json.loads((run_dir / "summary.json").read_text())
    return ((run_dir / "run.rrd").stat().st_size + (run_dir / "run.mcap").stat().st_size) / s["n_points_diffused"]


@pytest.mark.slow
def test_demo_records_at_most_300_bytes_per_point(tmp_path):
    p = run_cli("output.quiet=true", f"hydra.run.dir={tmp_path}")  # the default demo, default record
    assert p.returncode == 0, p.stderr
    per_point = _bytes_per_point(tmp_path)
    print(f"demo: {per_point:.0f} bytes per diffused point")
    assert per_point <= BUDGET


@pytest.mark.slow
@pytest.mark.skipif(not SCANNET.is_file(), reason=f"real ScanNet data absent: {SCANNET} not found")
def test_scannet0470_records_at_most_300_bytes_per_point(tmp_path):
    p = run_cli("scene=scannet0470", "output.quiet=true", f"hydra.run.dir={tmp_path}")
    assert p.returncode == 0, p.stderr
    per_point = _bytes_per_point(tmp_path)
    print(f"scannet0470: {per_point:.0f} bytes per diffused point")
    assert per_point <= BUDGET


def _with_hooks(cfg, scene, run_dir, **kw):
    hooks = make_hooks(cfg, run_dir, **kw)
    try:
        res = run(cfg, scene=scene, hooks=hooks)
    finally:
        hooks.close()
    return res, hooks


def test_the_recording_process_writes_what_the_thread_writes(small_demo_scene, tmp_path):
    from diffuser_lab.recording.process import ProcessLane, available

    if not available():
        pytest.skip("no fork on this platform: the thread records")
    cfg = default_config(**{"solver.max_iter": 40})
    res_t, thread = _with_hooks(cfg, small_demo_scene, tmp_path / "thread")
    res_p, proc = _with_hooks(cfg, small_demo_scene, tmp_path / "process", process=True)
    assert isinstance(proc.lane, ProcessLane) and proc.files() == thread.files() == {"rrd": "run.rrd", "mcap": "run.mcap"}
    np.testing.assert_array_equal(res_t.labels, res_p.labels)
    assert proc.recorded == thread.recorded == [1, 2, 5, 10, 20, 40]
    a, b = read_run(tmp_path / "thread" / "run.mcap", z="all"), read_run(tmp_path / "process" / "run.mcap", z="all")
    assert a.z_iterations == b.z_iterations and a.metrics == b.metrics and b.summary["records"] == proc.files()
    for it in a.z_iterations:
        np.testing.assert_array_equal(a.z[it], b.z[it])
    assert (tmp_path / "process" / "run.rrd").stat().st_size > 100_000


def test_a_dead_recording_process_costs_the_records_not_the_run(small_demo_scene, tmp_path, caplog):
    from diffuser_lab.recording.process import available

    if not available():
        pytest.skip("no fork on this platform: the thread records")
    cfg = default_config(**{"solver.max_iter": 40})
    hooks = make_hooks(cfg, tmp_path, process=True)
    hooks.lane._proc.kill()  # the recorder dies (OOM killer, a crash) before the run starts
    hooks.lane._proc.join()
    try:
        res = run(cfg, scene=small_demo_scene, hooks=hooks)
    finally:
        hooks.close()
    np.testing.assert_array_equal(res.labels, run(cfg, scene=small_demo_scene).labels)
    files = hooks.files()
    assert "rrd" not in files and "mcap" not in files
    assert set(files["errors"]) == {"rerun", "mcap"} and "recording process" in files["errors"]["mcap"]
