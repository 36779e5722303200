"""What a sweep tells (job count, job lines, the watcher of Ray/submitit jobs), the launchers'
defaults, and a job's kernel threads following its launcher's CPUs."""
import io
import json
import os
import subprocess
import sys

import pytest
from conftest import ROOT


def _compose(overrides):
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from diffuser_lab.config import register
    from diffuser_lab.data import sources  # noqa: F401 - stores the scene/options configs (the module run alone)
    from diffuser_lab.runs import launchers

    register()
    launchers.register()
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
            return compose("config", overrides=overrides, return_hydra_config=True)
    finally:
        GlobalHydra.instance().clear()


@pytest.mark.parametrize("overrides,jobs", [
    (["+experiment=smoke"], 4),
    (["+experiment=k"], 15),
    (["+experiment=k", "graph.k=8,16"], 6),  # the command line replaces the experiment's values
    (["+experiment=k", "seed=0"], 5),
    (["graph.use_normals=true,false", "predictions.seed=0,1,2"], 6),
    (["graph.k=16"], 1),
])
def test_count_jobs_as_the_basic_sweeper(overrides, jobs):
    from omegaconf import OmegaConf, open_dict

    from diffuser_lab.runs.sweep import count_jobs

    cfg = _compose([o for o in overrides if "," not in o])  # compose() takes no sweeps
    with open_dict(cfg):  # what Hydra puts there for a multirun: the command line as typed
        cfg.hydra.overrides.task = OmegaConf.create(overrides)
    assert count_jobs(cfg) == jobs


def test_job_lines(tmp_path, monkeypatch):
    from diffuser_lab.runs.sweep import JOBS_ENV, job_line, job_tag

    monkeypatch.setenv(JOBS_ENV, "15")
    assert job_tag(2) == "[3/15]"
    ok = {"status": "ok", "method": "diffuser", "metrics": {"miou": 73.71}, "baseline": {"bayesian": {"miou": 61.3}},
          "timings_s": {"total": 3.84}}
    assert job_line(2, tmp_path / "2_graph.k=24,seed=0", ok) == \
        "[3/15] 2_graph.k=24,seed=0: diffuser mIoU 73.7 (bayesian 61.3) in 3.8 s"
    bad = {"status": "failed", "error": "ConfigError: graph.k=0: expected >= 1"}
    assert job_line(0, tmp_path / "0_graph.k=0", bad) == "[1/15] 0_graph.k=0: FAILED: ConfigError: graph.k=0: expected >= 1"
    monkeypatch.delenv(JOBS_ENV)
    assert job_tag(0) == "[1]"


@pytest.mark.parametrize("before", [None, "7"])
def test_a_sweeps_job_count_leaves_the_process_with_it(tmp_path, monkeypatch, before):
    """The count is the sweep's jobs': set at its start, the process's own value again at its end (a run
    of the command line in a test worker compared os.environ with its server's and went to fresh
    interpreters for the rest of the worker's life)."""
    from omegaconf import OmegaConf, open_dict

    from diffuser_lab.runs.sweep import JOBS_ENV, SweepProgress

    if before is None:
        monkeypatch.delenv(JOBS_ENV, raising=False)
    else:
        monkeypatch.setenv(JOBS_ENV, before)
    cfg = _compose([])
    with open_dict(cfg):
        cfg.hydra.overrides.task = OmegaConf.create(["seed=0,1,2"])
        cfg.hydra.sweep.dir = str(tmp_path)
    cb = SweepProgress()
    cb.on_multirun_start(cfg)
    assert os.environ[JOBS_ENV] == "3"
    cb.on_multirun_end(cfg)
    assert os.environ.get(JOBS_ENV) == before


def test_watcher_prints_each_job_once(tmp_path, monkeypatch):
    from diffuser_lab.runs.sweep import JOBS_ENV, Watcher

    monkeypatch.setenv(JOBS_ENV, "2")
    out = io.StringIO()
    w = Watcher(tmp_path, file=out)
    for num in (0, 1):
        (tmp_path / f"{num}_seed={num}").mkdir()
    (tmp_path / "0_seed=0" / "summary.json").write_text(json.dumps({"status": "running", "overrides": ["seed=0"]}))
    w.poll()
    w.poll()
    (tmp_path / "0_seed=0" / "summary.json").write_text(json.dumps(
        {"status": "ok", "method": "diffuser", "metrics": {"miou": 50.0}, "baseline": {"bayesian": {"miou": 40.0}}}))
    (tmp_path / "1_seed=1" / "summary.json").write_text(json.dumps({"status": "failed", "error": "boom"}))
    w.poll()
    w.poll()
    assert out.getvalue().splitlines() == [
        "[1/2] started seed=0",
        "[1/2] 0_seed=0: diffuser mIoU 50.0 (bayesian 40.0)",
        "[2/2] 1_seed=1: FAILED: boom",
    ]


def test_launcher_defaults():
    pytest.importorskip("hydra_plugins.hydra_ray_launcher")
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    ray = _compose(["+experiment=k", "hydra/launcher=ray"]).hydra.launcher
    assert ray._target_.endswith("RayLauncher")
    assert ray.ray.init.address is None and ray.ray.init.include_dashboard is False
    assert ray.ray.remote.num_cpus == 1
    two = _compose(["+experiment=k", "hydra/launcher=ray", "hydra.launcher.ray.remote.num_cpus=2"]).hydra.launcher
    assert two.ray.remote.num_cpus == 2
    local = _compose(["+experiment=k", "hydra/launcher=submitit_local"]).hydra.launcher
    assert local._target_.endswith("LocalLauncher") and local.cpus_per_task == 1
    folder = str(local._get_node("submitit_folder")._value())
    assert folder == "${hydra.sweep.dir}/.submitit"  # no %j: submitit's local executor made a literal folder of it


def test_experiment_sweep_dirs_resolve_before_hydra_config_is_set():
    """Hydra resolves hydra.sweep.dir in the launcher before HydraConfig exists (the README's sweeps
    failed for every user on ${hydra:...}); the experiments must use the plain interpolation."""
    for path in [*sorted((ROOT / "conf" / "experiment").glob("*.yaml")), ROOT / "conf" / "sweep" / "ablation.yaml"]:
        assert "${hydra:" not in path.read_text(), path.name
    for path in sorted((ROOT / "conf" / "experiment").glob("*.yaml")):  # the shared preamble names each one's folder
        cfg = _compose([f"+experiment={path.stem}", "scene=scannet0470"])
        assert str(cfg.hydra.sweep.dir).startswith(f"logs/multirun/{path.stem}/"), cfg.hydra.sweep.dir
        assert str(cfg.hydra.sweep.dir).endswith("_scannet0470")
        assert cfg.record.mode.name == "mcap" and cfg.record.z_precision.name == "float16" and cfg.record.interval == 20


@pytest.mark.parametrize("env,expected", [({}, None), ({"OMP_NUM_THREADS": "1"}, 1), ({"SLURM_CPUS_PER_TASK": "1"}, 1),
                                          ({"NUMBA_NUM_THREADS": "2", "OMP_NUM_THREADS": "1"}, 2)])
def test_kernel_threads_follow_the_launchers_cpus(env, expected):
    pytest.importorskip("numba")
    import os

    e = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "SLURM_CPUS_PER_TASK", "NUMBA_NUM_THREADS")}
    e.update(env)
    code = "from diffuser_lab.backends import numba as k; print(k.n_threads()); k.limit_threads(1); print(k.n_threads())"
    out = subprocess.run([sys.executable, "-c", code], env=e, capture_output=True, text=True, check=True).stdout.split()
    cores = len(os.sched_getaffinity(0))
    assert int(out[0]) == (expected if expected is not None else cores) or cores == 1
    assert int(out[1]) == 1


def test_the_sweeper_checks_every_swept_value_once_at_start_up():
    """hydra/sweeper=diffuser_lab (the default): the basic sweeper's jobs, with a start-up check that
    composes only the jobs bringing an override not seen yet, which together hold every override."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra_plugins.diffuser_lab_sweeper.sweeper import CoveringSweeper, covering

    cfg = _compose(["+experiment=k"])
    assert cfg.hydra.sweeper._target_.endswith("CoveringSweeper") and issubclass(CoveringSweeper, BasicSweeper)
    items = [f"{k}={v}" for k, v in cfg.hydra.sweeper.params.items()]
    batch = BasicSweeper.split_arguments(OverridesParser.create().parse_overrides(items), None)[0]
    checked = covering(batch)
    assert len(batch) == 15 and len(checked) == 5  # 5 values of k x 3 seeds: each value once
    assert {o for job in checked for o in job} == {o for job in batch for o in job}
    assert [batch.index(job) for job in checked] == sorted(batch.index(job) for job in checked)


def test_a_bad_value_in_the_last_job_stops_the_sweep_before_any_job(tmp_path):
    from conftest import run_cli

    p = run_cli("-m", "graph.k=8,16,abc", "seed=0,1", "record=off", f"hydra.sweep.dir={tmp_path / 'sweep'}")
    assert p.returncode != 0 and "graph.k=abc" in p.stderr, p.stderr[-2000:]
    assert not list((tmp_path / "sweep").glob("*/summary.json"))  # no job ran


def test_a_sweeps_jobs_share_one_config_repository_and_compose_the_same_configs():
    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    from hydra._internal.utils import create_config_search_path
    from hydra.types import RunMode
    from hydra_plugins.diffuser_lab_sweeper.sweeper import _OneRepository
    from omegaconf import OmegaConf

    from diffuser_lab.config import register
    from diffuser_lab.data import sources  # noqa: F401 - stores the scene/options configs (the module run alone)
    from diffuser_lab.runs import launchers

    register()
    launchers.register()
    # method=ldls's @package _global_ graph keys once leaked into the later jobs' graph (a shared node);
    # jobs of different keys (a tuning sweep's): what one sets, adds or deletes is not the next one's
    jobs = [["graph.k=8", "seed=0"], ["graph.k=32", "seed=2", "hydra.searchpath=[file://" + str(ROOT / "conf") + "]"],
            ["graph.k=8", "seed=1"], ["method=ldls", "seed=0"], ["method=diffuser", "seed=0"],
            ["graph.k=8", "seed=0", "+scene.options.spare=1", "~hydra.callbacks.sweep"],
            ["graph.k=8", "seed=1", "+scene.options.spare=2", "~hydra.callbacks.sweep"], ["seed=1"]]

    def composed(share: bool) -> list[str]:
        loader = ConfigLoaderImpl(config_search_path=create_config_search_path(str(ROOT / "conf")))
        master = loader.load_configuration("config", ["+experiment=k"], RunMode.MULTIRUN)
        if share:
            loader._parse_overrides_and_create_caching_repo = _OneRepository(loader)
        out = [OmegaConf.to_yaml(loader.load_sweep_config(master, job)) for job in jobs]
        if share:  # one repository per search path; the loader still travels to joblib's processes
            assert len(loader._parse_overrides_and_create_caching_repo.repos) == 2
            cloudpickle = pytest.importorskip("joblib.externals.cloudpickle")
            cloudpickle.loads(cloudpickle.dumps(loader))
        return out

    shared = composed(True)
    assert shared == composed(False)
    assert "k: 24" in shared[7] and "spare" not in shared[7] and "spare: 2" in shared[6]


def test_the_sweep_table_names_jobs_on_other_machines(tmp_path, monkeypatch):
    """print_table: one line when the jobs' provenance differs (what and how many jobs per value),
    nothing when they agree; a job without the block (an older run's) is left out."""
    import copy

    from diffuser_lab.backends import provenance
    from diffuser_lab.runs import sweep

    here = provenance.collect()
    amd = copy.deepcopy(here)
    amd["machine"]["cpu_model"] = "AMD EPYC 7742 64-Core Processor"

    def table(blocks) -> str:
        d = tmp_path / str(len(list(tmp_path.iterdir())))
        for i, block in enumerate(blocks):
            (d / f"{i}_seed={i}").mkdir(parents=True)
            s = {"status": "ok", "overrides": [f"seed={i}"], "metrics": {"miou": 50.0 + i}}
            if block is not None:
                s["provenance"] = block
            (d / f"{i}_seed={i}" / "summary.json").write_text(json.dumps(s))
        monkeypatch.setitem(sweep._started, "dir", d)
        out = io.StringIO()
        sweep.print_table(file=out)
        return out.getvalue().strip()

    agree = table([here, here, None])
    assert "| miou |" in agree and "3 of 3 jobs ok" in agree and "mixed" not in agree
    assert table([here, amd, here, None]).splitlines()[-1] == (
        f"mixed machines or versions: CPU {here['machine']['cpu_model']} (2 jobs), AMD EPYC 7742 64-Core "
        f"Processor (1 job)")
