"""The report's figures read as a researcher expects: convergence curves coloured by the swept value
with seeds aggregated, a methods plot that says something for a one-method sweep, numeric order on
the axes, and a report titled by the experiment rather than the folder."""
import json
import os
import shutil
import subprocess
import sys

import matplotlib.colors as mcolors
import matplotlib.pyplot as plt
import numpy as np
import pytest
from conftest import ROOT, run_cli

TINY = ["scene.options.point_spacing=0.1", "n_views=6", "solver.max_iter=20"]


@pytest.fixture(scope="module")
def sweeps(tmp_path_factory):
    """Three tiny sweeps in folders whose names are not the experiment's."""
    base = tmp_path_factory.mktemp("rp")
    jobs = {
        "ksweep": ["+experiment=k", "graph.k=8,16", "seed=0,1"],
        "twokeys": ["+experiment=k", "graph.k=8,16", "graph.use_normals=true,false", "seed=0"],
        "twomethods": ["+experiment=methods", "method=bayesian,diffuser", "seed=0,1"],
    }
    for name, args in jobs.items():
        res = run_cli("-m", *args, *TINY, f"hydra.sweep.dir={base / name}", cwd=base)
        assert res.returncode == 0, res.stderr[-2000:]
    return base


def _runs(path):
    from analysis.runs import find_runs

    return find_runs([str(path)])


def _legend(fig, title):
    found = [lg for lg in [*fig.legends, *(a.get_legend() for a in fig.axes)] if lg is not None
             and lg.get_title().get_text() == title]
    assert found, f"no legend titled {title!r}"
    return found[0]


def _final_mious(runs):
    from diffuser_lab.recording.mcap_read import read_run

    out = {}
    for r in runs:
        rows = read_run(r.path / "run.mcap").metrics
        out.setdefault(r.overrides["graph.k"], []).append(rows[-1]["miou"])
    return out


# --- convergence ---------------------------------------------------------------------------------

@pytest.mark.slow
def test_convergence_has_one_legend_entry_per_k_in_order(sweeps):
    from analysis.plots import convergence_figure

    fig = convergence_figure(_runs(sweeps / "ksweep"))
    try:
        lg = _legend(fig, "graph.k")
        assert [t.get_text() for t in lg.get_texts()] == ["8", "16"]
        colors = [mcolors.to_rgba(h.get_color()) for h in lg.legend_handles]
        assert colors[0] != colors[1]
        # a sequential map, ordered: the larger K is the lighter colour
        lum = [0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2] for c in colors]
        assert lum[0] < lum[1]
        # the curves carry the legend's colours
        a1 = fig.axes[0]
        by_label = {ln.get_label(): mcolors.to_rgba(ln.get_color()) for ln in a1.lines}
        assert by_label == {"graph.k=8": colors[0], "graph.k=16": colors[1]}
    finally:
        plt.close(fig)


@pytest.mark.slow
def test_convergence_aggregates_seeds_mean_and_band(sweeps):
    from analysis.plots import convergence_figure

    runs = _runs(sweeps / "ksweep")
    assert len(runs) == 4
    fig = convergence_figure(runs)
    try:
        a1, a2 = fig.axes[:2]
        assert len(a1.lines) == 2 and len(a2.lines) == 2  # 2 configurations, not 4 runs
        assert len(a1.collections) == 2 and len(a2.collections) == 2  # one band each
        assert a2.get_yscale() == "log"
        assert a1.get_ylabel().startswith("mIoU") and a1.get_xlabel() == a2.get_xlabel() == "iteration"
        finals = _final_mious(runs)
        for ln in a1.lines:
            k = ln.get_label().split("=")[1]
            assert np.isclose(ln.get_ydata()[-1], np.mean(finals[k]))
        title = fig._suptitle.get_text()
        assert "mean over 2 seeds" in title and "min–max" in title
    finally:
        plt.close(fig)


@pytest.mark.slow
def test_convergence_second_parameter_as_line_style(sweeps):
    from analysis.plots import convergence_figure

    fig = convergence_figure(_runs(sweeps / "twokeys"))
    try:
        a1 = fig.axes[0]
        assert len(a1.lines) == 4
        assert len({ln.get_linestyle() for ln in a1.lines}) == 2
        assert len({mcolors.to_rgba(ln.get_color()) for ln in a1.lines}) == 2
        colour = _legend(fig, "graph.k")
        assert [t.get_text() for t in colour.get_texts()] == ["8", "16"]
        other = [t.get_text() for lg in fig.legends if lg is not colour for t in lg.get_texts()]
        assert sum(t.startswith("graph.use_normals=") for t in other) == 2
    finally:
        plt.close(fig)


# --- methods -------------------------------------------------------------------------------------

@pytest.mark.slow
def test_methods_one_method_against_bayesian_per_k(sweeps):
    from analysis.plots import methods_figure

    runs = _runs(sweeps / "ksweep")
    fig = methods_figure(runs)
    try:
        ax = fig.axes[0]
        assert [t.get_text() for t in ax.get_legend().get_texts()] == ["diffuser", "bayesian (baseline)"]
        assert [t.get_text() for t in ax.get_xticklabels()] == ["8", "16"] and ax.get_xlabel() == "graph.k"
        bars = [p for p in ax.patches]
        assert len(bars) == 4
        want = {}
        for r in runs:
            want.setdefault(("diffuser", r.overrides["graph.k"]), []).append(r.summary["metrics"]["miou"])
            want.setdefault(("bayes", r.overrides["graph.k"]), []).append(r.summary["baseline"]["bayesian"]["miou"])
        heights = sorted(round(b.get_height(), 6) for b in bars)
        assert heights == sorted(round(float(np.mean(v)), 6) for v in want.values())
    finally:
        plt.close(fig)


@pytest.mark.slow
def test_methods_several_methods_one_bar_each_labels_above_error_bars(sweeps):
    from analysis.plots import methods_figure

    runs = _runs(sweeps / "twomethods")
    fig = methods_figure(runs)
    try:
        ax = fig.axes[0]
        assert [t.get_text() for t in ax.get_xticklabels()] == ["bayesian", "diffuser"]
        assert len(ax.patches) == 2  # bayesian is one of the methods: no extra baseline bar
        for name, text in zip(["bayesian", "diffuser"], ax.texts):
            v = np.array([r.summary["metrics"]["miou"] for r in runs if r.summary["method"] == name])
            assert text.get_text() == f"{v.mean():.1f}"
            assert text.get_position()[1] > v.mean() + v.std()  # above the error bar, not on it
            assert text.get_va() == "bottom"
    finally:
        plt.close(fig)


@pytest.fixture(scope="module")
def stripped(sweeps, tmp_path_factory):
    """One run of the K sweep copied without its Bayesian baseline, its experiment override
    and its .hydra folder: nothing left to compare a single method with, nothing naming the experiment."""
    dst = tmp_path_factory.mktemp("stripped") / "my_folder"
    for d in sorted((sweeps / "ksweep").glob("*graph.k=8*seed=0*")):
        shutil.copytree(d, dst / d.name, ignore=shutil.ignore_patterns(".hydra"))
        p = dst / d.name / "summary.json"
        s = json.loads(p.read_text())
        s.pop("baseline")
        s["overrides"] = [o for o in s["overrides"] if "experiment" not in o]
        p.write_text(json.dumps(s))
    return dst


@pytest.mark.slow
def test_one_bar_methods_plot_is_skipped_and_not_referenced(stripped, tmp_path):
    from analysis.plots import make_plots, methods_figure
    from analysis.report import report

    assert methods_figure(_runs(stripped)) is None
    assert "methods.png" not in {p.name for p in make_plots([str(stripped)], tmp_path / "p")}
    md = report([str(stripped)], tmp_path / "rep").read_text()
    assert "methods.png" not in md and not (tmp_path / "rep" / "methods.png").exists()
    assert "![convergence](convergence.png)" in md
    assert md.splitlines()[0] == "# Experiment my_folder — scene demo_room_seed0"  # folder-name fallback


# --- report --------------------------------------------------------------------------------------

@pytest.mark.slow
def test_report_title_names_the_experiment_and_scene(sweeps, tmp_path):
    from analysis.report import report

    md = report([str(sweeps / "ksweep")], tmp_path / "rep").read_text()
    first = md.splitlines()[0]
    assert first == "# Experiment k — scene demo", first
    assert "rp" not in first and "ksweep" not in first
    assert "![methods](methods.png)" in md and "`graph.k` ∈ {8, 16}" in md
    md = report([str(sweeps / "twomethods")], tmp_path / "rep2").read_text()
    assert md.splitlines()[0] == "# Experiment methods — scene demo"


@pytest.mark.slow
def test_experiment_from_hydra_yaml_when_overrides_do_not_say(sweeps, tmp_path):
    from analysis.runs import experiment_name

    runs = _runs(sweeps / "ksweep")
    for r in runs:
        r.raw_overrides = [o for o in r.raw_overrides if "experiment" not in o]
    assert experiment_name(runs, [str(sweeps / "ksweep")]) == "k"  # hydra.runtime.choices.experiment


@pytest.mark.slow
def test_report_cli_default_out_is_named_after_the_experiment(sweeps, tmp_path):
    res = subprocess.run([sys.executable, "-m", "analysis.report", str(sweeps / "ksweep")], cwd=tmp_path,
                         capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert (tmp_path / "results" / "k" / "report.md").is_file()
    res = subprocess.run([sys.executable, "-m", "analysis.plots", str(sweeps / "twokeys"), "--out", str(tmp_path / "p")],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert {"convergence.png", "methods.png", "per_class_iou.png", "miou_vs_graph.k.png",
            "miou_vs_graph.use_normals.png"} <= {p.name for p in (tmp_path / "p").iterdir()}


# --- the other plots -----------------------------------------------------------------------------

@pytest.mark.slow
def test_sweep_plot_axes_and_numeric_ticks(sweeps):
    from analysis.plots import sweep_figure

    fig = sweep_figure(_runs(sweeps / "ksweep"), "graph.k")
    try:
        ax = fig.axes[0]
        assert ax.get_xlabel() == "graph.k" and ax.get_ylabel() == "mIoU [%]"
        assert [t.get_text() for t in ax.get_xticklabels()] == ["8", "16"]
        labels = [t.get_text() for t in ax.get_legend().get_texts()]
        assert labels == ["diffuser", "bayesian (baseline)"]
    finally:
        plt.close(fig)


@pytest.mark.slow
def test_class_heatmap_rows_in_numeric_order_with_labels(sweeps):
    from analysis.plots import class_heatmap_figure

    fig = class_heatmap_figure(_runs(sweeps / "ksweep"))
    try:
        ax = fig.axes[0]
        rows = [t.get_text() for t in ax.get_yticklabels()]
        assert rows == ["8", "16", "bayesian (baseline)"]  # 8 before 16 (not string order)
        assert ax.get_ylabel() == "graph.k" and ax.get_xlabel() == "class"
        cols = [t.get_text() for t in ax.get_xticklabels()]
        assert cols[0] == "wall" and cols != sorted(cols)  # the taxonomy's order
    finally:
        plt.close(fig)
