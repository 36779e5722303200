"""A run's saved class distributions read back and scored, without the scene or the run.

A run with ``output.scores=true`` (the global protocol) holds, besides summary.json
(:func:`diffuser_lab.runs.records.write_scores`):

- ``scores.npy`` (N, C) float16, row i the class distribution of original point i (labels.npy's
  order): Eq. 16's row of Z (or a per-point method's mass) divided by its sum, all zero where
  nothing reached the point;
- ``gt_labels.npy`` (N,) int16 ground truth (IGNORE = unannotated), when the scene has it.

:func:`calibration_of_run` scores the distributions in ``scores.npy`` against ``gt_labels.npy``
with the run's ``calibration.temperature`` and ``calibration.bins``: the run's method's entry of
summary.json's ``metrics.calibration``, the same numbers (the run scores the rows it saves,
:func:`diffuser_lab.method.calibration.stored`); :func:`read_scores` is the array and the ground truth.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import numpy as np
import yaml

from diffuser_lab.data.frames import first_line
from diffuser_lab.method.calibration import BINS, Calibration

from .records import SCORES_FILE, load_npy, read_gt

__all__ = ["read_scores", "calibration_of_run"]


def _summary(run_dir: Path) -> dict:
    path = run_dir / "summary.json"
    if not path.is_file():
        raise FileNotFoundError(f"{run_dir}: no summary.json, expected a run folder")
    try:
        summary = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ValueError(f"{path}: unreadable ({type(exc).__name__}: {first_line(exc)})") from None
    if not isinstance(summary, dict) or not isinstance(summary.get("n_classes"), int):
        raise ValueError(f"{path}: no 'n_classes', expected a finished global-protocol run's summary")
    return summary


def read_scores(run_dir: str | Path) -> tuple[np.ndarray, Optional[np.ndarray], dict]:
    """(scores (N, C) float16 memory map, ground truth (N,) int16 or None, summary.json) of a run
    folder written with ``output.scores=true``.

    Raises:
        FileNotFoundError: no summary.json, or no scores.npy (the run did not save its scores).
        ValueError: one line naming the file: unreadable, scores not (N, C) float16 with C the
        summary's ``n_classes``, ground truth not (N,) class ids.
    """
    run_dir = Path(run_dir)
    summary = _summary(run_dir)
    path = run_dir / SCORES_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{run_dir}: no {SCORES_FILE}, expected a run with output.scores=true")
    scores = load_npy(path)
    c = summary["n_classes"]
    if scores.ndim != 2 or scores.shape[1] != c or scores.dtype != np.float16:
        raise ValueError(f"{path}: shape {scores.shape} dtype {scores.dtype}, expected (N, {c}) float16 "
                         f"({c} classes in summary.json)")
    return scores, read_gt(run_dir, scores.shape[0], c), summary


def _calibration_keys(run_dir: Path) -> tuple[float, int]:
    """``calibration.temperature`` and ``calibration.bins`` of the run's .hydra/config.yaml (defaults without it)."""
    path = run_dir / ".hydra" / "config.yaml"
    cal = {}
    if path.is_file():
        cal = (yaml.safe_load(path.read_text()) or {}).get("calibration") or {}
    return float(cal.get("temperature", 1.0)), int(cal.get("bins", BINS))


def calibration_of_run(run_dir: str | Path, temperature: Optional[float] = None,
                       bins: Optional[int] = None) -> dict:
    """The calibration figures (:meth:`~diffuser_lab.method.calibration.Calibration.result` and its
    ``temperature``) of the distributions a run saved in scores.npy, scored at its gt_labels.npy:
    ``temperature`` and ``bins`` default to the run's (.hydra/config.yaml). With the run's values
    they equal summary.json's ``metrics.calibration[<method>]``.

    Raises:
        FileNotFoundError / ValueError: as :func:`read_scores`; ValueError when the run saved no
        ground truth (a scene without it).
    """
    run_dir = Path(run_dir)
    scores, gt, summary = read_scores(run_dir)
    if gt is None:
        raise ValueError(f"{run_dir}: no gt_labels.npy (the scene has no ground truth): nothing to score")
    t, b = _calibration_keys(run_dir)
    t, b = t if temperature is None else float(temperature), b if bins is None else int(bins)
    cal = Calibration(scores.shape[1], b)
    cal.add(scores, gt, temperature=t)
    return {**cal.result(), "temperature": t}
