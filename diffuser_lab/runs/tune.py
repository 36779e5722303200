"""Tuning that never sees the test: a parameter search on validation runs, its best configuration
written as a preset, then run on held-out test runs beside what it is compared with.

With ``hydra.sweeper.tune`` set, the project's sweeper (``hydra_plugins/diffuser_lab_sweeper``)
runs :func:`search` (Optuna's TPE sampler, the ``tune`` extra) with these keys of it:

- ``params``: {key: search space}, in Hydra's override grammar as Hydra's Optuna sweeper spells
  them: ``interval(a, b)`` (float), ``tag(log, interval(a, b))`` (log-uniform), ``int(interval(a,
  b))``, ``range(a, b[, step])``, ``choice(a, b)`` or ``a,b``; a plain value is fixed;
- ``validation``, ``test``: named sets of jobs, {set: {key: value}}, a comma list a grid
  (``{demo: {seed: "3,4,5"}}``: three jobs). Each trial runs every validation job with its params
  (``split=validation``); its objective is the mean of their mIoU (a job's return value);
- ``compare``: {name: {key: value}}, configurations run beside the tuned one on every test job;
- ``n_trials``, ``n_startup_trials`` (TPE's random trials before it models), ``seed`` (the
  sampler's, through :mod:`diffuser_lab.seeding`), ``direction``, ``n_jobs`` (trials whose jobs
  are launched together: a parallel launcher runs them side by side);
- ``extends``: defaults entries the preset starts from (``["/lifter: tikhonov"]``).

A job's overrides, a later one winning on the same key: the command line's, the set's, the compare
arm's or the trial's params, then ``split=validation`` or ``split=test`` (summary.json's ``split``):
a command line ``seed=0`` cannot turn a validation job into a test one. After the search the best
trial's params are written as a preset, ``<sweep dir>/tuned/<experiment>.yaml`` (:func:`preset_text`),
then the test jobs run: the tuned configuration (the experiment's own with the preset's values) and
each ``compare`` arm on each test job. ``<sweep dir>/tune.json`` keeps the trials, the choice and the
test jobs (:data:`RECORD`). No test job runs before the choice is written.
"""
from __future__ import annotations

import json
import math
import statistics
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Optional, Sequence

import yaml

from diffuser_lab import seeding
from diffuser_lab.progress import say

__all__ = ["TuneSpec", "TuneError", "set_jobs", "merge", "count_jobs", "preset_text", "search", "RECORD", "PRESET_GROUP"]

RECORD = "tune.json"
"""The search's record in the sweep folder: space, trials (overrides, jobs, value), choice, test jobs."""
PRESET_GROUP = "tuned"
"""The preset's config group (a folder of the sweep dir: ``hydra.searchpath=[file://<sweep dir>] +tuned=<name>``)."""
SIGNIFICANT = 3
"""A float param is tried at this many significant digits (its override and the preset read as written)."""


class TuneError(ValueError):
    """A tuning sweep's config that cannot run; the message names the key."""


@dataclass
class TuneSpec:
    """``hydra.sweeper.tune``'s keys (module doc), checked: one :class:`TuneError` line naming the key."""

    params: dict = field(default_factory=dict)
    validation: dict = field(default_factory=dict)
    test: dict = field(default_factory=dict)
    compare: dict = field(default_factory=dict)
    n_trials: int = 8
    n_startup_trials: int = 4
    seed: int = 0
    direction: str = "maximize"
    n_jobs: int = 1
    extends: list = field(default_factory=list)

    def __post_init__(self) -> None:
        plain = _plain
        self.params, self.validation, self.test = plain(self.params), plain(self.validation), plain(self.test)
        self.compare, self.extends = plain(self.compare), list(plain(self.extends) or [])
        if not self.params:
            raise TuneError("hydra.sweeper.tune.params: expected at least one key to search, e.g. "
                            "solver.tikhonov: tag(log, interval(1e-4, 1))")
        for name in ("validation", "test"):
            sets = getattr(self, name)
            if not isinstance(sets, dict) or not sets or not all(isinstance(v, dict) and v for v in sets.values()):
                raise TuneError(f"hydra.sweeper.tune.{name}: expected named sets of jobs {{set: {{key: value}}}}, "
                                f"got {sets!r}")
        if not isinstance(self.compare, dict) or not all(isinstance(v, dict) for v in self.compare.values()):
            raise TuneError(f"hydra.sweeper.tune.compare: expected {{name: {{key: value}}}}, got {self.compare!r}")
        if self.direction not in ("maximize", "minimize"):
            raise TuneError(f"hydra.sweeper.tune.direction={self.direction!r}: expected maximize or minimize")
        for key in ("n_trials", "n_jobs"):
            if int(getattr(self, key)) < 1:
                raise TuneError(f"hydra.sweeper.tune.{key}={getattr(self, key)!r}: expected >= 1")
        if int(self.n_startup_trials) < 0:
            raise TuneError(f"hydra.sweeper.tune.n_startup_trials={self.n_startup_trials!r}: expected >= 0")


def _plain(node: Any) -> Any:
    """A DictConfig / ListConfig (or plain data) as plain dicts and lists."""
    try:
        from omegaconf import OmegaConf

        if OmegaConf.is_config(node):
            return OmegaConf.to_container(node, resolve=True)
    except ImportError:  # pragma: no cover - omegaconf is a dependency
        pass
    return node if node is not None else {}


def _parser():
    from hydra.core.override_parser.overrides_parser import OverridesParser

    return OverridesParser.create()


def _items(keys: Mapping[str, Any]) -> list[str]:
    """{key: value} -> ``key=value`` strings (a YAML list: a comma list)."""
    return [f"{k}={','.join(map(str, v)) if isinstance(v, (list, tuple)) else v}" for k, v in keys.items()]


def set_jobs(sets: Mapping[str, Mapping[str, Any]]) -> list[tuple[str, list[str]]]:
    """(set name, the job's overrides) of every job of named sets, in order: each set's comma lists
    as a grid (Hydra's basic sweeper's expansion)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper

    out = []
    for name, keys in sets.items():
        try:
            grid = BasicSweeper.split_arguments(_parser().parse_overrides(_items(keys)), None)[0]
        except Exception as exc:  # noqa: BLE001 - the grammar's error, one line naming the set
            raise TuneError(f"hydra.sweeper.tune set {name!r}: {str(exc).splitlines()[0]}") from None
        out += [(name, list(job)) for job in grid]
    return out


def _key(override: str) -> str:
    """An override's key without its ``+``/``++``/``~`` (``+lifter=x`` and ``lifter=y`` are one key)."""
    return override.split("=", 1)[0].lstrip("+~")


def merge(*parts: Sequence[str]) -> list[str]:
    """Overrides of ``parts`` in order, a later one replacing an earlier one of the same key (in its place)."""
    out: dict[str, str] = {}
    for part in parts:
        for o in part:
            out[_key(o)] = o
    return list(out.values())


def command_line(arguments: Sequence[str]) -> list[str]:
    """The command line's overrides; a sweep there is refused (the sets and params are the sweep)."""
    overrides = _parser().parse_overrides(list(arguments))
    sweeps = [o.input_line for o in overrides if o.is_sweep_override()]
    if sweeps:
        raise TuneError(f"hydra.sweeper.tune: {', '.join(sweeps)} on the command line is a sweep; the search's jobs are "
                        f"hydra.sweeper.tune.validation / test / params")
    return list(arguments)


def count_jobs(spec: TuneSpec) -> int:
    """The sweep's jobs: n_trials x the validation jobs + the test jobs x (1 + the compare arms)."""
    return int(spec.n_trials) * len(set_jobs(spec.validation)) + len(set_jobs(spec.test)) * (1 + len(spec.compare))


# --------------------------------------------------------------------------- the search space

def space(params: Mapping[str, Any]) -> tuple[dict, list[str]]:
    """({key: Optuna distribution} searched, [fixed ``key=value`` overrides]) of ``params``."""
    import optuna.distributions as od
    from hydra.core.override_parser.types import ChoiceSweep, IntervalSweep, RangeSweep

    dists, fixed = {}, []
    for item in _items(params):
        o = _parser().parse_override(item)
        key, v = o.get_key_element(), o.value()
        if isinstance(v, IntervalSweep):
            log, ints = "log" in v.tags, isinstance(v.start, int) and isinstance(v.end, int)
            if log and not v.start > 0:
                raise TuneError(f"hydra.sweeper.tune.params.{key}={item.split('=', 1)[1]}: a log interval starts above 0")
            dists[key] = (od.IntDistribution(int(v.start), int(v.end), log=log) if ints
                          else od.FloatDistribution(float(v.start), float(v.end), log=log))
        elif isinstance(v, RangeSweep):
            r = list(v.range())
            dists[key] = od.CategoricalDistribution(r)
        elif isinstance(v, ChoiceSweep):
            dists[key] = od.CategoricalDistribution(list(v.list))
        else:
            fixed.append(item)
    if not dists:
        raise TuneError(f"hydra.sweeper.tune.params {dict(params)!r}: nothing to search (expected an interval, range or choice)")
    return dists, fixed


def _value(x: Any) -> str:
    """A tried value as its override writes it: a float at :data:`SIGNIFICANT` digits."""
    if isinstance(x, float):
        return f"{x:.{SIGNIFICANT}g}"
    return str(x)


def trial_overrides(values: Mapping[str, Any], fixed: Sequence[str] = ()) -> list[str]:
    """The overrides of one trial's ``values`` ({key: value}) and the ``fixed`` params."""
    return [*fixed, *(f"{k}={_value(v)}" for k, v in values.items())]


def representative(dists: Mapping[str, Any]) -> dict:
    """A value of each distribution (its low end, its first choice): the start-up check's trial."""
    return {k: d.choices[0] if hasattr(d, "choices") else d.low for k, d in dists.items()}


def sampler_seed(seed: int) -> int:
    """The TPE sampler's seed (numpy draws inside Optuna keyed through :mod:`diffuser_lab.seeding`)."""
    return int(seeding.rng(int(seed), "tune.sampler").integers(2 ** 31))


# --------------------------------------------------------------------------- the preset

def preset_text(overrides: Sequence[str], extends: Sequence[Any], header: Sequence[str]) -> str:
    """A ``# @package _global_`` config: ``header`` as comments, the ``extends`` defaults entries
    (``"/lifter: tikhonov"`` or a dict) then ``_self_``, and the ``key=value`` ``overrides`` as nested keys."""
    from omegaconf import OmegaConf

    body: dict[str, Any] = {}
    if extends:
        entries = []
        for e in extends:
            if isinstance(e, str) and ":" in e:
                k, v = e.split(":", 1)
                entries.append({k.strip(): v.strip()})
            else:
                entries.append(e)
        body["defaults"] = [*entries, "_self_"]
    keys = OmegaConf.to_container(OmegaConf.from_dotlist([o.lstrip("+") for o in overrides]))
    body.update(keys)
    lines = ["# @package _global_", *(f"# {h}" for h in header)]
    return "\n".join(lines) + "\n" + yaml.safe_dump(body, sort_keys=False, default_flow_style=False)


# --------------------------------------------------------------------------- the search

@dataclass
class Trial:
    number: int
    overrides: list[str]
    jobs: list[str] = field(default_factory=list)  # the jobs' folders (sweep dir relative)
    values: list[Optional[float]] = field(default_factory=list)
    value: Optional[float] = None  # the objective: the mean of the jobs' values; None: a job failed
    error: str = ""


def _returns(results) -> list[tuple[str, Optional[float], str]]:
    """(job folder name, its value or None, why it has none) of launched jobs."""
    out = []
    for r in results:
        hc = getattr(r, "hydra_cfg", None)
        out_dir = hc.hydra.runtime.output_dir if hc is not None else getattr(r, "working_dir", "")
        name = Path(str(out_dir or "")).name
        try:
            v = r.return_value  # raises the job's exception when it failed
        except Exception as exc:  # noqa: BLE001 - a failed job: its trial fails, the search goes on
            out.append((name, None, f"{type(exc).__name__}: {(str(exc).splitlines() or [''])[0]}"))
            continue
        ok = isinstance(v, (int, float)) and math.isfinite(v)
        out.append((name, float(v) if ok else None, "" if ok else "no mIoU (a scene without ground truth?)"))
    return out


def _jobs_text(jobs: Sequence[tuple[str, list[str]]]) -> str:
    """``demo: seed=3; demo: seed=4`` of (set, overrides) jobs."""
    return "; ".join(f"{s}: {' '.join(j)}" for s, j in jobs)


def _mean_std(xs: Sequence[float]) -> str:
    """``mean ± std`` as the sweep's table writes it (the standard deviation of the values themselves)."""
    return f"{statistics.fmean(xs):.1f} ± {statistics.pstdev(xs):.1f}" if len(xs) > 1 else f"{xs[0]:.1f}"


def _best(trials: Sequence[Trial], direction: str) -> Optional[Trial]:
    """The completed trial of the best value (ties: the earliest), None if none completed."""
    done = [t for t in trials if t.value is not None]
    return (max if direction == "maximize" else min)(done, key=lambda t: t.value) if done else None


def search(spec: TuneSpec, arguments: Sequence[str], launch: Callable, validate: Callable, sweep_dir: Path,
           name: str) -> dict:
    """Run the search (module doc): ``launch(job_overrides, initial_job_idx)`` the launcher's,
    ``validate(job_overrides)`` the start-up composition of a covering of the jobs; ``name`` the
    preset's (the experiment). Returns the record written to :data:`RECORD`; raises
    :class:`TuneError` when no trial completed or a test job failed (after the record is written)."""
    try:
        import optuna
    except ImportError:
        raise TuneError("hydra.sweeper.tune needs Optuna: pip install -e '.[tune]'") from None

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    # every job in this sweep's folder: its name may interpolate the job's own choices (the scene)
    cmd = [*command_line(arguments), f"hydra.sweep.dir='{sweep_dir}'"]
    dists, fixed = space(spec.params)
    val_jobs, test_jobs = set_jobs(spec.validation), set_jobs(spec.test)
    arms = {"": []} | {k: _items(v) for k, v in spec.compare.items()}
    sample = trial_overrides(representative(dists), fixed)
    validate([merge(cmd, job, sample, ["split=validation"]) for _, job in val_jobs]
             + [merge(cmd, job, arm, ["split=test"]) for _, job in test_jobs for arm in arms.values()])
    sweep_dir.mkdir(parents=True, exist_ok=True)
    say(f"tune: {spec.n_trials} trials of {', '.join(dists)} on {len(val_jobs)} validation jobs "
        f"({_jobs_text(val_jobs)}), then the best and {len(arms) - 1} compared on {len(test_jobs)} test jobs")
    trials = _trials(optuna, spec, dists, fixed, [merge(cmd, job) for _, job in val_jobs], launch)
    record: dict[str, Any] = {
        "experiment": name, "direction": spec.direction, "params": {k: str(v) for k, v in spec.params.items()},
        "sampler": {"kind": "tpe", "seed": int(spec.seed), "n_startup_trials": int(spec.n_startup_trials)},
        "validation": {s: [" ".join(j) for t, j in val_jobs if t == s] for s in spec.validation},
        "test": {s: [" ".join(j) for t, j in test_jobs if t == s] for s in spec.test},
        "compare": {k: " ".join(v) for k, v in arms.items() if k},
        "trials": [vars(t) for t in trials], "best": None, "preset": None, "test_jobs": []}
    best = _best(trials, spec.direction)
    if best is None:
        _write(sweep_dir, record)
        raise TuneError(f"tune: none of the {len(trials)} trials completed (first: {trials[0].error}); no test job ran")
    preset = sweep_dir / PRESET_GROUP / f"{name}.yaml"
    preset.parent.mkdir(parents=True, exist_ok=True)
    header = [f"hydra.sweeper.tune, {name}: trial {best.number + 1} of {len(trials)}, the best mean validation mIoU "
              f"{best.value:.2f} ({' '.join(best.overrides)})",
              f"validation: {_jobs_text(val_jobs)}",
              f"load it: diffuser-lab 'hydra.searchpath=[file://{sweep_dir.resolve()}]' +{PRESET_GROUP}={name}"]
    preset.write_text(preset_text(best.overrides, spec.extends, header))
    record["best"] = {"trial": best.number, "overrides": best.overrides, "value": best.value}
    record["preset"] = str(preset.relative_to(sweep_dir))
    _write(sweep_dir, record)
    say(f"tune: chose {' '.join(best.overrides)} (trial {best.number + 1}, validation mIoU {best.value:.2f}) -> {preset}")
    # the held-out jobs, only now: the tuned configuration and each compared one on every test job
    jobs, tags = [], []
    for s, job in test_jobs:
        for arm, extra in arms.items():
            jobs.append(merge(cmd, job, extra or best.overrides, ["split=test"]))
            tags.append((s, arm or "tuned"))
    got = _returns(launch(jobs, sum(len(t.jobs) for t in trials)))
    record["test_jobs"] = [{"set": s, "arm": a, "job": g[0], "value": g[1], "error": g[2]} for (s, a), g in zip(tags, got)]
    _write(sweep_dir, record)
    for arm in ["tuned", *[a for a in arms if a]]:
        for s in spec.test:
            xs = [g[1] for (ts, a), g in zip(tags, got) if a == arm and ts == s and g[1] is not None]
            if xs:
                say(f"tune: test {s}: {arm} mIoU {_mean_std(xs)} ({len(xs)} jobs)")
    failed = [g for g in got if g[1] is None]
    if failed:
        raise TuneError(f"tune: {len(failed)} of {len(got)} test jobs failed (first {failed[0][0]}: {failed[0][2]})")
    return record


def _trials(optuna, spec: TuneSpec, dists: dict, fixed: list[str], val_jobs: list[list[str]],
            launch: Callable) -> list[Trial]:
    """``spec.n_trials`` trials, ``spec.n_jobs`` at a time: each asked of the TPE sampler, its
    validation jobs (``val_jobs``' overrides, its values, ``split=validation``) launched, told their
    mean (a trial with a failed job: failed); a line per trial."""
    sampler = optuna.samplers.TPESampler(seed=sampler_seed(spec.seed), n_startup_trials=int(spec.n_startup_trials))
    study = optuna.create_study(direction=spec.direction, sampler=sampler)
    trials: list[Trial] = []
    idx = 0
    while len(trials) < spec.n_trials:
        batch = []
        for _ in range(min(int(spec.n_jobs), spec.n_trials - len(trials))):
            t = study.ask(dists)
            batch.append((t, Trial(t.number, trial_overrides(t.params, fixed))))
        jobs = [merge(job, tr.overrides, ["split=validation"]) for _, tr in batch for job in val_jobs]
        got = _returns(launch(jobs, idx))
        idx += len(jobs)
        for k, (t, tr) in enumerate(batch):
            mine = got[k * len(val_jobs):(k + 1) * len(val_jobs)]
            tr.jobs, tr.values = [g[0] for g in mine], [g[1] for g in mine]
            errors = [g[2] for g in mine if g[1] is None]
            if errors:
                tr.error = errors[0]
                study.tell(t, state=optuna.trial.TrialState.FAIL)
            else:
                tr.value = statistics.fmean(tr.values)
                study.tell(t, tr.value)
            trials.append(tr)
            best = _best(trials, spec.direction)
            say(f"tune: trial {tr.number + 1}/{spec.n_trials} {' '.join(tr.overrides)}: " +
                (f"validation mIoU {tr.value:.2f} ({len(tr.values)} jobs)" if tr.value is not None else
                 f"FAILED ({tr.error})") + (f"; best {best.value:.2f} (trial {best.number + 1})" if best else ""))
    return trials


def _write(sweep_dir: Path, record: dict) -> None:
    (sweep_dir / RECORD).write_text(json.dumps(record, indent=1) + "\n")
