"""Run folders read back: their summaries, overrides, experiment and scene, and the sweep table
(one row per configuration, seeds as mean ± std). The CLI prints the table at the end of a sweep;
the scripts in ``analysis/`` build their CSVs, plots and reports on it."""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Iterable, Optional

import numpy as np

from diffuser_lab.backends import provenance
from diffuser_lab.data.inputs import manifest
from diffuser_lab.method.fusion import METHODS

SEED_KEYS = ("seed",)  # overrides that only repeat a configuration



def calibration_key(method: str, views: int) -> str:
    """The single-frame protocol's name of a Table II row in ``metrics.calibration``: ``diffuser_5v``."""
    return f"{method}_{views}v"


@dataclass
class Run:
    """One run folder: its summary and its command-line overrides as a dict (``raw_overrides``: the
    overrides as given, the ``+experiment=NAME`` preset included)."""

    path: Path
    summary: dict
    overrides: dict = field(default_factory=dict)
    raw_overrides: list = field(default_factory=list)

    @property
    def status(self) -> str:
        return self.summary.get("status", "unknown")

    @property
    def provenance(self) -> Optional[dict]:
        """summary.json's ``provenance`` block (machine, versions, commit), None in an older run's."""
        block = self.summary.get("provenance")
        return block if isinstance(block, dict) else None

    @property
    def inputs(self) -> dict[str, str]:
        """What the run read, by role: the manifest's sha256 (frames, predictions, feature maps) or
        the sha256 of a listed role's files' hashes (mesh, intrinsics, ...), and ``generator`` (a
        procedural scene's source and seed); {} in an older run's summary."""
        block = self.summary.get("inputs")
        if not isinstance(block, dict):
            return {}
        out = {role: m.get("sha256", "") for role, m in (block.get("manifests") or {}).items()}
        files: dict[str, list[str]] = {}
        for f in block.get("files") or []:
            files.setdefault(f.get("role", "?"), []).append(f.get("sha256", ""))
        out.update({role: manifest(hs) if len(hs) > 1 else hs[0] for role, hs in files.items()})
        gen = block.get("generator")
        if gen:
            out["generator"] = f"{gen.get('source')} seed {gen.get('seed')}"
        return out

    def metric(self, dotted: str):
        """A value of summary.json by dotted path, e.g. ``baseline.bayesian.miou``; None if absent.
        ``{method}`` / ``{bayesian}`` in the path stand for the run's method's / the Bayesian
        baseline's key in ``metrics.calibration`` (:meth:`calibration_key`)."""
        if "{" in dotted:
            dotted = dotted.format(method=self.calibration_key(str(self.summary.get("method", ""))),
                                   bayesian=self.calibration_key("bayesian"))
        node = self.summary
        for part in dotted.split("."):
            if not isinstance(node, dict) or part not in node:
                return None
            node = node[part]
        return node

    def calibration_key(self, method: str) -> str:
        """``method``'s key in ``metrics.calibration``: the method itself (global protocol) or its
        W-view row, e.g. ``diffuser_5v``, in a single-frame run (whose ``metrics`` is that row)."""
        if self.summary.get("protocol") == "single_frame":
            if method in METHODS:  # its widest row, as the summary's metrics / baseline.bayesian
                window = int(self.summary.get("window", 1))
                return calibration_key(method, max(METHODS[method].single_frame_rows(window)))
        return method

    @cached_property
    def hydra_choices(self) -> dict:
        """``hydra.runtime.choices`` of the job's .hydra/hydra.yaml (config group -> option); {} if absent."""
        path = self.path / ".hydra" / "hydra.yaml"
        if not path.is_file():
            return {}
        try:
            import yaml  # PyYAML, a dependency of omegaconf; plain loading (no interpolation) is enough

            doc = yaml.safe_load(path.read_text()) or {}
            choices = ((doc.get("hydra") or {}).get("runtime") or {}).get("choices") or {}
        except Exception:  # noqa: BLE001 - an unreadable hydra.yaml only loses the choices
            return {}
        return {str(k): ("" if v is None else str(v)) for k, v in choices.items()}

    @property
    def experiment(self) -> str | None:
        """The experiment preset the run was started with (``+experiment=NAME``), else Hydra's choice."""
        for item in self.raw_overrides:
            key, _, value = str(item).partition("=")
            if key.lstrip("+~") == "experiment" and value:
                return value
        return self.hydra_choices.get("experiment") or None


def parse_overrides(items: Iterable[str]) -> dict:
    """``["graph.k=16", "+experiment=k"]`` -> ``{"graph.k": "16"}`` (the experiment preset dropped)."""
    out = {}
    for item in items:
        key, _, value = item.partition("=")
        key = key.lstrip("+~")
        if key in ("experiment",) or key.startswith("hydra.") or key.startswith("record") or key.startswith("output."):
            continue
        out[key] = value
    return out


def find_runs(paths: Iterable[str | Path]) -> list[Run]:
    """Every run folder (with summary.json) under the given run or multirun folders, sorted by path.
    A job that died before writing its summary still appears when Hydra wrote its .hydra/ folder."""
    runs = []
    for root in paths:
        root = Path(root)
        if not root.exists():
            raise FileNotFoundError(f"{root}: no such run or multirun folder")
        candidates = {p.parent for p in root.rglob("summary.json")} | {p.parent.parent for p in root.rglob(".hydra/overrides.yaml")}
        for d in sorted(candidates):
            s_path = d / "summary.json"
            if s_path.is_file():
                try:
                    summary = json.loads(s_path.read_text())
                except json.JSONDecodeError as exc:
                    summary = {"status": "unreadable", "error": f"summary.json: {exc}"}
            else:
                summary = {"status": "no summary", "error": "the job died before writing summary.json"}
            ov = summary.get("overrides")
            if ov is None:
                ov = _read_overrides_yaml(d / ".hydra" / "overrides.yaml")
            ov = [str(x) for x in ov]
            runs.append(Run(path=d, summary=summary, overrides=parse_overrides(ov), raw_overrides=ov))
    return runs


_STAMP = re.compile(r"^\d{4}-\d{2}-\d{2}")  # a Hydra time-stamped sweep folder (logs/multirun/k/2026-...)


def folder_name(path: str | Path) -> str:
    """A name for a run folder when its runs do not say: its own name, or its parent's when it is one
    of Hydra's time-stamped folders (``logs/multirun/k/2026-12-01_..._demo`` -> ``k``)."""
    p = Path(path).resolve()
    return p.parent.name if _STAMP.match(p.name) and p.parent.name else p.name


def experiment_name(runs: list[Run], paths: Iterable[str | Path] = ()) -> str:
    """The experiment(s) of the runs (``+experiment=NAME``, or hydra.runtime.choices.experiment),
    joined with ", " when several; the folder name(s) when no run says."""
    names = sorted({r.experiment for r in runs if r.experiment})
    if names:
        return ", ".join(names)
    folders = list(dict.fromkeys(folder_name(p) for p in paths))
    return ", ".join(folders) if folders else "report"


def scenes(runs: list[Run]) -> list[str]:
    """The scene names of the runs' summaries (``demo_room_seed0``, ...), sorted, without repeats."""
    return sorted({str(r.summary["scene"]) for r in runs if r.summary.get("scene")})


def scene_name(runs: list[Run]) -> str | None:
    """The one scene the runs share: the summaries' scene name when all agree, else the Hydra
    scene option when all runs have the same one (``demo``: one generated room per seed); None when
    the runs come from several scenes."""
    names = scenes([r for r in runs if r.status == "ok"] or runs)
    if len(names) == 1:
        return names[0]
    choices = {r.hydra_choices.get("scene") for r in runs}
    if len(choices) == 1 and None not in choices and "" not in choices:
        return choices.pop()
    return None


def _read_overrides_yaml(path: Path) -> list[str]:
    if not path.is_file():
        return []
    from omegaconf import OmegaConf

    return [str(x) for x in OmegaConf.load(path)]


def number(value):
    """'1e-4' -> 1e-4, 'true' -> 'true'; numbers sort and plot as numbers."""
    try:
        f = float(value)
        return int(f) if f.is_integer() and "." not in str(value) and "e" not in str(value).lower() else f
    except (TypeError, ValueError):
        return value


def is_nan(x) -> bool:
    return x is None or (isinstance(x, float) and math.isnan(x))


METRICS = {
    "miou": "metrics.miou",
    "accuracy": "metrics.accuracy",
    "coverage": "metrics.coverage",
    "bayesian_miou": "baseline.bayesian.miou",
    "miou_2d": "predictions_2d.miou",
    "ece": "metrics.calibration.{method}.ece",  # percent (diffuser_lab/method/calibration.py)
    "nll": "metrics.calibration.{method}.nll",  # nats per point
    "brier": "metrics.calibration.{method}.brier",
    "bayesian_ece": "metrics.calibration.{bayesian}.ece",
    "bayesian_nll": "metrics.calibration.{bayesian}.nll",
    "bayesian_brier": "metrics.calibration.{bayesian}.brier",
    "iterations": "diffusion.iterations",
    "total_s": "timings_s.total",
    "load_s": "timings_s.load",  # in total_s; 0 for a sweep job that reused the scene loaded last
    "peak_rss_gb": "memory.peak_rss_gb",  # this job's peak resident memory (diffuser_lab/runs/memory.py)
    "diffusion_s": "timings_s.diffusion",
    "graph_s": "timings_s.graph",
}


def swept_keys(runs: list[Run]) -> list[str]:
    """Override keys that take more than one value across the runs (seeds included)."""
    keys: dict[str, set] = {}
    for r in runs:
        for k, v in r.overrides.items():
            keys.setdefault(k, set()).add(v)
    return [k for k, vals in keys.items() if len(vals) > 1 or k in SEED_KEYS]


PROVENANCE_COLUMNS = ("host", "cpu", "isa", "blas", "versions", "commit")
"""A run's row's machine and version columns (summary.json ``provenance``; empty in an older run's)."""


def provenance_cells(block: Optional[dict]) -> dict:
    """The :data:`PROVENANCE_COLUMNS` of a provenance block: ``versions`` as ``numpy 2.4.6; scipy
    1.17.1; ...``, ``commit`` the short hash with ``+dirty`` for a changed tree."""
    if not block:
        return dict.fromkeys(PROVENANCE_COLUMNS, "")
    f = provenance.flat(block)
    versions = "; ".join(f"{name} {f[name]}" for name in ("python", *provenance.DISTRIBUTIONS, "diffuser-lab")
                         if f[name] != "unknown")
    commit = "" if f["commit"] == "unknown" else f["commit"] + ("+dirty" if f["dirty tree"] == "yes" else "")
    return {"host": block.get("host") or "", "cpu": f["CPU"], "isa": f["ISA"], "blas": f["BLAS"],
            "versions": versions, "commit": commit}


def provenance_line(runs: list[Run], noun: str = "jobs") -> Optional[str]:
    """One line when the runs ran on different machines, ISA levels or versions: what differs and
    how many runs per value (:func:`diffuser_lab.backends.provenance.differences_line`); None when
    they agree (runs without a provenance block are left out)."""
    return provenance.differences_line([r.provenance for r in runs], noun)


SPLIT = "split"
"""summary.json's split of the data a run was scored on (``validation``, ``test``; null: not said):
a column of the tables when a run says it."""


def _keys(runs: list[Run], drop=()) -> list[str]:
    """The tables' configuration columns: the runs' override keys (without ``drop``), sorted, and
    ``split`` when a summary names one."""
    keys = sorted({k for r in runs for k in r.overrides} - set(drop))
    return keys + [SPLIT] if SPLIT not in keys and any(r.summary.get(SPLIT) for r in runs) else keys


def config_value(r: Run, key: str) -> str:
    """A run's value of a table's configuration column: its override, or for ``split`` summary.json's."""
    if key == SPLIT and key not in r.overrides:
        return str(r.summary.get(SPLIT) or "")
    return r.overrides.get(key, "")


def inputs_line(runs: list[Run], noun: str = "jobs") -> Optional[str]:
    """One line when runs of one scene name read different inputs (a frame folder edited or a
    prediction folder regenerated between jobs: figures of "one scene" that are not): per scene
    and role, the distinct hashes (12 hex digits) and how many runs read each, e.g. ``different
    inputs under one scene name: scene0470_00 frames 1a2b3c4d5e6f (3 runs), 9f8e7d6c5b4a (1 run)``;
    None when every scene's runs agree (runs without an ``inputs`` block left out)."""
    one = noun[:-1] if noun.endswith("s") else noun
    by_scene: dict[str, list[Run]] = {}
    for r in runs:
        if r.inputs and r.summary.get("scene"):
            by_scene.setdefault(str(r.summary["scene"]), []).append(r)
    parts = []
    for scene, members in sorted(by_scene.items()):
        for role in sorted({k for r in members for k in r.inputs}):
            counts: dict[str, int] = {}
            for r in members:
                if role in r.inputs:
                    counts[r.inputs[role]] = counts.get(r.inputs[role], 0) + 1
            if len(counts) > 1:
                values = ", ".join(f"{h[:12]} ({n} {one if n == 1 else noun})"
                                   for h, n in sorted(counts.items(), key=lambda kv: -kv[1]))
                parts.append(f"{scene} {role} {values}")
    return "different inputs under one scene name: " + "; ".join(parts) if parts else None


def notes(runs: list[Run], noun: str = "jobs") -> list[str]:
    """The lines a table of these runs ends with: different machines or versions
    (:func:`provenance_line`), different inputs under one scene name (:func:`inputs_line`)."""
    return [x for x in (provenance_line(runs, noun), inputs_line(runs, noun)) if x]


def run_rows(runs: list[Run]) -> tuple[list[str], list[dict]]:
    keys = _keys(runs)
    rows = []
    for r in runs:
        row = {"run": str(r.path), "status": r.status, "error": r.summary.get("error", ""),
               "method": r.summary.get("method", ""), "scene": r.summary.get("scene", "")}
        row.update({k: config_value(r, k) for k in keys})
        row.update({name: r.metric(path) for name, path in METRICS.items()})
        row.update(provenance_cells(r.provenance))
        row["inputs"] = ((r.summary.get("inputs") or {}).get("sha256") or "")[:12]
        rows.append(row)
    return ["run", "status", "error", "method", "scene", *keys, *METRICS, *PROVENANCE_COLUMNS, "inputs"], rows


def aggregate(runs: list[Run]) -> tuple[list[str], list[dict]]:
    """One row per configuration (overrides without the seed; the split when the runs name one):
    mean/std of each metric over the runs that finished, and counts of runs and failures."""
    keys = _keys(runs, SEED_KEYS)
    groups: dict[tuple, list[Run]] = {}
    for r in runs:
        groups.setdefault(tuple(config_value(r, k) for k in keys), []).append(r)
    rows = []
    for cfg, members in sorted(groups.items(), key=lambda kv: tuple(_sortable(x) for x in kv[0])):
        ok = [m for m in members if m.status == "ok"]
        row = dict(zip(keys, cfg))
        row["runs"] = len(members)
        row["failed"] = len(members) - len(ok)
        for name, path in METRICS.items():
            vals = [m.metric(path) for m in ok]
            vals = np.array([v for v in vals if not is_nan(v) and isinstance(v, (int, float))], float)
            row[name] = float(vals.mean()) if vals.size else None
            row[name + "_std"] = float(vals.std()) if vals.size else None
        errors = sorted({m.summary.get("error", m.status) for m in members if m.status != "ok"})
        row["errors"] = "; ".join(errors)
        rows.append(row)
    cols = [*keys, "runs", "failed"] + [c for n in METRICS for c in (n, n + "_std")] + ["errors"]
    return cols, rows


def _sortable(v):
    n = number(v)
    return (0, n, "") if isinstance(n, (int, float)) else (1, 0, str(n))


def _fmt(v, digits=1):
    if is_nan(v) or v == "":
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def markdown(cols: list[str], rows: list[dict], metrics=("miou", "bayesian_miou", "miou_2d", "coverage",
                                                         "iterations", "total_s")) -> str:
    """Aggregated rows as a Markdown table: mean ± std per metric."""
    keys = [c for c in cols if c not in METRICS and not c.endswith("_std") and c not in ("runs", "failed", "errors")]
    head = [*keys, *[m for m in metrics], "runs", "failed"]
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [_fmt(r[k]) for k in keys]
        for m in metrics:
            mean, std = r.get(m), r.get(m + "_std")
            digits = 2 if m.endswith(("_s", "_gb")) else 3 if m.endswith(("nll", "brier")) else 1
            cells.append("-" if is_nan(mean) else (f"{mean:.{digits}f} ± {std:.{digits}f}" if r["runs"] - r["failed"] > 1
                                                    else f"{mean:.{digits}f}"))
        cells += [str(r["runs"]), str(r["failed"])]
        out.append("| " + " | ".join(cells) + " |")
    failed = [r for r in rows if r["failed"]]
    if failed:
        out.append("")
        out.append("Failed runs: " + "; ".join(f"{', '.join(f'{k}={r[k]}' for k in keys)}: {r['errors']}" for r in failed))
    return "\n".join(out)
