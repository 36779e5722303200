"""Hydra multirun of a tiny sweep, then the analysis scripts on its output; launcher configs compose."""
import csv
import importlib.util
import re

import numpy as np
import pytest
from conftest import ROOT, run_cli


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    base = tmp_path_factory.mktemp("sweep")
    ok = run_cli("-m", "+experiment=smoke", f"hydra.sweep.dir={base / 'smoke'}", cwd=base)
    assert ok.returncode == 0, ok.stderr[-2000:]
    bad = run_cli("-m", "+experiment=smoke", "graph.sigma_s=-1", "graph.use_normals=true", "seed=0",
                  f"hydra.sweep.dir={base / 'bad'}", cwd=base)
    assert bad.returncode != 0  # Hydra reports the failed job ...
    return base


@pytest.mark.slow
def test_collect_table_has_the_sweep(sweep, tmp_path):
    from analysis.collect import collect

    rrows, arows, md = collect([str(sweep / "smoke")], tmp_path / "t")
    assert len(rrows) == 4 and all(r["status"] == "ok" for r in rrows)
    pairs = sorted((r["graph.use_normals"], r["seed"]) for r in rrows)
    assert pairs == [("false", "0"), ("false", "1"), ("true", "0"), ("true", "1")] or \
        pairs == [("False", "0"), ("False", "1"), ("True", "0"), ("True", "1")]
    assert len(arows) == 2 and all(r["runs"] == 2 and r["failed"] == 0 for r in arows)
    assert all(r["miou"] is not None and 0 < r["miou"] <= 100 for r in arows)
    with open(tmp_path / "t_runs.csv") as fh:
        assert len(list(csv.DictReader(fh))) == 4
    assert "graph.use_normals" in md and "±" in md


@pytest.mark.slow
def test_failed_job_shows_as_failed(sweep, tmp_path):
    from analysis.collect import collect

    rrows, arows, md = collect([str(sweep / "smoke"), str(sweep / "bad")], tmp_path / "t")
    failed = [r for r in rrows if r["status"] != "ok"]
    assert len(rrows) == 5 and len(failed) == 1  # ... and the other jobs are still in the table
    assert "graph.sigma_s" in failed[0]["error"]
    assert "Failed runs" in md and "graph.sigma_s" in md


@pytest.mark.slow
def test_plots_are_non_empty_pngs(sweep, tmp_path):
    from analysis.plots import make_plots

    made = make_plots([str(sweep / "smoke")], tmp_path)
    names = {p.name for p in made}
    assert {"miou_vs_graph.use_normals.png", "methods.png", "per_class_iou.png", "convergence.png"} <= names
    for p in made:
        data = p.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


@pytest.mark.slow
def test_report_and_compare(sweep, tmp_path):
    from analysis.compare import compare
    from analysis.report import report

    md = report([str(sweep / "smoke")], tmp_path / "rep").read_text()
    assert "| graph.use_normals |" in md and "![convergence](convergence.png)" in md
    runs = sorted((sweep / "smoke").glob("*seed=0"))  # same seed = same room: normals on vs off
    assert len(runs) == 2
    res = compare(runs[0], runs[1], tmp_path / "cmp.rrd")
    la, lb = (np.load(r / "labels.npy") for r in runs)
    assert res["n_points"] == la.size and res["n_differ"] == int((la != lb).sum())
    assert res["share_differ"] == pytest.approx(res["n_differ"] / la.size) and 0 < res["share_differ"] < 0.5
    assert (tmp_path / "cmp.rrd").stat().st_size > 1000


@pytest.mark.parametrize("launcher,plugin", [("local_parallel", "hydra_plugins.hydra_joblib_launcher"),
                                             ("slurm", "hydra_plugins.hydra_submitit_launcher"),
                                             ("ray", "hydra_plugins.hydra_ray_launcher")])
def test_launcher_configs_compose(launcher, plugin):
    if importlib.util.find_spec(plugin) is None:
        pytest.skip(f"{plugin} not installed (optional extra)")
    from hydra import compose, initialize_config_dir

    from diffuser_lab.config import register

    register()
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["+experiment=k", f"hydra/launcher={launcher}"], return_hydra_config=True)
    assert "Launcher" in cfg.hydra.launcher._target_
    assert cfg.hydra.sweeper.params["graph.k"] == "8,16,24,32,48"


def _other_cpu(here: dict) -> tuple[str, str]:
    """(model, vendor) of a CPU of the other vendor than ``here``'s (a summary's provenance): the
    suite runs on Intel and AMD machines."""
    if here["machine"].get("cpu_vendor") == "AuthenticAMD":
        return "Intel(R) Xeon(R) Platinum 8480+", "GenuineIntel"
    return "AMD EPYC 7742 64-Core Processor", "AuthenticAMD"


def _mixed_copy(sweep, tmp_path, other=None):
    """The smoke sweep copied, one job's summary as if run on another vendor's machine (``other``:
    :func:`_other_cpu`'s, by default of the sweep's host) and another's with an older numpy: (the
    copy, its job folders)."""
    import json
    import shutil

    copy = tmp_path / "mixed"
    shutil.copytree(sweep / "smoke", copy)
    jobs = sorted(p.parent for p in copy.glob("*/summary.json"))
    assert len(jobs) == 4
    if other is None:
        other = _other_cpu(json.loads((jobs[0] / "summary.json").read_text())["provenance"])
    for job, change in ((jobs[2], "cpu"), (jobs[3], "numpy")):
        s = json.loads((job / "summary.json").read_text())
        if change == "cpu":  # another vendor's CPU than the host's
            s["provenance"]["machine"].update(cpu_model=other[0], cpu_vendor=other[1])
        else:
            s["provenance"]["versions"]["numpy"] = "1.26.4"
        (job / "summary.json").write_text(json.dumps(s))
    return copy, jobs


@pytest.mark.slow
def test_collect_and_the_sweep_table_say_when_jobs_ran_on_different_machines(sweep, tmp_path):
    import io
    import json

    from analysis.collect import collect
    from analysis.report import report
    from conftest import check_provenance
    from diffuser_lab.runs import sweep as sweep_mod

    here = json.loads(next((sweep / "smoke").glob("*/summary.json")).read_text())["provenance"]
    check_provenance(here)
    cpu, numpy_v = here["machine"]["cpu_model"], here["versions"]["numpy"]
    rrows, _, md = collect([str(sweep / "smoke")], tmp_path / "same")
    assert "mixed" not in md  # all jobs agree: nothing extra
    assert {(r["cpu"], r["isa"]) for r in rrows} == {(cpu, here["machine"]["isa"])}
    assert all(f"numpy {numpy_v}" in r["versions"] for r in rrows)
    with open(tmp_path / "same_runs.csv") as fh:
        assert {"host", "cpu", "isa", "blas", "versions", "commit"} <= set(next(csv.DictReader(fh)))

    other = _other_cpu(here)
    mixed, jobs = _mixed_copy(sweep, tmp_path, other)
    line = (f"mixed machines or versions: CPU {cpu} (3 {{n}}), {other[0]} (1 {{one}}) "
            f"(with it: vendor); numpy {numpy_v} (3 {{n}}), 1.26.4 (1 {{one}})")
    rrows, _, md = collect([str(mixed)], tmp_path / "mixed")
    assert md.endswith("\n\n" + line.format(n="runs", one="run"))
    assert (tmp_path / "mixed.md").read_text().strip().endswith(line.format(n="runs", one="run"))
    assert sorted(r["cpu"] for r in rrows).count(other[0]) == 1
    assert line.format(n="runs", one="run") in (report([str(mixed)], tmp_path / "rep").read_text())

    out = io.StringIO()  # the end-of-sweep table, as the launching process prints it
    saved = dict(sweep_mod._started)
    try:
        for folder, expect in ((sweep / "smoke", None), (mixed, line.format(n="jobs", one="job"))):
            sweep_mod._started.clear()
            sweep_mod._started["dir"] = folder
            out = io.StringIO()
            sweep_mod.print_table(file=out)
            text = out.getvalue().strip()
            assert "| graph.use_normals |" in text
            if expect is None:
                assert "mixed" not in text
            else:
                assert text.splitlines()[-1] == expect
    finally:
        sweep_mod._started.clear()
        sweep_mod._started.update(saved)


@pytest.mark.slow
def test_compare_says_which_fields_differ(sweep, tmp_path, capsys):
    from analysis.compare import compare, main

    import json

    other = _other_cpu(json.loads(next((sweep / "smoke").glob("*/summary.json")).read_text())["provenance"])
    mixed, jobs = _mixed_copy(sweep, tmp_path, other)  # jobs 0 and 2 have seed 0 (one room), 1 and 3 seed 1
    smoke = [sweep / "smoke" / j.name for j in jobs]
    same = compare(smoke[0], smoke[2])["provenance"]
    assert same["same"] is True and same["differs"] == []
    assert main([str(smoke[0]), str(smoke[2])]) == 0
    assert "ran on the same machine and versions: " in capsys.readouterr().out
    p = compare(smoke[2], jobs[2])["provenance"]
    assert p["same"] is False and [d["field"] for d in p["differs"]] == ["CPU", "vendor"]
    assert p["differs"][0]["b"] == other[0]
    p = compare(jobs[1], jobs[3])["provenance"]
    assert [(d["field"], d["b"]) for d in p["differs"]] == [("numpy", "1.26.4")]
    assert main([str(smoke[0]), str(jobs[2])]) == 0
    out = capsys.readouterr().out
    assert "ran on different machines or versions: CPU, vendor differ" in out and f"B {other[0]}" in out


def _by_seed(folder, key="graph.use_normals"):
    """{(value, seed): (run folder, summary)} of the smoke sweep."""
    import json

    out = {}
    for p in folder.glob("*/summary.json"):
        s = json.loads(p.read_text())
        ov = dict(o.split("=", 1) for o in s["overrides"] if not o.startswith("+"))
        out[(ov[key], ov["seed"])] = (p.parent, s)
    return out


@pytest.mark.slow
def test_report_pairs_seeds_scores_the_common_support_and_renders_one_html_page(sweep, tmp_path):
    import base64
    import csv as csv_mod
    import re

    from analysis.report import report
    from diffuser_lab.method.metrics import score
    from diffuser_lab.data.taxonomy import load_taxonomy

    runs = _by_seed(sweep / "smoke")
    names = load_taxonomy("scannet20").names
    for folder, s in runs.values():  # what the run wrote scores as the run did
        gt, bayes = np.load(folder / "gt_labels.npy"), np.load(folder / "bayesian_labels.npy")
        assert gt.dtype == bayes.dtype == np.int16 and gt.shape == (s["n_points"],)
        assert score(bayes, gt, names)["miou"] == pytest.approx(s["baseline"]["bayesian"]["miou"], abs=1e-9)
    md = report([str(sweep / "smoke")], tmp_path / "rep", html=True).read_text()
    assert "Reference: `graph.use_normals=True` (the default run's" in md
    row = next(ln for ln in md.splitlines() if ln.startswith("| False | 2 |"))
    want = np.mean([runs[("False", s)][1]["metrics"]["miou"] - runs[("True", s)][1]["metrics"]["miou"] for s in "01"])
    assert row.split(" | ")[2].startswith(f"{want:+.1f} [") and row.endswith("n.s. |")  # 2 pairs: p >= 0.5
    # the common support at seed 0: the points all four label arrays of that room label
    seed0 = [np.load(runs[(v, "0")][0] / f) for v in ("True", "False") for f in ("labels.npy", "bayesian_labels.npy")]
    size = int((np.stack(seed0) >= 0).all(0).sum())
    assert f" {size:,} of {runs[('True', '0')][1]['n_points']:,} at seed=0, scene=demo)." in md
    assert "| graph.use_normals | miou_common | accuracy_common | bayesian_miou_common |" in md
    rep = tmp_path / "rep"
    assert (rep / "forest.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and "![forest](forest.png)" in md
    with open(rep / "paired.csv") as fh:
        metrics = {r["metric"] for r in csv_mod.DictReader(fh)}
    assert {"miou", "miou_common", "iou wall"} <= metrics
    page = (rep / "report.html").read_text()
    images = re.findall(r'<img alt="([^"]+)" src="data:image/png;base64,([^"]+)"', page)
    assert [a for a, _ in images] == re.findall(r"^!\[([^\]]+)\]", md, re.M)  # every image, inlined
    assert base64.b64decode(images[0][1]) == (rep / f"{images[0][0]}.png").read_bytes()
    assert "src=\"" + "forest.png" not in page and "<h2>Paired differences against the reference</h2>" in page


@pytest.mark.slow
def test_report_and_compare_refuse_to_mix_the_splits_unless_asked(sweep, tmp_path, capsys):
    import json
    import shutil

    from analysis import compare, report

    copy = tmp_path / "splits"
    shutil.copytree(sweep / "smoke", copy)
    for i, p in enumerate(sorted(copy.glob("*/summary.json"))):
        s = json.loads(p.read_text())
        s["split"] = "validation" if i < 1 else "test"
        p.write_text(json.dumps(s))
    assert report.main([str(copy), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert err == ("report: error: runs of the validation and test splits in one table (1 validation, 3 test); "
                   "pass --mix-splits to allow\n")
    assert not (tmp_path / "r").exists()
    assert compare.main([str(copy), str(copy), "--where-a", "graph.use_normals=True",
                         "--where-b", "graph.use_normals=False"]) == 2
    assert "(1 validation, 3 test); pass --mix-splits to allow" in capsys.readouterr().err
    assert report.main([str(copy), "--out", str(tmp_path / "r"), "--mix-splits"]) == 0
    md = (tmp_path / "r" / "report.md").read_text()
    assert "| graph.use_normals | split | miou |" in md and "| split | pairs |" in md


@pytest.mark.slow
def test_compare_two_groups_pairs_their_seeds(sweep, capsys):
    from analysis.compare import main

    runs = _by_seed(sweep / "smoke")
    smoke = str(sweep / "smoke")
    assert main([smoke, smoke, "--where-a", "graph.use_normals=True", "--where-b", "graph.use_normals=False"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[2].startswith("B - A over 2 pairs (seed=0, scene=demo; seed=1, scene=demo)")
    want = np.mean([runs[("False", s)][1]["metrics"]["miou"] - runs[("True", s)][1]["metrics"]["miou"] for s in "01"])
    line = next(ln for ln in out if ln.strip().startswith("miou "))
    assert line.split()[1] == f"{want:+.1f}"
    assert any(ln.startswith("Common support: ") for ln in out) and any(ln.startswith("wall ") for ln in out)
    assert main([smoke, smoke]) == 2
    assert "group A holds two runs at seed=0, scene=demo" in capsys.readouterr().err
    a, b = runs[("True", "0")][0], runs[("False", "0")][0]
    assert main([str(a), str(b)]) == 0
    assert re.search(r"^on the [\d,]+ points both runs and their Bayesian baselines label \(\d+\.\d%\): mIoU A ",
                     capsys.readouterr().out, re.M)


@pytest.mark.slow
def test_collect_and_the_report_flag_jobs_that_read_different_inputs_under_one_scene_name(sweep, tmp_path):
    import json
    import shutil

    from analysis.collect import collect
    from analysis.report import report

    rrows, _, md = collect([str(sweep / "smoke")], tmp_path / "same")
    assert "different inputs" not in md and all(len(r["inputs"]) == 12 for r in rrows)
    copy = tmp_path / "edited"
    shutil.copytree(sweep / "smoke", copy)
    jobs = sorted(p.parent for p in copy.glob("*/summary.json"))
    by_scene: dict = {}
    for j in jobs:
        by_scene.setdefault(json.loads((j / "summary.json").read_text())["scene"], []).append(j)
    scene, (a, b) = next((k, v[:2]) for k, v in sorted(by_scene.items()) if len(v) >= 2)
    s = json.loads((b / "summary.json").read_text())  # as if its taxonomy file had been edited before it ran
    (tax,) = [f for f in s["inputs"]["files"] if f["role"] == "taxonomy"]
    old, tax["sha256"] = tax["sha256"], "f" * 64
    (b / "summary.json").write_text(json.dumps(s))
    n = len(by_scene[scene])
    line = (f"different inputs under one scene name: {scene} taxonomy {old[:12]} ({n - 1} run{'s' if n > 2 else ''}), "
            f"{'f' * 12} (1 run)")
    _, _, md = collect([str(copy)], tmp_path / "edited")
    assert md.endswith("\n\n" + line)
    assert line in report([str(copy)], tmp_path / "rep").read_text()
