"""Paired comparisons of runs: each configuration against a reference row over the seeds and scenes
both ran, and every method scored on the points all of them label (the common support).

    python -m analysis.paired --x 54.4,54.7,53.6 --y 42.3,39.1,40.1   # x - y, pairs matched by position

prints the mean paired difference, its 95 % bootstrap interval and the sign-flip p-value of
numbers given by hand (a results page's per-seed figures); :mod:`analysis.report` and
:mod:`analysis.compare` compute the same from run folders.

The statistics (docs/sweeps.md, "Paired comparisons"): the n differences d_i = config - reference
at matched units (seed, scene); the mean of d; a percentile bootstrap interval of the mean
(``scipy.stats.bootstrap``, 9,999 resamples of the pairs); the two-sided sign-flip p-value
(``scipy.stats.permutation_test``, ``permutation_type='samples'`` on the one sample d: every d_i's
sign flipped, exact over all 2^n flips up to n = 16 pairs). Significant: the interval excludes 0
and p < 0.05; with n pairs the smallest p is 2 / 2^n (0.25 at 3, 0.0625 at 5), so with 5 pairs or
fewer no difference is significant: a statement about the design, not the methods. Every draw is
keyed by :mod:`diffuser_lab.seeding` with the differences themselves: the same differences give the
same interval in a report, a group comparison and this command.
"""
from __future__ import annotations

import argparse
import inspect
import math
import sys
import zlib
from dataclasses import dataclass, field
from enum import Enum
from functools import lru_cache
from pathlib import Path
from typing import Iterable, Optional

import numpy as np

from analysis.plots import sort_key
from analysis.runs import SEED_KEYS, Run, find_runs, is_nan, number
from diffuser_lab import seeding
from diffuser_lab.data.arrays import read_array
from diffuser_lab.data.scene import IGNORE
from diffuser_lab.method.metrics import confusion_matrix, scores_from_confusion
from diffuser_lab.runs.records import BAYESIAN_FILE, GT_FILE
from diffuser_lab.runs.results import METRICS, SPLIT, config_value

CONFIDENCE = 0.95
ALPHA = 0.05
RESAMPLES = 9999  # bootstrap resamples; sign flips drawn when 2^n exceeds 2^EXACT_PAIRS
EXACT_PAIRS = 16
STATS_SEED = 0  # the key prefix of the resampling's draws (seeding.rng)
UNIT_KEYS = (*SEED_KEYS, "scene", "scene.options.root", "scene.options.path")
"""Override keys that name a unit a configuration is repeated on (a seed, a scene): the pairs' keys."""
REFERENCE_OPTIONS = {"lifter": "diffuser"}
"""Optional config groups (``+lifter=``) whose option is the default run (conf/lifter/diffuser.yaml)."""
COMMON = {"miou_common": "miou", "accuracy_common": "accuracy",
          "bayesian_miou_common": "bayesian miou", "bayesian_accuracy_common": "bayesian accuracy"}
"""The common support's scores of a run (:func:`common_support`), by name."""
PAIRED_METRICS = ("miou", "accuracy", "coverage", "miou_common", "accuracy_common")
CALIBRATION = ("ece", "nll", "brier")
SPLITS = ("validation", "test")


# --- the statistics ------------------------------------------------------------------------------

@dataclass(frozen=True)
class Difference:
    """The paired difference (a - b) of one metric over ``n`` matched units, in the metric's unit
    (percentage points for mIoU, accuracy, coverage, ECE).

    Attributes:
        n: pairs; mean: mean of the n differences (None when n = 0);
        low, high: the 95 % percentile bootstrap interval of the mean (None when n < 2);
        p: two-sided sign-flip p-value (None when n = 0); exact: p from all 2^n sign flips.
    """

    n: int
    mean: Optional[float] = None
    low: Optional[float] = None
    high: Optional[float] = None
    p: Optional[float] = None
    exact: bool = True

    @property
    def significant(self) -> bool:
        """The interval excludes 0 and p < :data:`ALPHA`."""
        return (self.low is not None and (self.low > 0 or self.high < 0)) and self.p is not None and self.p < ALPHA

    @property
    def why(self) -> str:
        """Why the difference is not significant ('' when it is)."""
        if self.significant:
            return ""
        if self.n < 2:
            return f"{self.n} pair" + ("" if self.n == 1 else "s")
        if self.low <= 0 <= self.high:
            return "interval crosses 0"
        floor = 2.0 / 2 ** self.n
        return f"p {self.p:.2g} >= {ALPHA}" + (f" (smallest p at {self.n} pairs: {floor:.2g})" if floor >= ALPHA else "")

    def cell(self, digits: int = 1) -> str:
        """``+4.7 [+2.1, +7.3] p 0.031``, ``n.s.`` appended when not significant; ``-`` without pairs."""
        if self.mean is None:
            return "-"
        f = f"{{:+.{digits}f}}"
        text = f.format(self.mean)
        if self.low is not None:
            text += f" [{f.format(self.low)}, {f.format(self.high)}]"
        text += f" p {self.p:.2g}"
        return text if self.significant else text + " n.s."

    def as_dict(self) -> dict:
        return {"n": self.n, "mean": self.mean, "low": self.low, "high": self.high, "p": self.p,
                "exact": self.exact, "significant": self.significant, "why": self.why}


def _mean(x, axis=-1):
    return np.mean(x, axis=axis)


def _rng(fn, d: np.ndarray, what: str) -> dict:
    """scipy's keyword (``rng``; ``random_state`` before scipy 1.15) for a Generator keyed by the
    differences themselves: the same differences get the same interval wherever they are computed
    (a report, a group comparison, ``python -m analysis.paired``)."""
    gen = seeding.rng(STATS_SEED, f"analysis.paired.{what}", zlib.crc32(np.ascontiguousarray(d, "<f8").tobytes()))
    return {"rng" if "rng" in inspect.signature(fn).parameters else "random_state": gen}


def paired_difference(d: Iterable[float]) -> Difference:
    """The mean of the paired differences ``d`` ((n,) a - b per unit; NaN / None left out), its
    bootstrap interval and sign-flip p-value (module docstring)."""
    from scipy import stats

    d = np.array([np.nan if is_nan(x) else float(x) for x in d], float)
    d = d[np.isfinite(d)]
    n = int(d.size)
    if n == 0:
        return Difference(0)
    mean = float(d.mean())
    low = high = None
    if n >= 2 and np.ptp(d) == 0:  # every resample has this mean (scipy warns on a constant sample)
        low = high = mean
    elif n >= 2:
        ci = stats.bootstrap((d,), _mean, vectorized=True, confidence_level=CONFIDENCE, n_resamples=RESAMPLES,
                             method="percentile", **_rng(stats.bootstrap, d, "bootstrap")).confidence_interval
        low, high = float(ci.low), float(ci.high)
    if n == 1:  # the two flips +d and -d: each as extreme as the other
        return Difference(1, mean, None, None, 1.0, True)
    exact = n <= EXACT_PAIRS
    res = stats.permutation_test((d,), _mean, vectorized=True, permutation_type="samples", alternative="two-sided",
                                 n_resamples=np.inf if exact else RESAMPLES, **_rng(stats.permutation_test, d, "flips"))
    return Difference(n, mean, low, high, float(min(1.0, res.pvalue)), exact)


# --- units, configurations, the reference --------------------------------------------------------

def unit_of(run: Run) -> tuple[str, ...]:
    """The unit a run repeats its configuration on: its seed and scene (:data:`UNIT_KEYS`; the
    scene option from .hydra when not overridden)."""
    out = []
    for k in UNIT_KEYS:
        v = run.overrides.get(k, "")
        if k == "scene" and not v:
            v = run.hydra_choices.get("scene", "")
        elif k in SEED_KEYS and not v:  # not overridden: the default seed (seed=0 given or not: one unit)
            v = str(default_value(k))
        out.append(v)
    return tuple(out)


def unit_label(unit: tuple[str, ...]) -> str:
    return ", ".join(f"{k}={v}" for k, v in zip(UNIT_KEYS, unit) if v) or "one unit"


def config_keys(runs: list[Run]) -> list[str]:
    """The keys that vary between the runs' configurations (overrides, not the units'; ``split``
    when summary.json has one), sorted."""
    keys = {k for r in runs for k in r.overrides if k not in UNIT_KEYS}
    keys |= {SPLIT} if any(r.summary.get(SPLIT) for r in runs) else set()
    return sorted(k for k in keys if len({config_value(r, k) for r in runs}) > 1)


def config_label(config: dict) -> str:
    return ", ".join(f"{k}={v}" for k, v in config.items()) or "all runs"


@lru_cache(maxsize=1)
def _group_defaults() -> dict[str, str]:
    """conf/config.yaml's default option of each config group (``method: diffuser``, ...)."""
    import yaml

    from diffuser_lab.cli.main import config_dir

    doc = yaml.safe_load((Path(config_dir()) / "config.yaml").read_text()) or {}
    out = dict(REFERENCE_OPTIONS)
    for item in doc.get("defaults") or []:
        if isinstance(item, dict):
            for k, v in item.items():
                if not str(k).startswith("override") and v is not None:
                    out[str(k)] = str(v)
    return out


def default_value(key: str):
    """The default run's value of an override key (a group's option, a schema key's default; the
    paper's values), or None when the default run has none."""
    groups = _group_defaults()
    if key in groups:
        return groups[key]
    from diffuser_lab.config import default_config

    node = default_config()
    for part in key.split("."):
        node = node.get(part) if isinstance(node, dict) else getattr(node, part, None)
        if node is None:
            return None
    return node


def _is_default(value: str, default) -> bool:
    if default is None:
        return False
    if isinstance(default, bool):
        return value.lower() == str(default).lower()
    if isinstance(default, Enum):
        return value in (default.name, str(default.value))
    if isinstance(default, (int, float)):
        n = number(value)
        return isinstance(n, (int, float)) and not isinstance(n, bool) and math.isclose(n, default, rel_tol=1e-9)
    return value == str(default)


def parse_assignments(items: Iterable[str], what: str = "--reference") -> dict[str, str]:
    """``["graph.k=16", "a=1,b=2"]`` -> ``{"graph.k": "16", "a": "1", "b": "2"}`` (``+`` dropped)."""
    out = {}
    for item in items:
        for part in str(item).split(","):
            key, eq, value = part.partition("=")
            if not eq or not key.strip():
                raise ValueError(f"{what} {item}: expected KEY=VALUE (a swept key and one of its values)")
            out[key.strip().lstrip("+~")] = value.strip()
    return out


def choose_reference(runs: list[Run], keys: list[str], named: Optional[dict] = None) -> tuple[dict, str]:
    """The reference's values of the reference keys and a sentence saying how they were chosen.

    ``named`` (``--reference``): those keys and values (each must be a varying key with that value
    among the runs'). Otherwise every varying key whose default (the paper's value) is among its
    values; when none is, the first configuration's value of the first key. The other varying
    keys are held equal within a pair."""
    values = {k: sorted({config_value(r, k) for r in runs}, key=lambda v: sort_key(k, v)) for k in keys}
    if named:
        for k, v in named.items():
            if k not in values:
                raise ValueError(f"--reference {k}={v}: {k} is not a key the runs vary"
                                 + (f" (they vary: {', '.join(keys)})" if keys else " (they vary none)"))
            if v not in values[k]:
                raise ValueError(f"--reference {k}={v}: no run has {k}={v} (values: {', '.join(values[k])})")
        return dict(named), f"`{config_label(named)}` (named with --reference)"
    ref = {}
    for k in keys:
        hit = [v for v in values[k] if _is_default(v, default_value(k))]
        if hit:
            ref[k] = hit[0]
    if ref:
        return ref, f"`{config_label(ref)}` (the default run's, the paper's values; another: `--reference KEY=VALUE`)"
    if not keys:
        return {}, "none (the runs vary no key)"
    first = {keys[0]: values[keys[0]][0]}
    return first, (f"`{config_label(first)}` (the first row: no row has the default run's values; "
                   "another: `--reference KEY=VALUE`)")


# --- the common support --------------------------------------------------------------------------

@dataclass
class Support:
    """Every run scored on the points all compared runs label at its unit.

    Attributes:
        scores: run folder -> {``miou_common``, ``accuracy_common`` and, with the run's
            bayesian_labels.npy, ``bayesian_miou_common``, ``bayesian_accuracy_common``} (percent).
        sizes: (unit label, points in the support, points) per unit and point set.
        left_out: one line per run not on a support (why).
        baseline: whether the runs' Bayesian baselines are among the compared labels.
    """

    scores: dict = field(default_factory=dict)
    sizes: list = field(default_factory=list)
    left_out: list = field(default_factory=list)
    baseline: bool = False

    def line(self) -> str:
        """How large the common support is (one sentence), '' when there is none."""
        if not self.sizes:
            return ""
        share = np.array([100.0 * s / max(n, 1) for _, s, n in self.sizes])
        who = "every compared run" + (" and every run's Bayesian baseline" if self.baseline else "")
        lo, hi = share.min(), share.max()
        spread = "" if len(share) == 1 else f"{lo:.1f}-{hi:.1f} % over {len(share)} seeds and scenes; "
        first = self.sizes[0]
        return (f"Common support: the points that {who} label (per seed and scene): {share.mean():.1f} % of the "
                f"points ({spread}{first[1]:,} of {first[2]:,} at {first[0]}).")


def _load_labels(path: Path, n: Optional[int] = None) -> np.ndarray:
    a = read_array(path, "labels", role=None)
    if a.ndim != 1 or a.dtype.kind not in "iu" or (n is not None and a.size != n):
        want = f"({n},)" if n is not None else "(N,)"
        raise ValueError(f"{path}: shape {a.shape} dtype {a.dtype}, expected {want} integer class ids (-1 = unlabeled)")
    return a.astype(np.int64)


def _scores(pred: np.ndarray, gt: np.ndarray, n_classes: int) -> tuple[float, float]:
    s = scores_from_confusion(confusion_matrix(pred, gt, n_classes), [str(c) for c in range(n_classes)])
    return s["miou"], s["accuracy"]


def common_support(runs: list[Run], unit=unit_of) -> Support:
    """Score each finished run's labels.npy (and bayesian_labels.npy) on the points that every run
    of its unit (``unit(run)``, default :func:`unit_of`) labels, with the project's metrics
    (:mod:`diffuser_lab.method.metrics`); runs of one unit on different point sets (other ground
    truth) get one support per point set."""
    out = Support()
    groups: dict[tuple, list] = {}
    for r in runs:
        if r.status != "ok":
            continue
        if not (r.path / "labels.npy").is_file() or not (r.path / GT_FILE).is_file():
            missing = "labels.npy" if not (r.path / "labels.npy").is_file() else GT_FILE
            out.left_out.append(f"`{r.path.name}`: no {missing}")
            continue
        gt = _load_labels(r.path / GT_FILE)
        key = (unit(r), gt.size, zlib.crc32(np.ascontiguousarray(gt).tobytes()))
        groups.setdefault(key, []).append((r, gt))
    for (u, n, _), members in groups.items():
        gt = members[0][1]
        labels, bayes = [], []
        for r, _ in members:
            lab = _load_labels(r.path / "labels.npy", n)
            b = _load_labels(r.path / BAYESIAN_FILE, n) if (r.path / BAYESIAN_FILE).is_file() else None
            labels.append(lab)
            bayes.append(b)
        stack = np.stack(labels + [b for b in bayes if b is not None])
        support = (stack != IGNORE).all(0)
        out.baseline = out.baseline or any(b is not None for b in bayes)
        out.sizes.append((unit_label(u), int(support.sum()), n))
        for (r, _), lab, b in zip(members, labels, bayes):
            c = int(r.summary.get("n_classes") or max(int(gt.max()), int(lab.max())) + 1)
            s = {}
            s["miou_common"], s["accuracy_common"] = _scores(lab[support], gt[support], c)
            if b is not None:
                s["bayesian_miou_common"], s["bayesian_accuracy_common"] = _scores(b[support], gt[support], c)
            out.scores[r.path] = s
    return out


# --- matching and the paired table ---------------------------------------------------------------

def metric(run: Run, name: str, support: Optional[Support] = None):
    """A run's value of a metric: a :data:`~diffuser_lab.runs.results.METRICS` name or a common
    support's (:data:`COMMON`); None when absent."""
    if name in COMMON:
        return None if support is None else support.scores.get(run.path, {}).get(name)
    v = run.metric(METRICS[name])
    return v if isinstance(v, (int, float)) and not is_nan(v) else None


@dataclass
class Row:
    """One configuration against its reference: ``diffs`` metric -> :class:`Difference` (config -
    reference), ``per_class`` class -> Difference of the IoU, ``pairs`` the matched units."""

    config: dict
    reference: dict
    diffs: dict
    per_class: dict
    pairs: list


@dataclass
class Comparison:
    """Every configuration of a set of runs against the reference (:func:`compare_configurations`).

    Attributes:
        keys: the varying configuration keys; reference: the reference keys' values; how: how the
        reference was chosen; held: the varying keys held equal within a pair; rows: one per
        configuration that is not a reference; references: the reference configurations;
        unmatched: one line per run without a partner; metrics: the metrics compared.
    """

    keys: list
    reference: dict
    how: str
    held: list
    rows: list
    references: list
    unmatched: list
    metrics: tuple


def _config(run: Run, keys: list[str]) -> tuple:
    return tuple(config_value(run, k) for k in keys)


def _by_unit(members: list[Run], unmatched: list[str]) -> dict:
    """unit -> the run (the first by path when a unit repeats: the others listed as duplicates)."""
    out = {}
    for r in sorted(members, key=lambda r: str(r.path)):
        u = unit_of(r)
        if u in out:
            unmatched.append(f"`{r.path.name}`: a second run at {unit_label(u)} (`{out[u].path.name}` used)")
        else:
            out[u] = r
    return out


def pair_up(a: list[Run], b: list[Run], unmatched: list[str], metrics: Iterable[str],
            support: Optional[Support] = None, what_b: str = "the reference") -> tuple[dict, dict, list]:
    """Differences a - b over the units both ran: (metric -> Difference, class -> Difference of
    the per-class IoU, the units). Runs of either side without a partner go to ``unmatched``."""
    ua, ub = _by_unit(a, unmatched), _by_unit(b, unmatched)
    units = sorted(set(ua) & set(ub))
    for u in sorted(set(ua) - set(ub)):
        unmatched.append(f"`{ua[u].path.name}`: no run of {what_b} at {unit_label(u)}")
    diffs = {}
    for m in metrics:
        d = [(metric(ua[u], m, support), metric(ub[u], m, support)) for u in units]
        diffs[m] = paired_difference([x - y for x, y in d if x is not None and y is not None])
    classes: dict[str, list] = {}
    for u in units:
        ia = ua[u].metric("metrics.per_class_iou") or {}
        ib = ub[u].metric("metrics.per_class_iou") or {}
        for c in ia:
            if c in ib:
                classes.setdefault(c, []).append(ia[c] - ib[c])
    per_class = {c: paired_difference(v) for c, v in classes.items()}
    return diffs, per_class, units


def metrics_of(runs: list[Run], support: Optional[Support] = None) -> tuple:
    """The metrics worth a paired difference for these runs: :data:`PAIRED_METRICS` (the common
    support's when there is one) and the calibration metrics when the runs have them."""
    have = [m for m in PAIRED_METRICS if m not in COMMON or (support is not None and support.scores)]
    ok = [r for r in runs if r.status == "ok"]
    have += [m for m in CALIBRATION if any(metric(r, m) is not None for r in ok)]
    return tuple(have)


def compare_configurations(runs: list[Run], reference: Optional[dict] = None,
                           support: Optional[Support] = None) -> Comparison:
    """Each configuration of the finished runs against the reference over matched units (module
    docstring); ``reference``: named keys and values (``--reference``), else the default run's."""
    ok = [r for r in runs if r.status == "ok"]
    keys = config_keys(ok)
    ref, how = choose_reference(ok, keys, reference)
    held = [k for k in keys if k not in ref]
    groups: dict[tuple, list[Run]] = {}
    for r in ok:
        groups.setdefault(_config(r, keys), []).append(r)
    order = sorted(groups, key=lambda cfg: tuple(sort_key(k, v) for k, v in zip(keys, cfg)))
    metrics = metrics_of(ok, support)
    rows, references, unmatched = [], [], []
    for cfg in order:
        config = dict(zip(keys, cfg))
        target = {**config, **ref}
        if target == config:
            references.append(config)
            continue
        mine = tuple(target[k] for k in keys)
        if mine not in groups:
            unmatched += [f"`{r.path.name}`: no reference run ({config_label(target)})" for r in groups[cfg]]
            rows.append(Row(config, target, {m: Difference(0) for m in metrics}, {}, []))
            continue
        diffs, per_class, units = pair_up(groups[cfg], groups[mine], unmatched, metrics,
                                          support, f"`{config_label(target)}`")
        rows.append(Row(config, target, diffs, per_class, units))
    return Comparison(keys, ref, how, held, rows, references, sorted(set(unmatched)), metrics)


def baseline_differences(runs: list[Run], support: Optional[Support] = None) -> list[tuple[dict, dict]]:
    """Each configuration's method against the Bayesian baseline of the same runs: (configuration,
    metric -> Difference of ``m - bayesian_m`` over its runs) for mIoU, the common support's mIoU
    and the calibration metrics the runs have."""
    ok = [r for r in runs if r.status == "ok"]
    keys = config_keys(ok)
    groups: dict[tuple, list[Run]] = {}
    for r in ok:
        groups.setdefault(_config(r, keys), []).append(r)
    pairs = [("miou", "bayesian_miou"), ("miou_common", "bayesian_miou_common")] + \
        [(m, f"bayesian_{m}") for m in CALIBRATION]
    out = []
    for cfg in sorted(groups, key=lambda c: tuple(sort_key(k, v) for k, v in zip(keys, c))):
        config = dict(zip(keys, cfg))
        diffs = {}
        for m, b in pairs:
            d = [(metric(r, m, support), metric(r, b, support)) for r in groups[cfg]]
            d = [x - y for x, y in d if x is not None and y is not None]
            if d:
                diffs[m] = paired_difference(d)
        if diffs:
            out.append((config, diffs))
    return out


def check_splits(runs: list[Run], mix: bool) -> None:
    """One line (ValueError) when the runs hold both splits (summary.json ``split``) and ``mix`` is off:
    a figure tuned on the validation runs must not sit in the test runs' table unasked."""
    counts = {s: sum(r.summary.get(SPLIT) == s for r in runs) for s in SPLITS}
    if all(counts.values()) and not mix:
        raise ValueError(f"runs of the validation and test splits in one table ({counts['validation']} validation, "
                         f"{counts['test']} test); pass --mix-splits to allow")


def digits(name: str) -> int:
    return 3 if name.endswith(("nll", "brier")) else 1


# --- numbers given by hand -----------------------------------------------------------------------

def _numbers(text: str, what: str) -> list[float]:
    try:
        return [float(x) for x in text.replace(" ", "").split(",") if x]
    except ValueError:
        raise ValueError(f"{what} {text}: expected comma-separated numbers, e.g. 54.4,54.7,53.6") from None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m analysis.paired", description=__doc__.splitlines()[0])
    ap.add_argument("--x", help="one value per unit (comma-separated)")
    ap.add_argument("--y", help="the other side's values at the same units, in the same order")
    ap.add_argument("--d", help="the differences x - y themselves (instead of --x and --y)")
    ap.add_argument("--digits", type=int, default=1, help="decimals printed (default 1)")
    a = ap.parse_args(argv)
    try:
        if a.d is not None:
            d = _numbers(a.d, "--d")
        elif a.x is not None and a.y is not None:
            x, y = _numbers(a.x, "--x"), _numbers(a.y, "--y")
            if len(x) != len(y):
                raise ValueError(f"--x has {len(x)} values, --y {len(y)}: expected one pair per unit")
            d = [u - v for u, v in zip(x, y)]
        else:
            raise ValueError("give --x and --y (values per unit) or --d (their differences)")
    except ValueError as exc:
        print(f"paired: error: {exc}", file=sys.stderr)
        return 2
    r = paired_difference(d)
    how = f"exact over {2 ** r.n} sign flips" if r.exact else f"{RESAMPLES} random sign flips"
    print(f"x - y over {r.n} pair{'' if r.n == 1 else 's'}: {r.cell(a.digits)} (95 % percentile bootstrap interval; two-sided sign-flip p, {how})")
    if not r.significant:
        print(f"not significant: {r.why}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    raise SystemExit(main())
