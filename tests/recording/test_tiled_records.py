"""Records of a tiled run (diffuser_lab/recording/tiled.py): run.rrd and run.mcap hold the final
labels (thinned for display), the tiles' figures and their boxes by status; record=off writes
neither and gives the same labels; diffuser-lab-inspect lists the tiles."""
import dataclasses
import json

import numpy as np
import pytest

from diffuser_lab.cli import inspect
from diffuser_lab.recording import record_result
from diffuser_lab.recording import tiled as rec_tiled
from diffuser_lab.recording.mcap_encode import TOPIC_SCENE, TOPIC_TILED_LABELS, TOPIC_TILED_RECORDS, decode_point_cloud
from diffuser_lab.recording.mcap_read import RunLog, iter_run
from diffuser_lab.recording.rerun_log import UNLABELED_ID
from diffuser_lab.runs import report
from diffuser_lab.runs.protocols import PROTOCOLS
from conftest import compose, run_cli

ARGS = ["protocol=tiled", "tiling.size=1.9",  # a 3x3 grid of 1.67 m
        "scene.options.n_views=12", "scene.options.point_spacing=0.07",
        "solver.max_iter=60"]


def mcap_messages(path) -> dict:
    """{topic: [raw messages]} of a run.mcap."""
    out: dict = {}
    for topic, data in iter_run(path, RunLog(path=path)):
        out.setdefault(topic, []).append(data)
    return out


def mcap_cloud(path, topic) -> dict:
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

    return decode_point_cloud(PointCloud.FromString(mcap_messages(path)[topic][0]))


def rrd_static(path) -> dict:
    """{entity path: record batch} of run.rrd's static chunks."""
    from rerun.chunk import RrdReader

    return {ch.entity_path: ch.to_record_batch() for ch in RrdReader(path).stream() if ch.is_static}


def rgb(packed) -> tuple:
    return ((packed >> 24) & 255, (packed >> 16) & 255, (packed >> 8) & 255)


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("tiled_rec") / "run"
    out = run_cli(*ARGS, f"hydra.run.dir={d}")
    assert out.returncode == 0, out.stderr
    return d


@pytest.mark.slow
def test_a_tiled_run_records_its_labels_and_tiles(cli_run):
    d = cli_run
    summary = json.loads((d / "summary.json").read_text())
    assert summary["records"] == {"rrd": "run.rrd", "mcap": "run.mcap"}
    labels = np.load(d / "labels.npy")
    tiles = summary["tiling"]["tiles"]
    # run.mcap: the final labels of every point (the demo is below the display limit), the tiles' records
    cloud = mcap_cloud(d / "run.mcap", TOPIC_TILED_LABELS)
    np.testing.assert_array_equal(cloud["label"], labels)
    msgs = mcap_messages(d / "run.mcap")
    recs = [json.loads(m) for m in msgs[TOPIC_TILED_RECORDS]]
    assert [r["id"] for r in recs] == [t["id"] for t in tiles] and all(r["status"] == "done" for r in recs)
    assert "/diffuser_lab/z" not in msgs  # no intermediate Z
    # run.rrd: the same labels, one green box per tile, the figures on the tile timeline
    st = rrd_static(d / "run.rrd")
    ids = np.asarray(st["/world/tiled/labels"].column("Points3D:class_ids").to_pylist()[0])
    np.testing.assert_array_equal(ids, np.where(labels < 0, UNLABELED_ID, labels.astype(np.int64)))  # not int16: 65535
    boxes = st["/world/tiled/tiles"]
    assert boxes.column("Boxes3D:labels").to_pylist()[0] == [f"{t['id']} done" for t in tiles]
    assert {rgb(c) for c in boxes.column("Boxes3D:colors").to_pylist()[0]} == {rec_tiled.STATUS_RGB["done"]}
    assert len(boxes.column("Boxes3D:centers").to_pylist()[0]) == len(tiles)


@pytest.mark.slow
def test_tiled_layout_outlines_on_the_tiles_tab_only_grey_errors_bars_per_tile(cli_run):
    from rrd_layout import check_layout

    from diffuser_lab.data.taxonomy import load_taxonomy
    from diffuser_lab.recording.rerun_log import APP_TILED, RIGHT_RGB

    d = cli_run
    summary = json.loads((d / "summary.json").read_text())
    tiles = summary["tiling"]["tiles"]
    rrd = d / "run.rrd"
    st = rrd_static(rrd)
    gt = np.asarray(st["/world/tiled/ground_truth"].column("Points3D:class_ids").to_pylist()[0])
    v = check_layout(rrd, APP_TILED, load_taxonomy(summary["taxonomy"]), gt[gt != UNLABELED_ID], {})
    assert v["tabs"] == ["tiled: labels", "tiles", "errors", "ground truth"]
    boxed = [t for t in v["tabs"] if "/world/tiled/tiles" in v[t]["query"]]
    assert boxed == ["tiles"]  # labels, errors and ground truth free of boxes
    assert st["/world/tiled/tiles"].column("Boxes3D:fill_mode").to_pylist()[0] == [1]  # MajorWireframe: outlines
    for tab in ("tiles", "errors"):  # over the cloud in one grey
        (over,) = v[tab]["overrides"].values()
        assert rgb(over["Points3D:colors"][0]) == RIGHT_RGB
    # the boxes end where the cloud ends (the grid's last cells reach past it)
    pts = np.asarray(st["/world/tiled/labels"].column("Points3D:positions").to_pylist()[0])
    c = np.asarray(st["/world/tiled/tiles"].column("Boxes3D:centers").to_pylist()[0])
    h = np.asarray(st["/world/tiled/tiles"].column("Boxes3D:half_sizes").to_pylist()[0])
    np.testing.assert_allclose((c + h)[:, :2].max(0), pts[:, :2].max(0), atol=1e-4)
    # a bar per tile and figure, keyed by the tile's id, at its table row
    for k in ("accuracy", "iterations", "residual_log10", "points", "time_s"):
        for i, t in enumerate(tiles):
            bar = st[f"/tile/{k}/{t['id']}"]
            assert bar.column("BarChart:abscissa").to_pylist()[0] is not None
    charts = [f"accuracy [%], mIoU {summary['metrics']['miou']:.1f}", "iterations", "last residual, log10", "points"]
    assert [v[c]["query"] for c in charts] == [["$origin/**"]] * 4
    def bar(k, t):  # a tensor of one value
        return st[f"/tile/{k}/{t['id']}"].column("BarChart:values").to_pylist()[0][0]["buffer"][0]

    for t in tiles:
        assert bar("residual_log10", t) == pytest.approx(np.log10(t["residual"]), rel=1e-5)
        assert bar("iterations", t) == t["iterations"] and bar("points", t) == t["points"]
        assert 0 < bar("accuracy", t) <= 100


@pytest.mark.slow
def test_inspect_lists_the_tiles(cli_run, capsys):
    assert inspect.main([str(cli_run)]) == 0
    out = capsys.readouterr().out
    assert "tiled 3x3 grid" in out and "9 done" in out
    assert sum(line.split()[1:2] == ["done"] for line in out.splitlines()) == 9
    assert inspect.main([str(cli_run), "--at", "last"]) == 2  # no iterations: a usage error, no crash


@pytest.mark.slow
def test_record_off_writes_nothing_and_the_same_labels(cli_run, tmp_path, monkeypatch):
    conf = compose(*ARGS, "record=off")
    proto = PROTOCOLS["tiled"]
    res = proto.run(conf, run_dir=tmp_path)
    files = record_result(conf, tmp_path, res)
    done = proto.finish(res, conf, tmp_path, report.SummaryFile(tmp_path, []), files)
    assert files == {} and done["records"] == {}
    assert not (tmp_path / "run.rrd").exists() and not (tmp_path / "run.mcap").exists()
    np.testing.assert_array_equal(np.load(tmp_path / "labels.npy"), np.load(cli_run / "labels.npy"))

    # the same result recorded with a display limit of 5,000 points and two tiles failed / kept:
    # every 4th point, the boxes by status
    monkeypatch.setattr(rec_tiled, "MAX_DISPLAY_POINTS", 5000)
    tiles = [dict(t) for t in res.tiles]
    tiles[0]["status"], tiles[1]["status"] = "error", "resumed"
    res2 = dataclasses.replace(res, tiles=tiles)
    out = tmp_path / "thin"
    files = record_result(compose(*ARGS), out, res2)
    assert files == {"rrd": "run.rrd", "mcap": "run.mcap"}
    stride = -(-res.scene.n_points // 5000)
    cloud = mcap_cloud(out / "run.mcap", TOPIC_TILED_LABELS)
    np.testing.assert_array_equal(cloud["label"], res.labels[::stride])
    np.testing.assert_allclose(cloud["x"], res.scene.points[::stride, 0].astype(np.float32))
    assert len(mcap_cloud(out / "run.mcap", TOPIC_SCENE)["x"]) == len(cloud["x"]) <= 5000
    boxes = rrd_static(out / "run.rrd")["/world/tiled/tiles"]
    cols = [rgb(c) for c in boxes.column("Boxes3D:colors").to_pylist()[0]]
    S = rec_tiled.STATUS_RGB
    assert cols == [S["error"], S["resumed"]] + [S["done"]] * (len(tiles) - 2)
