"""analysis.online: the frame-by-frame figure of a real (small) online run carries its per-frame
values and batch references, handles skipped frames, growing maps and runs without ground truth,
and the command line says so when a folder holds no online run."""
import copy
import json
import subprocess
import sys

import matplotlib.pyplot as plt
import numpy as np
import pytest
from conftest import ROOT

TINY = ["protocol=online", "record=off", "scene.options.n_views=6", "scene.options.image_width=64",
        "scene.options.image_height=48"]


def compose(*overrides):
    from hydra import compose as hcompose
    from hydra import initialize_config_dir

    from diffuser_lab.cli.main import config_dir
    from diffuser_lab.config import register, to_object

    register()
    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        return to_object(hcompose("config", overrides=list(overrides)))


@pytest.fixture(scope="module")
def summary():
    from diffuser_lab.runs.online import online
    from diffuser_lab.runs.online import summary as online_summary

    s = online_summary(online(compose(*TINY)))
    s["status"] = "ok"  # as the CLI adds
    return json.loads(json.dumps(s))  # what summary.json reads back as


def _write(folder, s):
    folder.mkdir(parents=True)
    (folder / "summary.json").write_text(json.dumps(s))
    return folder


def _line(ax, gid):
    found = [ln for ln in ax.lines if ln.get_gid() == gid]
    assert len(found) == 1, [ln.get_gid() for ln in ax.lines]
    return found[0]


def _runs(*folders):
    from analysis.online import online_runs

    return online_runs([str(f) for f in folders])


@pytest.mark.slow
def test_lines_carry_frames_and_batch_references(summary, tmp_path):
    from analysis.online import online_figure

    frames = summary["online"]["frames"]
    assert len(frames) == 6 and all(f["skipped"] is None for f in frames)
    fig = online_figure(_runs(_write(tmp_path / "run", summary)))
    try:
        a_miou, a_lat = fig.axes[:2]
        d = _line(a_miou, "online_diffuser")
        assert np.array_equal(d.get_xdata(), np.arange(6))
        assert np.allclose(d.get_ydata(), [f["diffuser_miou"] for f in frames])
        assert np.allclose(_line(a_miou, "online_bayesian").get_ydata(), [f["bayesian_miou"] for f in frames])
        for key in ("diffuser", "bayesian"):
            ref = _line(a_miou, f"batch_{key}")
            want = summary["batch"][key]["miou"]
            assert np.allclose(ref.get_ydata(), want) and ref.get_linestyle() == "--"
            assert ref.get_label() == f"batch {key} ({want:.1f})"
        lat = _line(a_lat, "latency")
        assert np.allclose(lat.get_ydata(), [f["latency_ms"] for f in frames])
        for key in ("median", "p95"):
            assert np.allclose(_line(a_lat, key).get_ydata(), summary["online"]["latency_ms"][key])
        assert len(fig.axes) == 2  # a given map: no point-count axis
        assert summary["scene"] in a_miou.get_title(loc="left") and "given map" in a_miou.get_title(loc="left")
        assert not [ln for ln in a_miou.lines if ln.get_gid() == "skipped"]
    finally:
        plt.close(fig)


@pytest.mark.slow
def test_skipped_frames_are_gaps_and_marks_growing_map_points(summary, tmp_path):
    from analysis.online import online_figure

    s = copy.deepcopy(summary)
    s["map"] = "growing"
    f2 = s["online"]["frames"][2]
    f2.update(skipped="no valid depth", latency_ms=0.0)
    for k in ("diffuser_miou", "bayesian_miou"):
        f2.pop(k)
    for i, f in enumerate(s["online"]["frames"]):
        f["points"] = 1000 * (i + 1)
    fig = online_figure(_runs(_write(tmp_path / "run", s)))
    try:
        a_miou, a_lat, a_pts = fig.axes
        y = _line(a_miou, "online_diffuser").get_ydata()
        assert np.isnan(y[2]) and np.isfinite(np.delete(y, 2)).all()
        assert np.isnan(_line(a_lat, "latency").get_ydata()[2])
        marks = [ln for ln in a_miou.lines if ln.get_gid() == "skipped"]
        assert len(marks) == 1 and np.allclose(marks[0].get_xdata(), 2)
        assert np.allclose(_line(a_pts, "points").get_ydata(), [1000, 2000, np.nan, 4000, 5000, 6000],
                           equal_nan=True)
        assert "growing map" in a_miou.get_title(loc="left") and "1 skipped" in a_miou.get_title(loc="left")
    finally:
        plt.close(fig)


@pytest.mark.slow
def test_without_ground_truth_latency_only_and_said(summary, tmp_path):
    from analysis.online import online_figure

    s = copy.deepcopy(summary)
    for f in s["online"]["frames"]:
        for k in [k for k in f if k.endswith(("_miou", "_accuracy")) or k == "coverage"]:
            f.pop(k)
    s["metrics"], s["batch"] = None, {k: v for k, v in s["batch"].items() if k not in ("diffuser", "bayesian")}
    runs = _runs(_write(tmp_path / "gt" / "a", summary), _write(tmp_path / "nogt" / "b", s))
    fig = online_figure(runs)
    try:
        assert len(fig.axes) == 4  # one row per run
        a_miou, a_lat = fig.axes[2:]
        assert not a_miou.lines and "no ground truth" in a_miou.texts[0].get_text()
        assert "no ground truth" in a_lat.get_title(loc="left")
        assert np.allclose(_line(a_lat, "latency").get_ydata(), [f["latency_ms"] for f in s["online"]["frames"]])
        assert _line(fig.axes[0], "online_diffuser")  # the other run keeps its mIoU panel
    finally:
        plt.close(fig)


@pytest.mark.slow
def test_cli_writes_png_and_errors_on_a_folder_without_online_runs(summary, tmp_path):
    batch = dict(summary, protocol="global")  # a batch run next to the online one is ignored
    _write(tmp_path / "runs" / "a_online", summary)
    _write(tmp_path / "runs" / "b_batch", batch)
    out = tmp_path / "o" / "online.png"
    cmd = [sys.executable, "-m", "analysis.online"]
    res = subprocess.run([*cmd, str(tmp_path / "runs"), "--out", str(out)], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 20000
    res = subprocess.run([*cmd, str(tmp_path / "runs" / "b_batch"), "--out", str(tmp_path / "x.png")], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and not (tmp_path / "x.png").exists()
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("online: error: no online run"), res.stderr


@pytest.mark.slow
def test_make_plots_adds_online_png(summary, tmp_path):
    from analysis.plots import make_plots

    made = make_plots([str(_write(tmp_path / "runs" / "a", summary))], tmp_path / "p")
    assert tmp_path / "p" / "online.png" in made
