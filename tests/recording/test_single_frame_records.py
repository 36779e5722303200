"""Records of single-frame runs (issue 50 item 3): each target frame's diffusion in run.rrd and
run.mcap (its window, Z on the schedule, its labels against the frame's ground truth), Table II
as it accumulates, a layout of its own, and diffuser-lab-inspect / --to-rrd reading them."""
import json

import numpy as np
import pytest
from conftest import run_cli
from test_viewer import per_step

from diffuser_lab.cli.inspect import main as inspect_main
from diffuser_lab.recording.mcap_read import read_run
from diffuser_lab.recording.rerun_log import APP_SINGLE_FRAME, UNLABELED_ID
from diffuser_lab.recording.schedule import schedule

pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings("ignore:RRD file has no footer")]

ARGS = ["protocol=single_frame", "scene.options.n_views=8", "scene.options.point_spacing=0.08",
        "scene.options.image_width=96", "scene.options.image_height=72", "protocol.max_targets=3",
        "protocol.window=3", "solver.max_iter=60", "output.quiet=true"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    out = {}
    for rec in ("both", "off"):
        d = tmp_path_factory.mktemp(f"sf_{rec}")
        p = run_cli(*ARGS, f"record={rec}", f"hydra.run.dir={d}")
        assert p.returncode == 0, p.stderr
        out[rec] = d
    return out


def summary(d):
    return json.loads((d / "summary.json").read_text())


def test_records_change_nothing_and_are_reported(runs):
    on, off = summary(runs["both"]), summary(runs["off"])
    assert on["records"] == {"rrd": "run.rrd", "mcap": "run.mcap"} and off["records"] == {}
    strip = lambda rows: [{k: v for k, v in r.items() if k != "calibration"} for r in rows]  # noqa: E731
    assert strip(on["rows"]) == strip(off["rows"])  # Table II identical with and without records
    assert not (runs["off"] / "run.rrd").exists()


def test_mcap_holds_every_targets_diffusion_and_rows(runs):
    log = read_run(runs["both"] / "run.mcap", z="all")
    s = summary(runs["both"])
    assert log.complete and log.single_frame["window"] == 3 and len(log.targets) == s["n_targets"] == 3
    steps = []
    for k, t in enumerate(log.targets):
        assert t["method"] == "diffuser" and t["views"] == 3 and len(t["window"]) == 3 and t["index"] in t["window"]
        assert t["iterations"] == 60 and t["end"] == t["start"] + 61
        if k:
            assert t["start"] == log.targets[k - 1]["end"] + 1
        steps += [t["start"] + i for i in schedule(60)]
        mine = {(r["method"], r["views"]): r for r in t["rows"]}
        assert mine[("diffuser", 3)]["frame_miou"] is not None
    assert log.z_iterations == steps
    ends = {t["start"] + 60 for t in log.targets}
    assert all(log.z_dtype[i] == ("float32" if i in ends else "q8") for i in steps)
    assert [m["iteration"] for m in log.metrics] == steps
    assert log.summary["rows"] == s["rows"]


def test_rrd_every_iteration_scalars_end_on_the_rows_frame_miou(runs):
    from rrd_layout import app_id

    rrd = runs["both"] / "run.rrd"
    assert app_id(rrd) == APP_SINGLE_FRAME
    log = read_run(runs["both"] / "run.mcap")
    miou = per_step(rrd, "/metrics/miou", "Scalars:scalars")
    for t in log.targets:
        its = [t["start"] + i for i in range(1, 61)]
        assert set(its) <= set(miou)
        mine = next(r for r in t["rows"] if (r["method"], r["views"]) == ("diffuser", 3))
        # the last iteration's 2D mIoU is the frame's Table II figure (pixels without depth as misses)
        assert miou[its[-1]][0] == pytest.approx(mine["frame_miou"], abs=1e-9)
        live = per_step(rrd, "/target/diffuser", "SegmentationImage:buffer")
        rows = per_step(rrd, "/target/rows/diffuser_3", "SegmentationImage:buffer")
        assert np.array_equal(np.asarray(live[its[-1]]), np.asarray(rows[t["end"]]))  # the last labels, projected
    table = per_step(rrd, "/table", "TextDocument:text")
    assert sorted(table) == [t["end"] for t in log.targets] and "| diffuser | 3 |" in table[log.targets[-1]["end"]][0]


def test_layout_legend_and_plots(runs):
    from rrd_layout import check_layout, static_column

    from diffuser_lab.data.taxonomy import load_taxonomy

    rrd = runs["both"] / "run.rrd"
    gt = np.asarray(static_column(rrd, "/world/scene/ground_truth", "Points3D:class_ids"))
    tax = load_taxonomy(summary(runs["both"])["taxonomy"])
    v = check_layout(rrd, APP_SINGLE_FRAME, tax, [], {
        "this frame: 2D mIoU, accuracy [%]": ["/metrics/miou", "/metrics/accuracy"],
        "Table II so far: 2D mIoU [%]": ["/table/miou/**"], "relative residual, log10": ["/metrics/residual_log10"]})
    assert {"target: labels", "through the target camera", "confidence", "errors", "ground truth", "scene + window",
            "frame: Diffuser labels", "frame: diffuser_3", "frame: ground truth", "Table II"} <= set(v)
    assert gt[gt != UNLABELED_ID].size


def test_inspect_at_and_to_rrd(runs, tmp_path, capsys):
    d = runs["both"]
    assert inspect_main([str(d)]) == 0
    out = capsys.readouterr().out
    assert "single-frame protocol (Table II): 3 target frames" in out and "diffuser         3" in out
    log = read_run(d / "run.mcap")
    last = log.z_iterations[-1]
    assert inspect_main([str(d), "--at", str(last), "--out", str(tmp_path / "z.npy")]) == 0
    assert np.load(tmp_path / "z.npy").shape[0] == log.targets[-1]["n_points"]
    out_rrd = tmp_path / "replay.rrd"
    assert inspect_main([str(d), "--to-rrd", str(out_rrd)]) == 0
    live = per_step(d / "run.rrd", "/world/diffusion/labels", "Points3D:class_ids")
    again = per_step(out_rrd, "/world/diffusion/labels", "Points3D:class_ids")
    assert sorted(again) == sorted(live)  # each target's start and its recorded iterations
    for step in log.z_iterations:
        np.testing.assert_array_equal(np.asarray(again[step]), np.asarray(live[step]))
    assert sorted(per_step(out_rrd, "/table", "TextDocument:text")) == [t["end"] for t in log.targets]
