"""Finding and reading run folders (each holds a summary.json written by diffuser-lab)."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

SEED_KEYS = ("seed",)  # overrides that only repeat a configuration


@dataclass
class Run:
    """One run folder: its summary and its command-line overrides as a dict."""

    path: Path
    summary: dict
    overrides: dict = field(default_factory=dict)

    @property
    def status(self) -> str:
        return self.summary.get("status", "unknown")

    def metric(self, dotted: str):
        """A value of summary.json by dotted path, e.g. ``baseline.bayesian.miou``; None if absent."""
        node = self.summary
        for part in dotted.split("."):
            if not isinstance(node, dict) or part not in node:
                return None
            node = node[part]
        return node


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
            runs.append(Run(path=d, summary=summary, overrides=parse_overrides(ov)))
    return runs


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
