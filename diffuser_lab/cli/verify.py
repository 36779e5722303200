"""`diffuser-lab-verify`: re-run a run from its folder and say whether it still holds.

    diffuser-lab-verify RUN_DIR                 re-run into logs/verify/<date>/<time>_<run's name>/
    diffuser-lab-verify RUN_DIR --out NEW_DIR   ... into NEW_DIR (new or empty)

The re-run takes the run's saved config (``RUN_DIR/.hydra/config.yaml``, every key as the run had
it, so a default changed since does not change it) and its overrides (``overrides.yaml``: the new
summary.json's), from the directory the run was started in (``.hydra/hydra.yaml``: relative paths
read the same files), into a new folder (never the run's own). It works for every protocol (batch,
single-frame, online, features, tiled, on Ray too) and for one job of a sweep (re-run alone).

It prints one verdict line first, then the details:

    identical: labels bit for bit (50,957 points), 2 outputs and 141 figures equal, the same inputs; changed since: commit
    differs: labels of 12 of 50,957 points; 3 of 141 figures (metrics.miou 77.0 -> 76.9, ...); changed since: inputs (frames: .../depth/10.png)
    cannot re-run: 2 of its inputs are gone: /data/scene/depth/3.png (frames), ...

and what changed since the run (machine, versions, commit, inputs) below. A run whose config
cannot give the same labels twice (an online run's idle steps: ``online.rate`` > 0) says so in
its verdict. The re-run's summary.json gets the verdict (``verify``).
Exit codes: 0 identical; 1 differs, or the re-run could not be made (inputs gone, it failed);
2 bad arguments (not a run folder).
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Optional, Sequence

import yaml

from diffuser_lab.config import Config, claim_run_dir, register
from diffuser_lab.runs import compare as cmp
from diffuser_lab.runs.memory import snapshot
from diffuser_lab.runs.records import timed_output, write_json_atomic

PROG = "diffuser-lab-verify"
SHOW = 5
"""Figures and files named in the verdict line (all of them in the details)."""


class UsageError(Exception):
    pass


def _load_yaml(path: Path) -> Any:
    try:
        return yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise UsageError(f"{path}: unreadable ({type(exc).__name__}: {str(exc).splitlines()[0]})") from None


def read_run(run_dir: Path) -> tuple[dict, dict, list[str], Path]:
    """(summary.json, the saved config as a dict, the overrides, the directory it was started in)."""
    if not run_dir.is_dir():
        raise UsageError(f"{run_dir}: no such run folder")
    s_path, c_path = run_dir / "summary.json", run_dir / ".hydra" / "config.yaml"
    if not s_path.is_file() or not c_path.is_file():
        missing = s_path if not s_path.is_file() else c_path
        raise UsageError(f"{run_dir}: not a run folder ({missing.relative_to(run_dir)} missing)")
    try:
        summary = json.loads(s_path.read_text())
    except json.JSONDecodeError as exc:
        raise UsageError(f"{s_path}: unreadable ({exc})") from None
    config = _load_yaml(c_path) or {}
    over = run_dir / ".hydra" / "overrides.yaml"
    overrides = [str(x) for x in (_load_yaml(over) or [])] if over.is_file() else list(summary.get("overrides") or [])
    hydra_yaml = run_dir / ".hydra" / "hydra.yaml"
    cwd = ((((_load_yaml(hydra_yaml) or {}).get("hydra") or {}).get("runtime") or {}).get("cwd")
           if hydra_yaml.is_file() else None)
    return summary, config, overrides, Path(cwd) if cwd and Path(cwd).is_dir() else Path.cwd()


def new_folder(run_dir: Path, out: Optional[str]) -> Path:
    """The re-run's folder: ``out`` (made; refused when it holds anything) or
    ``logs/verify/<date>/<HH-MM-SS-ffffff>_<run's name>`` under the current directory."""
    if out:
        d = Path(out).resolve()
        if d.exists() and (not d.is_dir() or any(d.iterdir())):
            raise UsageError(f"--out {out}: not empty; an earlier run is never overwritten")
        d.mkdir(parents=True, exist_ok=True)
        return d
    now = datetime.datetime.now()
    return Path(claim_run_dir(str(Path("logs/verify") / f"{now:%Y-%m-%d}"), run_dir.resolve().name, now)).resolve()


def rerun(run_dir: Path, new_dir: Path, config: dict, overrides: Sequence[str], cwd: Path,
          kernels: Optional[str] = None) -> dict:
    """The run's saved config run again into ``new_dir`` (``.hydra/`` copied there), from ``cwd``, on
    the run's kernels (``kernels``: its summary.json's, numba or numpy; None: as a run decides); the
    new summary.json's content (:class:`diffuser_lab.cli.main.JobFailed` when it fails)."""
    from omegaconf import OmegaConf

    from diffuser_lab.cli.main import execute

    hydra_dir = new_dir / ".hydra"
    hydra_dir.mkdir(exist_ok=True)
    for name in ("config.yaml", "overrides.yaml", "hydra.yaml"):  # the new folder is a run folder of its own
        if (run_dir / ".hydra" / name).is_file():
            shutil.copyfile(run_dir / ".hydra" / name, hydra_dir / name)
    register()
    cfg = OmegaConf.merge(OmegaConf.structured(Config), OmegaConf.create(config))
    old = Path.cwd()
    os.chdir(cwd)
    try:
        return execute(cfg, new_dir, list(overrides), kernels=kernels)[2]
    finally:
        os.chdir(old)


def _num(v: Any) -> str:
    return f"{v:.6g}" if isinstance(v, float) else str(v)


def _figure(path: str, a: Any, b: Any) -> str:
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        return f"{path} {_num(a)} -> {_num(b)} ({b - a:+.3g})"
    return f"{path} {_num(a)} -> {_num(b)}"


def _inputs_text(c: cmp.Comparison, limit: int = SHOW) -> str:
    parts = []
    for kind in ("changed", "gone", "added"):
        es = c.inputs.get(kind) or []
        if es:
            roles = sorted({e.role for e in es})
            names = ", ".join(e.path for e in es[:limit]) + (f" and {len(es) - limit} more" if len(es) > limit else "")
            verb = {"changed": "changed", "gone": "not read now", "added": "read now only"}[kind]
            parts.append(f"{len(es)} file{'s' if len(es) != 1 else ''} {verb} ({', '.join(roles)}): {names}")
    if "config" in c.inputs:
        a, b = c.inputs["config"]
        parts.append(f"the resolved config ({(a or '?')[:12]} -> {(b or '?')[:12]}: keys or defaults added since)")
    if "generator" in c.inputs:
        parts.append(f"the scene's generator {c.inputs['generator'][0]} -> {c.inputs['generator'][1]}")
    return "; ".join(parts)


def verdict(c: cmp.Comparison, why_not: Optional[str] = None) -> str:
    """The one verdict line (module doc)."""
    changed = [k for k in ("machine", "versions", "commit", "kernels") if k in c.changed]
    since = f"; changed since: {', '.join(changed)}" if changed else ""
    timed = f" (but {', '.join(c.outputs_timed)}: written with the time)" if c.outputs_timed else ""
    equal = (f"labels bit for bit ({c.n_points:,} points), " if c.n_points is not None else
             "no labels file (single-frame), ") + f"every output{timed} and {c.figures} figures equal"
    if c.identical:
        return f"identical: {equal}, the same inputs{since or '; nothing changed since'}"
    if c.inputs_changed:
        changed.append(f"inputs ({_inputs_text(c, 1)})")
        since = f"; changed since: {', '.join(changed)}"
    if not c.labels_differ and not c.outputs_differ and not c.figures_differ:  # the inputs alone
        return f"differs in its inputs: {_inputs_text(c, 1)}; {equal} all the same" + \
            (f"; changed since: {', '.join(changed[:-1])}" if changed[:-1] else "")
    parts = []
    if c.labels_differ == -1:
        parts.append(f"labels of {c.n_points:,} points vs {'no' if c.new_points is None else format(c.new_points, ',')} "
                     f"in the re-run")
    elif c.labels_differ:
        parts.append(f"labels of {c.labels_differ:,} of {c.n_points:,} points")
    elif c.n_points is not None:
        parts.append(f"labels bit for bit ({c.n_points:,} points)")
    if c.figures_differ:
        shown = ", ".join(_figure(*f) for f in c.figures_differ[:SHOW])
        more = ", ..." if len(c.figures_differ) > SHOW else ""
        parts.append(f"{len(c.figures_differ)} of {c.figures} figures ({shown}{more})")
    else:
        parts.append(f"{c.figures} figures equal")
    other = [o for o in c.outputs_differ if o != "labels.npy"]
    if other:
        parts.append(f"outputs {', '.join(other)}")
    head = "differs" + (f" (as expected: {why_not})" if why_not else "")
    return f"{head}: {'; '.join(parts)}{since}"


def details(c: cmp.Comparison, run_dir: Path, new_dir: Path, old: dict, new: dict, wall: float) -> str:
    """The lines after the verdict: the folders, every difference, what changed, the cost."""
    lines = [f"run       {run_dir} ({old.get('started', '?')})", f"re-run    {new_dir}"]
    if c.n_points is not None:
        lines.append("labels    " + ("bit for bit" if not c.labels_differ else
                                     f"{c.labels_differ:,} of {c.n_points:,} differ" if c.labels_differ > 0 else
                                     "not comparable (lengths differ)"))
    files = sorted((new.get("outputs") or {}).get("files") or {})
    lines.append("outputs   " + (", ".join(f"{f} {_output_state(c, f)}" for f in files) or "none"))
    lines.append(f"figures   {c.figures - len(c.figures_differ)} of {c.figures} equal")
    lines += [f"          {_figure(*f)}" for f in c.figures_differ]
    for k in ("machine", "versions", "commit", "kernels"):
        diff = c.changed.get(k)
        lines.append(f"{k:<9s} " + ("; ".join(f"{'' if f == k else f + ' '}{a} -> {b}" for f, a, b in diff)
                                    if diff else "same"))
    inp = (old.get("inputs") or {})
    lines.append("inputs    " + (_inputs_text(c, 20) if c.inputs_changed else
                                 f"same (sha256 {(inp.get('sha256') or '?')[:12]}, config "
                                 f"{(inp.get('config_sha256') or '?')[:12]})"))
    t_old = (old.get("timings_s") or {}).get("total")
    t_new = (new.get("timings_s") or {}).get("total")
    m_old, m_new = (old.get("memory") or {}).get("peak_rss_gb"), (new.get("memory") or {}).get("peak_rss_gb")
    lines.append(f"cost      run {_opt(t_old, 's')}, peak {_opt(m_old, 'GB')}; re-run {_opt(t_new, 's')}, peak "
                 f"{_opt(m_new, 'GB')}; verify {wall:.2f} s, peak {snapshot().get('peak_rss_gb', 0):.2f} GB")
    return "\n".join(lines)


def _output_state(c: cmp.Comparison, name: str) -> str:
    if name in c.outputs_timed:
        return f"differs ({timed_output(name)})"
    return "differs" if name in c.outputs_differ else "equal"


def _opt(v: Optional[float], unit: str) -> str:
    return "-" if v is None else f"{v:.2f} {unit}"


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog=PROG, description="Re-run a diffuser-lab run from its folder and say whether "
                                 "it still holds (labels bit for bit, figures equal), or what differs and what "
                                 "changed since.")
    ap.add_argument("run", help="the run folder (logs/runs/..., or one job of a sweep)")
    ap.add_argument("--out", metavar="NEW_DIR", help="the re-run's folder (default logs/verify/<date>/<time>_<name>)")
    args = ap.parse_args(argv)
    os.environ.setdefault("RUST_LOG", "off")  # Rerun's own log lines: the records' errors come in one line
    t0 = time.perf_counter()
    run_dir = Path(args.run)
    try:
        old, config, overrides, cwd = read_run(run_dir)
        if old.get("status") not in ("ok", "incomplete"):
            print(f"cannot verify: {run_dir} did not finish (status {old.get('status')}: "
                  f"{old.get('error', 'no error recorded')})")
            return 1
        gone = cmp.missing_inputs(run_dir, old)  # inputs.tsv's paths are absolute
        if gone:
            names = ", ".join(f"{e.path} ({e.role})" for e in gone[:SHOW]) + (", ..." if len(gone) > SHOW else "")
            print(f"cannot re-run: {len(gone)} of its inputs {'is' if len(gone) == 1 else 'are'} gone: {names}")
            return 1
        new_dir = new_folder(run_dir, args.out)
    except UsageError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    from diffuser_lab.cli.main import JobFailed, one_line

    try:
        new = rerun(run_dir.resolve(), new_dir, config, overrides, cwd, old.get("kernels"))
    except JobFailed as failed:
        print(f"cannot re-run: the re-run failed ({type(failed.cause).__name__}: {one_line(failed.cause)}); "
              f"its folder: {new_dir}")
        return 1
    c = cmp.compare(run_dir, new_dir)
    line = verdict(c, None if c.identical else cmp.nondeterminism(config))
    wall = time.perf_counter() - t0
    print(line)
    print(details(c, run_dir, new_dir, old, new, wall))
    new["verify"] = {"of": str(run_dir.resolve()), "identical": c.identical, "verdict": line,
                     "wall_s": round(wall, 3)}
    write_json_atomic(new_dir / "summary.json", new)
    return 0 if c.identical else 1


if __name__ == "__main__":
    sys.exit(main())
