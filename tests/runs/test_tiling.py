"""protocol=tiled (diffuser_lab/runs/tiled.py): the global pipeline per x-y tile equals the untiled run;
a tile reads the frames that see it; tiles on a two-node Ray cluster; resume; the memory refusal."""
import dataclasses
import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from diffuser_lab.backends import provenance
from diffuser_lab.config import default_config
from diffuser_lab.data import validate
from diffuser_lab.data.frames import LazyFrames
from diffuser_lab.data.predictions import with_predictions
from diffuser_lab.method import evidence as evidence_mod
from diffuser_lab.method.graph import nearest_distinct
from diffuser_lab.runs import pipeline, tiled
from diffuser_lab.runs.tiled import TileSpec, frames_meeting, tile_points
from conftest import ROOT, SMALL_DEMO, check_provenance, run_cli

SMALL = {"scene.options.n_views": 12, "scene.options.point_spacing": 0.07, "solver.max_iter": 60}
TILED = {**SMALL, "protocol.name": "tiled", "tiling.size": 1.9}  # a 3x3 grid of 1.67 m (the room is 5.01 x 4.01 m)


@pytest.fixture(scope="module")
def untiled():
    return pipeline.run(default_config(**SMALL))


@pytest.fixture(scope="module")
def local_tiled(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("tiled")
    return tiled.tiled(default_config(**TILED), run_dir=run_dir), run_dir


def test_tiled_labels_equal_the_untiled_run(untiled, local_tiled):
    res, _ = local_tiled
    assert res.grid == (3, 3) and not res.failed
    assert (res.labels == untiled.labels).mean() >= 0.999
    np.testing.assert_array_equal(res.bayesian_labels, untiled.bayesian_labels)  # the same evidence per point
    assert res.metrics["miou"] == pytest.approx(untiled.metrics["miou"], abs=0.2)
    assert sum(r["points"] for r in res.tiles) == untiled.scene.n_points
    # rho tile by tile is the untiled graph's; the default halo is halo_factor * sigma_d, in metres
    assert res.rho == pytest.approx(untiled.graph.rho, rel=1e-9)
    cfg = default_config(**TILED)
    assert cfg.tiling.halo is None and res.halo == pytest.approx(cfg.tiling.halo_factor * untiled.graph.sigma_d)


def test_the_spacing_tile_by_tile_is_the_whole_clouds():
    """rho from the tiles' own points, the points near a cell's border looked up again beyond it,
    equals the whole cloud's (duplicates and a lone point in a cell included)."""
    rng = np.random.default_rng(5)
    pts = (rng.random((20_000, 3)) * [9.0, 5.0, 2.0]).astype(np.float32)
    pts[:40] = pts[40:80]  # duplicates
    pts[-1] = [8.99, 4.99, 1.0]  # alone near a corner cell's edge
    for size in (0.5, 2.0):
        cells = tiled.Cells(pts, size)
        d = nearest_distinct(pts, 24)
        assert cells.spacing(pts, 24) == pytest.approx(d[np.isfinite(d)].mean(), rel=1e-9)


@pytest.mark.parametrize("halo", [0.0, 0.3, 2.5])
def test_a_tiles_rows_from_its_neighbouring_cells_are_the_brute_force_ones(halo):
    rng = np.random.default_rng(3)
    pts = (rng.random((20_000, 3)) * [9.0, 5.0, 2.0]).astype(np.float32)
    pts[:50, 0] = np.float32(2.0)  # on a cell edge
    cells = tiled.Cells(pts, 2.0)
    assert cells.shape == (5, 3) and sum(o.size for o in cells.owns.values()) == len(pts)
    for ix, iy in cells.owns:
        spec = TileSpec(ix, iy, cells.origin, cells.size, halo)
        own, rows = tile_points(pts, spec)
        np.testing.assert_array_equal(cells.owns[(ix, iy)], own)
        np.testing.assert_array_equal(cells.rows(pts, spec), rows)


def test_the_grid_is_fitted_to_the_cloud():
    """tiling.size is the largest edge (up to GRID_SLACK more): the grid keeps ceil(extent / size) cells an axis, the edge
    shrunk so that they just cover the cloud (no near-empty last row or column, as a 130 m city cut
    into 60 m tiles had: 10 m of points in its last column)."""
    rng = np.random.default_rng(0)
    pts = (rng.random((60_000, 3)) * [130.0, 70.0, 20.0]).astype(np.float32)
    cells = tiled.Cells(pts, 60.0)
    assert cells.shape == (3, 2) and 43.2 < cells.size <= 130.0 / 3 * (1 + 1e-6)
    counts = np.array([o.size for o in cells.owns.values()])
    assert len(counts) == 6 and counts.min() >= 0.6 * counts.mean(), counts  # at 60 m: 3 of 6 cells ~1/6 full
    origin, shape, cell = tiled.tile_grid(pts, 60.0)
    assert shape == cells.shape and cell.max(0).tolist() == [2, 1]  # the farthest point in the last cell
    # a cloud over a whole number of tiles by less than GRID_SLACK of tiling.size keeps that number:
    # the 3x3 city at 0.1 m (181.9 m) gets 3 x 60.63 m, not 4 x 45.5 m (borders in its buildings)
    city = np.array([[0, 0, 0], [181.89, 121.26, 0]], np.float32)
    assert tiled.tile_grid(city, 60.0)[1] == (3, 2)
    assert tiled.fitted_edge(city, 60.0) == pytest.approx(60.63, abs=1e-3) and 60.63 <= 60.0 * (1 + tiled.GRID_SLACK)
    assert tiled.tile_grid(city, 57.0)[1] == (4, 3)  # 3.19 x 57 m: a fourth column
    square = np.array([[0, 0, 0], [4, 4, 0]], np.float32)
    assert tiled.fitted_edge(square, 2.0) == 2.0 and tiled.fitted_edge(square, 3.0) == pytest.approx(2.0)


def test_a_frame_has_the_same_predictions_in_a_tile(untiled):
    cfg = default_config(**SMALL)
    frames, tax = untiled.scene.frames, untiled.scene.taxonomy
    whole = with_predictions(frames, cfg.predictions, tax)
    keep = [7, 2, 9]
    part = with_predictions(LazyFrames.subset(frames, keep), cfg.predictions, tax)
    for i, k in enumerate(keep):
        np.testing.assert_array_equal(part[i].labels, whole[k].labels)


def test_a_tile_reads_the_frames_that_see_it(untiled, local_tiled):
    """Every frame into which a tile's point (or halo point) projects, in front of the camera, is
    read by the tile (its ``frames_read``) (brute force: all points into all frames); the evidence its points get from
    the frames it reads is the evidence of all frames."""
    res, _ = local_tiled
    scene, cfg = untiled.scene, default_config(**TILED)
    preds = with_predictions(scene.frames, cfg.predictions, scene.taxonomy)
    extra = reads = 0
    for rec in res.tiles:
        ix, iy = map(int, rec["id"].split("_"))
        spec = TileSpec(ix, iy, tuple(scene.points[:, :2].min(0).astype(float)), res.tile_m, res.halo)
        _, rows = tile_points(scene.points, spec)
        p = scene.points[rows].astype(np.float64)
        sees = []
        for i, f in enumerate(scene.frames):
            X = p @ f.T_cw[:3, :3].T + f.T_cw[:3, 3]
            z = X[:, 2]
            u = X @ f.K[0] / np.where(z > 0, z, 1)
            v = X @ f.K[1] / np.where(z > 0, z, 1)
            h, w = f.shape
            if np.any((z > 0) & (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)):
                sees.append(i)
        box = np.stack([p.min(0), p.max(0)])[None]
        margin = cfg.evidence.pixel_radius + 1.0
        read = [i for i, f in enumerate(scene.frames) if frames_meeting(box, f.K, f.T_cw, f.shape, margin)[0]]
        assert set(sees) <= set(read) and rec["frames_read"] == len(read)
        extra += len(read) - len(sees)
        reads += len(read)
        mine = evidence_mod.accumulate(p.astype(np.float32), [preds[i] for i in read], scene.taxonomy.num_classes,
                                       depth_tol=cfg.evidence.depth_tol, pixel_radius=cfg.evidence.pixel_radius)
        np.testing.assert_array_equal(mine.mass, untiled.evidence.mass[rows])
    # the box test (the tile's box against each view's pyramid) reads some frames that see none of
    # the tile's points (21 of 95 here: a room's tile boxes span floor to ceiling); never one too few
    assert extra <= 0.3 * reads


def test_resume_keeps_finished_tiles_and_redoes_damaged_ones(local_tiled, tmp_path):
    res, run_dir = local_tiled
    files = sorted((run_dir / "tiles").glob("*.npz"))
    assert len(files) == len(res.tiles)
    kept, damaged, missing = files[0], files[1], files[2]
    before = {f.name: os.stat(f).st_mtime_ns for f in files}
    damaged.write_bytes(damaged.read_bytes()[:100])  # a half-written file
    missing.unlink()
    again = tiled.tiled(default_config(**TILED, **{"tiling.resume": str(run_dir)}), run_dir=tmp_path)
    np.testing.assert_array_equal(again.labels, res.labels)
    assert os.stat(kept).st_mtime_ns == before[kept.name]
    assert os.stat(damaged).st_mtime_ns != before[damaged.name] and missing.is_file()
    status = {r["id"]: r["status"] for r in again.tiles}
    assert status[kept.stem] == "resumed" and status[damaged.stem] == status[missing.stem] == "done"
    assert not (tmp_path / "tiles").exists()  # the tiles stay in the resumed folder


def test_a_tile_from_another_machine_is_named(local_tiled, tmp_path):
    """Each tile keeps the provenance of the process that computed it: a tile resumed from a run on
    another machine (here: its record's CPU and numpy version rewritten) is listed apart."""
    import shutil

    res, run_dir = local_tiled
    here = provenance.collect()
    assert [m["tiles"] for m in res.machines] == [[r["id"] for r in res.tiles]]
    assert res.machines[0]["differs"] == [] and "provenance" not in res.machines[0]
    assert all(r["machine"] == provenance.key(here) and "provenance" not in r for r in res.tiles)
    shutil.copytree(run_dir / "tiles", tmp_path / "earlier" / "tiles")
    path = tmp_path / "earlier" / "tiles" / f"{res.tiles[0]['id']}.npz"
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    rec = json.loads(str(arrays["record"]))
    check_provenance(rec["provenance"])
    rec["provenance"]["machine"]["cpu_model"] = "AMD EPYC 7742 64-Core Processor"
    rec["provenance"]["versions"]["numpy"] = "1.26.4"
    arrays["record"] = np.array(json.dumps(rec))
    np.savez(path, **arrays)
    again = tiled.tiled(default_config(**TILED, **{"tiling.resume": str(tmp_path / "earlier")}),
                        run_dir=tmp_path / "again")
    other = [m for m in again.machines if m["differs"]]
    assert len(again.machines) == 2 and len(other) == 1
    assert other[0]["tiles"] == [res.tiles[0]["id"]] and other[0]["differs"] == ["CPU", "numpy"]
    assert other[0]["provenance"]["machine"]["cpu_model"] == "AMD EPYC 7742 64-Core Processor"
    assert f"1 tile ran on another machine or versions ({here['host']}: CPU, numpy differ)" in \
        tiled.table(again, tmp_path / "again")
    assert tiled.summary(again, default_config(**TILED))["tiling"]["machines"] == again.machines


def test_resume_with_another_config_is_refused(local_tiled, tmp_path):
    _, run_dir = local_tiled
    with pytest.raises(ValueError, match="another config"):
        tiled.tiled(default_config(**TILED, **{"tiling.resume": str(run_dir), "tiling.halo": 0.1}), run_dir=tmp_path)


def _budget_failing_the_largest_tile(res, k=24, classes=20):
    need = sorted(validate.estimate_memory(r["points_with_halo"], r["points_with_halo"], classes, k)
                  for r in res.tiles)
    return (need[-1] + need[-2]) / 2 / validate.GIB


def test_a_failing_tile_is_reported_and_the_others_kept(untiled, tmp_path):
    # a halo narrower than the tiles (the default, 30 sigma_d, is 2.1 m on this coarse room): tiles of different sizes
    cfg = {**TILED, "tiling.halo": 0.75}
    res = tiled.tiled(default_config(**cfg), run_dir=tmp_path / "all")
    budget = _budget_failing_the_largest_tile(res)
    out = tiled.tiled(default_config(**cfg, memory_budget_gb=budget), run_dir=tmp_path)
    assert len(out.failed) == 1 and out.failed[0]["error"].startswith("MemoryError: this run needs about")
    bad = out.failed[0]["id"]
    assert not (tmp_path / "tiles" / f"{bad}.npz").exists()
    ok = out.labels != -1
    lost = (res.labels != -1) & ~ok  # labelled by the complete run, not by this one: the failed tile's
    n_bad, unseen = out.failed[0]["points"], int((res.labels == -1).sum())  # unseen: no evidence reaches them
    assert (out.labels[ok] == res.labels[ok]).all() and n_bad - unseen <= lost.sum() <= n_bad
    assert f"tile {bad} failed: MemoryError" in tiled.table(out, tmp_path)


@pytest.mark.slow
def test_the_command_line_writes_the_tiles_and_their_records(tmp_path):
    p = run_cli(*SMALL_DEMO, "protocol=tiled", "record=off", "output.labels_ply=false", f"hydra.run.dir={tmp_path}")
    assert p.returncode == 0, p.stderr
    # the default 2 m: 3 columns, and 2 rows of 2.007 m for the room's 4.014 m (GRID_SLACK), not 3 of 1.34 m
    assert "tiled 3x2 grid, 6 tiles" in p.stdout and "tiles: 6 of 6 done" in p.stdout
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["status"] == "ok" and s["protocol"] == "tiled" and s["tiling"]["grid"] == [3, 2]
    rec = s["tiling"]["tiles"][0]
    assert {"id", "points", "frames_read", "iterations", "time_s", "node", "pid", "status", "machine"} <= set(rec)
    check_provenance(s["provenance"])  # tiles in this process: one machine, the run's
    assert s["tiling"]["machines"] == [{"machine": provenance.key(s["provenance"]), "tiles": [t["id"] for t in
                                        s["tiling"]["tiles"]], "nodes": [rec["node"]], "differs": []}]
    assert len(list((tmp_path / "tiles").glob("*.npz"))) == 6 and (tmp_path / "labels.npy").is_file()


def test_memory_refusal_names_the_tiling_keys():
    with pytest.raises(MemoryError) as err:
        validate.check_memory(3_000_000, 3_000_000, 20, 24, 1.0)
    msg = str(err.value)
    assert "\n" not in msg and "protocol=tiled tiling.size=" in msg and "this run needs about" in msg
    with pytest.raises(MemoryError, match=r"memory_budget_gb=0.01; .* protocol=tiled tiling.size=<metres> \(at least"):
        pipeline.run(default_config(**SMALL, memory_budget_gb=0.01))  # refused before the frames are read


@pytest.fixture(scope="module")
def cluster():
    ray = pytest.importorskip("ray")
    from ray.cluster_utils import Cluster

    c = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    c.add_node(num_cpus=1)
    c.wait_for_nodes()
    yield c
    if ray.is_initialized():
        ray.shutdown()
    c.shutdown()


@pytest.mark.slow  # ~40 s with the cluster's start
def test_tiles_on_a_two_node_ray_cluster(cluster, local_tiled, tmp_path):
    res, _ = local_tiled
    cfg = default_config(**TILED, **{"tiling.address": cluster.address, "tiling.max_retries": 1})
    out = tiled.tiled(cfg, run_dir=tmp_path / "a")
    np.testing.assert_array_equal(out.labels, res.labels)
    assert {r["status"] for r in out.tiles} == {"done"} and len({r["pid"] for r in out.tiles}) >= 2
    # each worker collected its own provenance (both "nodes" are this machine: the same block)
    assert [m["tiles"] for m in out.machines] == [[r["id"] for r in out.tiles]] and out.machines[0]["differs"] == []
    # each task read its tile's points from tiles/inputs/<id>.npz, removed once the tile was done
    assert (tmp_path / "a" / "tiles" / "inputs").is_dir() and not list((tmp_path / "a" / "tiles" / "inputs").iterdir())
    # a tile that fails (its memory estimate over the budget) is retried, then reported; the others are kept
    # (a halo narrower than the default's 2.1 m on this coarse room: tiles of different sizes)
    narrow = dataclasses.replace(cfg, tiling=dataclasses.replace(cfg.tiling, halo=0.75))
    ref = tiled.tiled(narrow, run_dir=tmp_path / "c")
    bad = dataclasses.replace(narrow, memory_budget_gb=_budget_failing_the_largest_tile(ref))
    out = tiled.tiled(bad, run_dir=tmp_path / "b")
    assert len(out.failed) == 1 and "MemoryError" in out.failed[0]["error"]
    ok = out.labels != -1
    assert (out.labels[ok] == ref.labels[ok]).all()


@pytest.mark.slow
def test_a_ray_worker_killed_mid_tile_is_retried_and_the_labels_equal(tmp_path):
    """SIGKILL to the Ray worker while it runs a tile (its process title ray::_ray_tile): Ray runs the
    task again (tiling.max_retries), the run ends done with labels equal to an undisturbed run's."""
    pytest.importorskip("ray")
    psutil = pytest.importorskip("psutil")
    args = [sys.executable, "-m", "diffuser_lab", "scene.options.n_views=10", "scene.options.point_spacing=0.08",
            "solver.max_iter=500", "solver.tol=0", "protocol=tiled", "tiling.size=1.5", "record=off",
            "output.labels_ply=false"]  # 500 steps, no early stop: a tile lasts ~0.2 s, long enough to be caught running
    # its own local Ray (RAY_ADDRESS of another test's cluster would send the tasks there)
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR" and not k.startswith("RAY_")}
    proc = subprocess.Popen([*args, "tiling.workers=1", f"hydra.run.dir={tmp_path / 'ray'}"], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    killed = None
    deadline = time.time() + 180
    while killed is None and proc.poll() is None and time.time() < deadline:
        for c in psutil.Process(proc.pid).children(recursive=True):  # loop over the run's processes
            try:
                if "ray::_ray_tile" in " ".join(c.cmdline()):
                    c.kill()
                    killed = c.pid
                    break
            except psutil.Error:
                pass
        time.sleep(0.005)
    _, err = proc.communicate(timeout=300)
    assert killed is not None, f"no worker was seen running a tile (exit {proc.returncode}: {err[-800:]})"
    ref = subprocess.run([*args, f"hydra.run.dir={tmp_path / 'ref'}"], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=300)
    assert proc.returncode == 0 and ref.returncode == 0, err + ref.stderr
    s = json.loads((tmp_path / "ray" / "summary.json").read_text())
    assert s["tiling"]["failed"] == 0 and all(t["status"] == "done" for t in s["tiling"]["tiles"])
    assert all(t["pid"] != killed for t in s["tiling"]["tiles"])  # the killed task's tile ran again elsewhere
    np.testing.assert_array_equal(np.load(tmp_path / "ray" / "labels.npy"), np.load(tmp_path / "ref" / "labels.npy"))


def test_a_point_its_tile_left_unlabelled_takes_a_neighbours_halo_label():
    """fill_from_halos: an unlabelled point takes the label of the first tile that labelled it in its
    halo; a labelled point keeps its own; a halo's unlabelled entries are never there to give."""
    from diffuser_lab.runs.tiled import fill_from_halos

    from diffuser_lab.data.scene import IGNORE

    labels = np.array([3, IGNORE, IGNORE, 5, IGNORE], np.int16)
    halos = [(np.array([1, 3]), np.array([7, 9], np.int16)), (np.array([1, 2]), np.array([8, 4], np.int16))]
    kept = labels.copy()
    assert fill_from_halos(labels, halos) == 2
    assert labels.tolist() == [3, 7, 4, 5, IGNORE]
    assert fill_from_halos(kept, halos, done=np.array([1, 0, 1, 1, 1], bool)) == 1  # point 1's tile failed
    assert kept.tolist() == [3, IGNORE, 4, 5, IGNORE]
