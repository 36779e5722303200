"""What a multirun tells on the terminal: how many jobs, which one is running, one line per
finished job, and the swept values' table at the end.

The Hydra callback :class:`SweepProgress` (``hydra.callbacks.sweep`` in ``conf/config.yaml``)
counts the jobs before the launcher starts them and hands the count to the jobs through the
environment (``DIFFUSER_LAB_SWEEP_JOBS``: inherited by joblib, Ray, submitit and SLURM workers
started from this process). Jobs of the basic and joblib launchers print their own lines
(their stdout is this terminal); for Ray and submitit, whose jobs write to their own log
files, a :class:`Watcher` thread reads the jobs' ``summary.json`` files as they change and
prints the same lines. :func:`print_table` runs in the launching process after the last job,
whatever the launcher and whether or not a job failed.
"""
from __future__ import annotations

import json
import os
import re
import sys
import threading
from pathlib import Path
from typing import Any, Optional

from hydra.experimental.callback import Callback

from diffuser_lab.progress import say

from .results import aggregate, find_runs, markdown, notes

JOBS_ENV = "DIFFUSER_LAB_SWEEP_JOBS"
WATCHED_LAUNCHERS = ("ray_launcher", "submitit")  # whose jobs' stdout does not reach this terminal
_started: dict[str, Any] = {}  # the sweep this process launched: {"dir": Path, "watcher": Watcher}



def count_jobs(config: Any) -> Optional[int]:
    """Number of jobs Hydra's basic sweeper makes of ``hydra.sweeper.params`` and the command
    line (the same parsing and precedence as ``BasicSweeper.sweep``; ours makes the same jobs), or
    a search's (``hydra.sweeper.tune``: :func:`diffuser_lab.runs.tune.count_jobs`); None for other sweepers."""
    try:
        from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
        from hydra.core.override_parser.overrides_parser import OverridesParser
        from omegaconf import OmegaConf

        target = str(config.hydra.sweeper.get("_target_", ""))
        if target.endswith("CoveringSweeper") and config.hydra.sweeper.get("tune") is not None:
            from . import tune  # it prints through this module

            return tune.count_jobs(tune.TuneSpec(**config.hydra.sweeper.tune))
        if not target.endswith(("BasicSweeper", "CoveringSweeper")):
            return None  # CoveringSweeper: hydra_plugins/diffuser_lab_sweeper, the basic one's jobs
        params = config.hydra.sweeper.get("params") or {}
        items = [f"{k}={v}" for k, v in params.items()]
        items += list(OmegaConf.to_container(config.hydra.overrides.task, resolve=False))
        overrides = OverridesParser.create().parse_overrides(items)
        return len(BasicSweeper.split_arguments(overrides, None)[0])
    except Exception:  # noqa: BLE001 - a count is a courtesy; the sweep reports its own errors
        return None


class SweepProgress(Callback):
    """Says how many jobs a sweep has and where it writes them; remembers the folder for the table."""

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        n = count_jobs(config)
        sweep_dir = Path(str(config.hydra.sweep.dir))
        _started["dir"] = sweep_dir
        if n is not None:
            _started["jobs_env"] = os.environ.get(JOBS_ENV)  # given back at the sweep's end
            os.environ[JOBS_ENV] = str(n)
        launcher = str(config.hydra.launcher.get("_target_", ""))
        print(f"sweep: {n if n is not None else 'unknown number of'} jobs -> {sweep_dir}", flush=True)
        if any(w in launcher for w in WATCHED_LAUNCHERS):
            _started["watcher"] = Watcher(sweep_dir)
            _started["watcher"].start()

    def on_multirun_end(self, config: Any, **kwargs: Any) -> None:
        # the job count was for this sweep's jobs only: a process that goes on (a test, a notebook) gets its
        # environment back (tests/conftest.py's command-line server serves only the environment it started with)
        if "jobs_env" in _started:
            before = _started.pop("jobs_env")
            if before is None:
                os.environ.pop(JOBS_ENV, None)
            else:
                os.environ[JOBS_ENV] = before


def job_tag(num: Optional[int]) -> str:
    """``[3/15]`` for the 3rd job of 15 (``[3]`` when the total is unknown)."""
    if num is None:
        return "[?]"
    total = os.environ.get(JOBS_ENV)
    return f"[{num + 1}/{total}]" if total else f"[{num + 1}]"


def job_line(num: Optional[int], run_dir: Path, summary: dict, seconds: Optional[float] = None) -> str:
    """The one line a finished job prints: ``[3/15] 2_graph.k=24,seed=0: diffuser mIoU 73.7
    (bayesian 61.3) in 3.8 s``; a failed job's line carries its error."""
    head = f"{job_tag(num)} {Path(run_dir).name}:"
    if summary.get("status") != "ok":
        return f"{head} FAILED: {summary.get('error', summary.get('status'))}"
    m = summary.get("metrics") or {}
    if seconds is None:
        seconds = (summary.get("timings_s") or {}).get("total")
    took = f" in {seconds:.1f} s" if seconds is not None else ""
    if summary.get("protocol") == "single_frame" or "bayesian" not in (summary.get("baseline") or {}):
        return f"{head} {summary.get('method', '')} 2D mIoU {m.get('miou', float('nan')):.1f}{took}"
    bayes = ((summary.get("baseline") or {}).get("bayesian") or {}).get("miou", float("nan"))
    return f"{head} {summary.get('method', '')} mIoU {m.get('miou', float('nan')):.1f} (bayesian {bayes:.1f}){took}"


def _job_num(run_dir: Path) -> Optional[int]:
    m = re.match(r"(\d+)_", run_dir.name)
    return int(m.group(1)) if m else None


class Watcher(threading.Thread):
    """Prints a line when a job of the sweep starts (its summary.json says ``running``) and when
    it ends (``ok`` / ``failed``), reading the job folders every ``period`` seconds."""

    def __init__(self, sweep_dir: Path, period: float = 0.5, file=None):
        super().__init__(name="diffuser-lab-sweep-watcher", daemon=True)
        self.sweep_dir, self.period, self.file = Path(sweep_dir), period, file
        self.seen: dict[Path, str] = {}
        self._stop_event = threading.Event()

    def poll(self) -> None:
        for path in sorted(self.sweep_dir.glob("*/summary.json"), key=lambda p: (_job_num(p.parent) or 0, p)):
            try:
                summary = json.loads(path.read_text())
            except (OSError, ValueError):  # being written (it is replaced atomically, but be safe)
                continue
            status = summary.get("status", "")
            if self.seen.get(path.parent) == status:
                continue
            num = _job_num(path.parent)
            if status == "running" and path.parent not in self.seen:
                line = f"{job_tag(num)} started {' '.join(summary.get('overrides', []))}"
            elif status in ("ok", "failed"):
                line = job_line(num, path.parent, summary)
            else:
                continue
            self.seen[path.parent] = status
            say(line, self.file)

    def run(self) -> None:
        while not self._stop_event.wait(self.period):
            self.poll()

    def stop(self) -> None:
        self._stop_event.set()
        self.join(timeout=5)
        self.poll()  # the jobs that ended since the last look


def started_sweep() -> Optional[Path]:
    return _started.get("dir")


def print_table(file=sys.stdout) -> None:
    """The collected table of the sweep this process launched (one row per configuration, seeds
    as mean ± std; a tuning sweep's validation and test runs in a table each) and, when its jobs ran
    on different machines, ISA levels or versions, one line saying what differs and how many jobs
    per value (and one when jobs of one scene name read different inputs); nothing if it launched none."""
    if _started.get("watcher") is not None:
        _started.pop("watcher").stop()
    sweep_dir = _started.get("dir")
    if sweep_dir is None or not Path(sweep_dir).is_dir():
        return
    runs = find_runs([sweep_dir])
    if not runs:
        return
    ok = sum(r.status == "ok" for r in runs)
    print(f"\nsweep {sweep_dir}: {ok} of {len(runs)} jobs ok", file=file)
    splits = sorted({r.summary.get("split") for r in runs}, key=lambda s: ("", "validation", "test").index(s or ""))
    for split in splits:  # a tuning sweep's validation and test runs: never one table (summary.json's split)
        part = [r for r in runs if r.summary.get("split") == split]
        if len(splits) > 1:
            print(f"{split or 'no split'} runs ({len(part)}):", file=file)
        cols, rows = aggregate(part)
        print(markdown(cols, rows), file=file, flush=True)
    for line in notes(runs, "jobs"):  # other machines or versions; other inputs under one scene name
        print(line, file=file, flush=True)
