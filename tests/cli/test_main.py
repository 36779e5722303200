"""The `diffuser-lab` command: run folder contents, one-line errors, packaged configs."""
import json
import subprocess
import sys
import zipfile

import numpy as np
import pytest
from conftest import ROOT, SMALL_DEMO, check_provenance, run_cli

SUMMARY_KEYS = {"method", "scene", "n_points", "n_frames", "n_classes", "metrics", "baseline", "predictions_2d",
                "diffusion", "timings_s", "records", "overrides", "status", "provenance"}


@pytest.mark.slow
def test_run_writes_its_folder(tmp_path):
    run_dir = tmp_path / "run"
    p = run_cli(*SMALL_DEMO, f"hydra.run.dir={run_dir}")
    assert p.returncode == 0, p.stderr
    assert "diffuser" in p.stdout and "bayesian (baseline)" in p.stdout and "2D predictions" in p.stdout
    s = json.loads((run_dir / "summary.json").read_text())
    assert SUMMARY_KEYS <= set(s)
    assert s["status"] == "ok" and s["method"] == "diffuser"
    assert {"miou", "accuracy", "coverage", "per_class_iou"} <= set(s["metrics"])
    assert {"miou", "accuracy"} <= set(s["baseline"]["bayesian"])
    assert {"load", "evidence", "graph", "diffusion", "total"} <= set(s["timings_s"])
    assert s["diffusion"]["iterations"] == 60
    assert "scene.options.n_views=10" in s["overrides"]
    check_provenance(s["provenance"])  # the machine, ISA and versions of this process
    labels = np.load(run_dir / "labels.npy")
    assert labels.shape == (s["n_points"],) and labels.dtype == np.int16
    assert (labels >= -1).all() and (labels < s["n_classes"]).all()
    assert (run_dir / "labels.ply").stat().st_size > 0
    assert (run_dir / ".hydra" / "config.yaml").is_file() and (run_dir / ".hydra" / "overrides.yaml").is_file()
    # the same folder is never reused
    again = run_cli(*SMALL_DEMO, f"hydra.run.dir={run_dir}")
    assert again.returncode != 0 and "never overwritten" in again.stderr
    assert json.loads((run_dir / "summary.json").read_text()) == s


@pytest.mark.slow
def test_default_run_folders_are_distinct(tmp_path):
    dirs = []
    for _ in range(2):
        p = run_cli(*SMALL_DEMO, "solver.max_iter=2", "output.quiet=true", "output.labels_ply=false", cwd=tmp_path)
        assert p.returncode == 0, p.stderr
    dirs = sorted((tmp_path / "logs" / "runs").glob("*/*"))
    assert len(dirs) == 2 and all((d / "summary.json").is_file() for d in dirs)


@pytest.mark.parametrize("override,expected", [
    ("graph.kk=3", "graph.kk"),
    ("graph.k=0", "graph.k=0"),
    ("graph.k=abc", "graph.k"),
    ("evidence.pixel_weight=0", "evidence.pixel_weight"),
    ("evidence.pixel_weight=-1e-4", "evidence.pixel_weight"),
    ("method=foo", "method/foo"),
    ("method.name=foo", "method.name"),
    ("solver.max_iter=0", "solver.max_iter"),
    ("record.compression=gzip", "record.compression"),
    ("record.retain_heap_mb=-1", "record.retain_heap_mb=-1"),
    ("+nonsense=1", "nonsense"),
])
def test_bad_config_fails_with_one_line(override, expected, tmp_path):
    p = run_cli(override, cwd=tmp_path)
    assert p.returncode == 2
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, p.stderr
    assert lines[0].startswith("diffuser-lab: error:") and expected in lines[0]
    assert "Traceback" not in p.stderr
    assert not (tmp_path / "logs").exists()  # nothing was started


def test_bad_input_at_run_time_is_one_line_and_recorded(tmp_path):
    run_dir = tmp_path / "run"
    p = run_cli(*SMALL_DEMO, "method=direct", "method.view=999", f"hydra.run.dir={run_dir}")
    assert p.returncode == 1
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "method.view=999" in lines[0], p.stderr
    s = json.loads((run_dir / "summary.json").read_text())
    assert s["status"] == "failed" and "method.view=999" in s["error"]


@pytest.mark.slow
def test_wheel_carries_the_configs(tmp_path):
    """Build the wheel, install it without an editable checkout, compose a config from it."""
    wheel_dir = tmp_path / "wheel"
    b = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(wheel_dir), str(ROOT)],
                       capture_output=True, text=True, timeout=600)
    if b.returncode != 0 and "No matching distribution" in b.stderr:
        pytest.skip("cannot fetch the build backend (hatchling) here")
    assert b.returncode == 0, b.stderr
    wheel = next(wheel_dir.glob("diffuser_lab-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    confs = sorted(n for n in names if n.startswith("diffuser_lab/conf/"))
    expected = sorted("diffuser_lab/" + str(p.relative_to(ROOT)) for p in (ROOT / "conf").rglob("*.yaml"))
    assert confs == expected
    assert "hydra_plugins/diffuser_lab_sweeper/sweeper.py" in names  # conf/config.yaml's sweeper
    target = tmp_path / "site"
    i = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(target), str(wheel)],
                       capture_output=True, text=True, timeout=600)
    assert i.returncode == 0, i.stderr
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    p = subprocess.run([sys.executable, "-c", "import sys; sys.path.insert(0, sys.argv[1]); sys.argv = ['diffuser-lab', "
                        "'--cfg', 'job', 'graph.k=7', 'method=ldls']; import diffuser_lab.cli.main as c; "
                        "assert c.__file__.startswith(sys.path[0]), c.__file__; print(c.config_dir()); c.main()",
                        str(target)], cwd=elsewhere, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert str(target) in p.stdout and "k: 7" in p.stdout and "name: ldls" in p.stdout


@pytest.mark.parametrize("overrides", [{}, {"graph.k": 8, "record.mode": "off", "solver.name": "exact"},
                                       {"scene.voxel_size": 0.05, "record.z_precision": "float16", "seed": 3}])
def test_config_yaml_is_omegaconfs_text(overrides):
    from omegaconf import OmegaConf

    from diffuser_lab.config import default_config
    from diffuser_lab.runs.records import config_yaml

    conf = default_config(**overrides)
    assert config_yaml(conf) == OmegaConf.to_yaml(OmegaConf.structured(conf))
    # the two ways in (a Config object's fast dump, a DictConfig through OmegaConf) write one text
    assert config_yaml(OmegaConf.structured(conf)) == config_yaml(conf)


def test_summary_file_is_built_in_one_place(tmp_path):
    """summary.json: written as `running` at once, warnings kept, finished `failed` with the
    error; a folder that holds a run is refused and its summary left as it was."""
    from diffuser_lab.runs.report import SummaryFile

    s = SummaryFile(tmp_path, ["graph.k=8"])
    first = json.loads((tmp_path / "summary.json").read_text())
    assert first["status"] == "running" and first["overrides"] == ["graph.k=8"] and "started" in first
    check_provenance(first["provenance"])  # there from the start: a run that fails keeps it
    s.warn("depth looks like millimetres")
    s.update(method="diffuser")
    s.failed("ValueError: bad frame")
    last = json.loads((tmp_path / "summary.json").read_text())
    assert last["status"] == "failed" and last["error"] == "ValueError: bad frame"
    assert last["warnings"] == ["depth looks like millimetres"] and last["method"] == "diffuser"
    with pytest.raises(FileExistsError, match="refusing to overwrite"):
        SummaryFile(tmp_path, [])
    assert json.loads((tmp_path / "summary.json").read_text()) == last
