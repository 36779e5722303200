"""Two run folders of one config compared: the labels bit for bit, the other outputs by their
hashes, the figures exactly (:func:`diffuser_lab.runs.report.figures`: timings and where it ran
left out), and which of machine, versions, commit and inputs changed between them. What
``diffuser-lab-verify`` (:mod:`diffuser_lab.cli.verify`) says of a run and its re-run."""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from diffuser_lab.backends import provenance
from diffuser_lab.data import inputs
from diffuser_lab.data.arrays import read_array

from .records import timed_output
from .report import figures

__all__ = ["Comparison", "compare", "flat_figures", "missing_inputs", "input_entries", "nondeterminism",
           "FIELD_GROUPS"]

FIELD_GROUPS = (("machine", "machine."), ("versions", "versions."), ("commit", "diffuser_lab."))
"""The provenance fields (:data:`diffuser_lab.backends.provenance.FIELDS`) by what changed: the
machine, the versions (python, the distributions), the commit (diffuser-lab's version, commit, dirty tree)."""


def flat_figures(summary: dict) -> dict[str, Any]:
    """:func:`~diffuser_lab.runs.report.figures` as {dotted path (list items by index): leaf value}."""
    out: dict[str, Any] = {}

    def walk(o: Any, path: str) -> None:
        if isinstance(o, dict):
            for k, v in o.items():
                walk(v, f"{path}.{k}" if path else str(k))
        elif isinstance(o, list):
            for i, v in enumerate(o):
                walk(v, f"{path}[{i}]")
        else:
            out[path] = o

    walk(figures(summary), "")
    return out


def input_entries(run_dir: Path, summary: dict) -> Optional[list[inputs.Entry]]:
    """A run's input files: its ``inputs.tsv`` (every file), else summary.json's listed files (an
    ``inputs.tsv`` removed); None for a run from before inputs were recorded."""
    listed = Path(run_dir) / ((summary.get("inputs") or {}).get("list") or inputs.LIST_NAME)
    if listed.is_file():
        return inputs.read_list(listed)
    files = (summary.get("inputs") or {}).get("files")
    return None if files is None else [inputs.Entry(**f) for f in files]


def missing_inputs(run_dir: Path, summary: dict) -> list[inputs.Entry]:
    """The inputs a run read that are no longer there."""
    return [e for e in input_entries(run_dir, summary) or [] if not os.path.exists(e.path)]


def nondeterminism(config: dict) -> Optional[str]:
    """Why a run of this config (``.hydra/config.yaml`` as a dict) cannot give the same labels twice,
    None when nothing in it says so: an online run's idle steps follow the wall clock
    (``online.rate`` > 0, docs/online.md), a followed capture's frames depend on when they came."""
    protocol = str(((config.get("protocol") or {}).get("name")) or "")
    rate = float((config.get("online") or {}).get("rate") or 0)
    follow = ((config.get("scene") or {}).get("options") or {}).get("follow")
    if protocol == "online" and rate > 0:
        return (f"online.rate={rate:g}: an online run's idle steps follow the wall clock, so its labels are not "
                f"reproducible (online.rate=0 online.finish=0 makes them so)")
    if follow:
        return "scene.options.follow: the frames taken depend on when the recorder wrote them"
    return None


@dataclass
class Comparison:
    """A run (``old``) and another run of its config (``new``), compared.

    Attributes:
        n_points: labels.npy's length in the old run (None: no labels.npy, a single-frame run).
        labels_differ: points whose label differs (None: no labels to compare; -1: the lengths differ).
        new_points: labels.npy's length in the new run.
        outputs_differ: output files (summary.json ``outputs.files``) whose hashes differ or that one lacks;
            outputs_timed those of them that hold their write time (:func:`~.records.timed_output`):
            not counted against identical.
        figures: the figures compared; figures_differ (path, old, new) of those that differ.
        changed: {"machine" | "versions" | "commit": [(field, old, new)]} of the provenance fields that
            differ, and "kernels" when one ran numba's kernels and the other their numpy twins.
        inputs: ``{"changed", "gone", "added"}`` (:func:`diffuser_lab.data.inputs.compare_lists`),
            ``config`` (old and new config hashes when they differ), ``generator`` (likewise).
    """

    n_points: Optional[int] = None
    new_points: Optional[int] = None
    labels_differ: Optional[int] = None
    outputs_differ: list[str] = field(default_factory=list)
    outputs_timed: list[str] = field(default_factory=list)
    figures: int = 0
    figures_differ: list[tuple[str, Any, Any]] = field(default_factory=list)
    changed: dict[str, list[tuple[str, str, str]]] = field(default_factory=dict)
    inputs: dict[str, Any] = field(default_factory=dict)

    @property
    def inputs_changed(self) -> bool:
        return any(self.inputs.get(k) for k in ("changed", "gone", "added", "config", "generator"))

    @property
    def identical(self) -> bool:
        """Labels bit for bit, every output's hash and figure equal, the same inputs."""
        return (not self.labels_differ and not self.outputs_differ and not self.figures_differ
                and not self.inputs_changed)


def _labels(run_dir: Path) -> Optional[np.ndarray]:
    p = Path(run_dir) / "labels.npy"
    return read_array(p, "labels", role=None) if p.is_file() else None


def compare(old_dir: Path, new_dir: Path) -> Comparison:
    """``old_dir`` and ``new_dir`` (run folders with summary.json) compared (:class:`Comparison`)."""
    old_s = json.loads((Path(old_dir) / "summary.json").read_text())
    new_s = json.loads((Path(new_dir) / "summary.json").read_text())
    c = Comparison()
    a, b = _labels(old_dir), _labels(new_dir)
    if a is not None:
        c.n_points = int(a.size)
        c.new_points = None if b is None else int(b.size)
        if b is None or a.shape != b.shape or a.dtype != b.dtype:
            c.labels_differ = -1
        else:  # integer ids (int16): equal values, equal bits
            c.labels_differ = int(np.count_nonzero(a != b))
    oa = (old_s.get("outputs") or {}).get("files") or {}
    ob = (new_s.get("outputs") or {}).get("files") or {}
    differ = sorted(k for k in oa.keys() | ob.keys() if (oa.get(k) or {}).get("sha256") != (ob.get(k) or {}).get("sha256"))
    c.outputs_timed = [k for k in differ if timed_output(k) and k in oa and k in ob]
    c.outputs_differ = [k for k in differ if k not in c.outputs_timed]
    fa, fb = flat_figures(old_s), flat_figures(new_s)
    c.figures = len(fa.keys() | fb.keys())
    c.figures_differ = [(k, fa.get(k), fb.get(k)) for k in sorted(fa.keys() | fb.keys(), key=_natural)
                        if fa.get(k) != fb.get(k) or (k in fa) != (k in fb)]
    for name, prefix in FIELD_GROUPS:
        paths = {label for path, label in provenance.FIELDS if path.startswith(prefix)}
        diff = [d for d in provenance.blocks_differ(old_s.get("provenance"), new_s.get("provenance")) if d[0] in paths]
        if diff:
            c.changed[name] = diff
    if old_s.get("kernels") != new_s.get("kernels"):  # numba's kernels or their numpy twins (an older run: unknown)
        c.changed["kernels"] = [("kernels", str(old_s.get("kernels") or "unknown"), str(new_s.get("kernels")))]
    ia, ib = old_s.get("inputs") or {}, new_s.get("inputs") or {}
    ea, eb = input_entries(old_dir, old_s), input_entries(new_dir, new_s)
    c.inputs = inputs.compare_lists(ea or [], eb or []) if ea is not None and eb is not None else {}
    for key in ("config_sha256", "generator"):
        if ia.get(key) != ib.get(key) and key in ia:
            c.inputs["config" if key == "config_sha256" else key] = (ia.get(key), ib.get(key))
    return c


def _natural(key: str) -> tuple:
    """``tiles[10]`` after ``tiles[9]``: list indices compared as numbers."""
    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", key))
