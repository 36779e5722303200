"""Tuning that never sees the test (issue 58 item 3): hydra.sweeper.tune's sets, precedence, search
space and preset; a small search end to end: validation jobs only on validation seeds, the preset
written before any test job, the test jobs of the chosen value and of Diffuser, summary.json's split."""
import json
from pathlib import Path
from types import SimpleNamespace

import pytest
from conftest import run_cli

from diffuser_lab.runs import tune
from diffuser_lab.runs.tune import TuneError, TuneSpec

pytest.importorskip("optuna")

SETS = {"validation": {"demo": {"seed": "3,4,5"}},
        "test": {"demo": {"seed": "0,1,2"}, "scannet0470": {"scene": "scannet0470", "depth": "sensor", "seed": "0,1,2"}}}


def _spec(**kw) -> TuneSpec:
    return TuneSpec(**{"params": {"solver.tikhonov": "tag(log, interval(1e-4, 1))"}, **SETS, **kw})


def test_sets_are_grids_and_a_later_override_wins():
    jobs = tune.set_jobs(SETS["test"])
    assert [s for s, _ in jobs] == ["demo"] * 3 + ["scannet0470"] * 3
    assert jobs[0][1] == ["seed=0"] and jobs[4][1] == ["scene=scannet0470", "depth=sensor", "seed=1"]
    # the command line's seed=0 cannot make a validation job a test one; +key and key are one key
    assert tune.merge(["seed=0", "+lifter=tikhonov", "graph.k=8"], ["seed=3"], ["lifter=diffuser"], ["split=validation"]) \
        == ["seed=3", "lifter=diffuser", "graph.k=8", "split=validation"]
    assert tune.count_jobs(_spec(n_trials=8, compare={"diffuser": {"lifter": "diffuser"}})) == 8 * 3 + 6 * 2
    with pytest.raises(TuneError, match=r"seed=0,1 on the command line is a sweep"):
        tune.command_line(["+experiment=tune_tikhonov", "seed=0,1"])


def test_the_search_space_is_hydras_optuna_grammar():
    import optuna.distributions as od

    dists, fixed = tune.space({"solver.tikhonov": "tag(log, interval(1e-4, 1))", "graph.k": "int(interval(8, 48))",
                               "graph.use_normals": "true,false", "evidence.pixel_radius": "range(0, 3)",
                               "solver.max_iter": 100})
    assert dists["solver.tikhonov"] == od.FloatDistribution(1e-4, 1.0, log=True)
    assert dists["graph.k"] == od.IntDistribution(8, 48)
    assert dists["graph.use_normals"] == od.CategoricalDistribution([True, False])
    assert dists["evidence.pixel_radius"] == od.CategoricalDistribution([0, 1, 2])
    assert fixed == ["solver.max_iter=100"]
    # a tried float is written at 3 significant digits, so the preset reads as the job ran
    assert tune.trial_overrides({"solver.tikhonov": 0.0031234567}, fixed) == ["solver.max_iter=100", "solver.tikhonov=0.00312"]
    with pytest.raises(TuneError, match=r"^hydra\.sweeper\.tune\.params\.solver\.tikhonov=.*starts above 0$"):
        tune.space({"solver.tikhonov": "tag(log, interval(0, 1))"})
    with pytest.raises(TuneError, match="nothing to search"):
        tune.space({"solver.tikhonov": 0.1})


def test_a_tuning_config_that_cannot_run_is_one_line():
    with pytest.raises(TuneError, match=r"^hydra\.sweeper\.tune\.params: expected at least one key"):
        TuneSpec(validation=SETS["validation"], test=SETS["test"])
    with pytest.raises(TuneError, match=r"^hydra\.sweeper\.tune\.test: expected named sets"):
        _spec(test={})
    with pytest.raises(TuneError, match=r"^hydra\.sweeper\.tune\.direction='up': expected maximize or minimize$"):
        _spec(direction="up")
    with pytest.raises(TuneError, match=r"^hydra\.sweeper\.tune\.n_trials=0: expected >= 1$"):
        _spec(n_trials=0)
    seeds = [tune.sampler_seed(s) for s in (0, 0, 1)]  # keyed through seeding.py: the same each call
    assert seeds[0] == seeds[1] != seeds[2] and 0 <= seeds[0] < 2 ** 31


def test_the_preset_loads_as_a_config(tmp_path):
    from omegaconf import OmegaConf

    text = tune.preset_text(["solver.tikhonov=0.00412", "+graph.k=16"], ["/lifter: tikhonov"], ["a header"])
    assert text.startswith("# @package _global_\n# a header\n")
    (tmp_path / "p.yaml").write_text(text)
    cfg = OmegaConf.load(tmp_path / "p.yaml")
    assert cfg.defaults == [{"/lifter": "tikhonov"}, "_self_"]
    assert cfg.solver.tikhonov == 0.00412 and cfg.graph.k == 16


class _Return:
    """What a launcher returns of a job (hydra.core.utils.JobReturn's fields the search reads)."""

    def __init__(self, out_dir, value=None, error=None):
        self.hydra_cfg = SimpleNamespace(hydra=SimpleNamespace(runtime=SimpleNamespace(output_dir=str(out_dir))))
        self._value, self._error = value, error

    @property
    def return_value(self):
        if self._error is not None:
            raise self._error
        return self._value


def _fake_launcher(objective):
    """(launch, the batches launched): each job's value objective(overrides as a dict) (None: it fails)."""
    batches = []

    def launch(jobs, idx):
        batches.append([list(j) for j in jobs])
        out = []
        for k, job in enumerate(jobs):
            keys = dict(o.lstrip("+").split("=", 1) for o in job)
            v = objective(keys)
            out.append(_Return(f"/sweep/{idx + k}_job", v, None if v is not None else RuntimeError("job died")))
        return out

    return launch, batches


def test_the_search_runs_every_test_job_after_the_choice_in_the_sweeps_folder(tmp_path):
    import math

    def objective(keys):  # a peak at t = 10^-2.5; the first trial's seed-4 job fails
        if len(batches) == 1 and keys["seed"] == "4":
            return None
        t = float(keys.get("solver.tikhonov", 1e-9))
        return 60 - (math.log10(t) + 2.5) ** 2 + (0 if keys.get("lifter") != "diffuser" else -5)

    launch, batches = _fake_launcher(objective)
    checked = []
    spec = _spec(n_trials=6, n_startup_trials=3, compare={"diffuser": {"lifter": "diffuser"}})
    record = tune.search(spec, ["+experiment=tune_tikhonov", "seed=0"], launch, checked.append, tmp_path, "tune_tikhonov")
    # the start-up check saw every validation and test job once, before any ran
    assert len(checked) == 1 and len(checked[0]) == 3 + 6 * 2
    val, test = [j for b in batches[:-1] for j in b], batches[-1]
    assert len(batches) == 7 and len(val) == 18 and len(test) == 12  # the test jobs in one batch, last
    assert all(f"hydra.sweep.dir='{tmp_path}'" in j for j in val + test)  # one folder, whatever the job's scene
    assert {o for j in val for o in j if o.startswith(("seed=", "split="))} == {"seed=3", "seed=4", "seed=5",
                                                                                 "split=validation"}
    assert {o for j in test for o in j if o.startswith("split=")} == {"split=test"}
    assert sum("scene=scannet0470" in j for j in test) == 6 and sum("lifter=diffuser" in j for j in test) == 6
    first, *rest = record["trials"]
    assert first["value"] is None and first["error"] == "RuntimeError: job died"  # failed, the search went on
    values = [t["value"] for t in rest]
    assert None not in values and record["best"]["value"] == max(values) and len(rest) == 5
    chosen = record["best"]["overrides"][0]
    assert all(chosen in j for j in test if "lifter=diffuser" not in j)
    assert not any(o.startswith("solver.tikhonov") for j in test if "lifter=diffuser" in j for o in j)
    assert (tmp_path / "tuned" / "tune_tikhonov.yaml").read_text().count(chosen.split("=")[1]) >= 2
    assert json.loads((tmp_path / "tune.json").read_text()) == json.loads(json.dumps(record))
    assert [t["arm"] for t in record["test_jobs"]][:2] == ["tuned", "diffuser"]


def test_a_search_without_a_completed_trial_runs_no_test_job(tmp_path):
    launch, batches = _fake_launcher(lambda keys: None if keys["split"] == "validation" else 50.0)
    with pytest.raises(TuneError, match=r"^tune: none of the 2 trials completed \(first: RuntimeError: job died\); "
                                        r"no test job ran$"):
        tune.search(_spec(n_trials=2), [], launch, lambda jobs: None, tmp_path, "x")
    assert len(batches) == 2 and not (tmp_path / "tuned").exists()
    assert json.loads((tmp_path / "tune.json").read_text())["best"] is None


@pytest.mark.slow
def test_a_search_sees_validation_only_and_then_runs_the_test(tmp_path):
    """+experiment=tune_tikhonov shrunk to 2 trials on one validation room and one test room: every
    validation job ran on the validation seed, the preset was written before the first test job, the
    test jobs are the chosen weight's and Diffuser's (no trial's weight leaks into it), and
    summary.json's split and the closing tables keep the two apart."""
    sweep = tmp_path / "sweep"
    p = run_cli("-m", "+experiment=tune_tikhonov", "scene.options.point_spacing=0.15", "scene.options.image_width=80",
                "scene.options.image_height=60", "seed=0", "hydra.sweeper.tune.n_trials=2",
                "hydra.sweeper.tune.validation.demo.seed=4", "hydra.sweeper.tune.test.demo.seed=1",
                "~hydra.sweeper.tune.test.scannet0470", f"hydra.sweep.dir={sweep}")
    assert p.returncode == 0, p.stderr[-3000:]
    assert "sweep: 4 jobs" in p.stdout and "4 of 4 jobs ok" in p.stdout
    assert "validation runs (2):" in p.stdout and "test runs (2):" in p.stdout
    record = json.loads((sweep / "tune.json").read_text())
    jobs = {d.name: json.loads((d / "summary.json").read_text()) for d in sweep.iterdir() if (d / "summary.json").is_file()}
    cfgs = {name: (sweep / name / ".hydra" / "config.yaml").read_text() for name in jobs}
    val = [j for t in record["trials"] for j in t["jobs"]]
    test = [t["job"] for t in record["test_jobs"]]
    assert len(val) == 2 and len(test) == 2 and set(val) | set(test) == set(jobs)
    assert all(jobs[j]["split"] == "validation" and "seed: 4\n" in cfgs[j] for j in val)  # not the command line's 0
    assert all(jobs[j]["split"] == "test" and "seed: 1\n" in cfgs[j] for j in test)
    best = max(record["trials"], key=lambda t: t["value"])
    assert record["best"]["overrides"] == best["overrides"] and record["best"]["value"] == best["value"]
    weight = float(best["overrides"][0].split("=")[1])
    preset = sweep / record["preset"]
    assert f"tikhonov: {weight}" in preset.read_text() and "- /lifter: tikhonov" in preset.read_text()
    first_test = min((sweep / j / ".hydra" / "config.yaml").stat().st_mtime_ns for j in test)
    assert preset.stat().st_mtime_ns <= first_test
    tuned, diffuser = (next(t for t in record["test_jobs"] if t["arm"] == a) for a in ("tuned", "diffuser"))
    assert f"tikhonov: {weight}\n" in cfgs[tuned["job"]] and "name: exact" in cfgs[tuned["job"]]
    assert "tikhonov: 0.0\n" in cfgs[diffuser["job"]] and "name: jacobi" in cfgs[diffuser["job"]]
    assert jobs[tuned["job"]]["metrics"]["miou"] == pytest.approx(tuned["value"])
    # the preset is the configuration the test ran: loaded by its search path, the same solver keys
    from conftest import compose

    loaded = compose(f"hydra.searchpath=[file://{Path(sweep).resolve()}]", "+tuned=tune_tikhonov")
    assert loaded.solver.tikhonov == weight and loaded.solver.name.value == "exact"
