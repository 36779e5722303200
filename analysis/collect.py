"""Collect run / multirun folders into one table (CSV and Markdown), seeds aggregated.

    python -m analysis.collect logs/multirun/k/2026-... [more folders] --out results/k

writes ``<out>.csv`` (one row per run: overrides, status, metrics, timings) and ``<out>.md``
(one row per configuration: mean and standard deviation over seeds, number of runs and failures).
"""
from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

from analysis.runs import SEED_KEYS, Run, find_runs, is_nan, number

METRICS = {
    "miou": "metrics.miou",
    "accuracy": "metrics.accuracy",
    "coverage": "metrics.coverage",
    "bayesian_miou": "baseline.bayesian.miou",
    "miou_2d": "predictions_2d.miou",
    "iterations": "diffusion.iterations",
    "total_s": "timings_s.total",
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


def run_rows(runs: list[Run]) -> tuple[list[str], list[dict]]:
    keys = sorted({k for r in runs for k in r.overrides})
    rows = []
    for r in runs:
        row = {"run": str(r.path), "status": r.status, "error": r.summary.get("error", ""),
               "method": r.summary.get("method", ""), "scene": r.summary.get("scene", "")}
        row.update({k: r.overrides.get(k, "") for k in keys})
        row.update({name: r.metric(path) for name, path in METRICS.items()})
        rows.append(row)
    return ["run", "status", "error", "method", "scene", *keys, *METRICS], rows


def aggregate(runs: list[Run]) -> tuple[list[str], list[dict]]:
    """One row per configuration (overrides without the seed): mean/std of each metric over the
    runs that finished, and counts of runs and failures."""
    keys = sorted({k for r in runs for k in r.overrides} - set(SEED_KEYS))
    groups: dict[tuple, list[Run]] = {}
    for r in runs:
        groups.setdefault(tuple(r.overrides.get(k, "") for k in keys), []).append(r)
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
            digits = 2 if m.endswith("_s") else 1
            cells.append("-" if is_nan(mean) else (f"{mean:.{digits}f} ± {std:.{digits}f}" if r["runs"] - r["failed"] > 1
                                                    else f"{mean:.{digits}f}"))
        cells += [str(r["runs"]), str(r["failed"])]
        out.append("| " + " | ".join(cells) + " |")
    failed = [r for r in rows if r["failed"]]
    if failed:
        out.append("")
        out.append("Failed runs: " + "; ".join(f"{', '.join(f'{k}={r[k]}' for k in keys)}: {r['errors']}" for r in failed))
    return "\n".join(out)


def write_csv(path: Path, cols: list[str], rows: list[dict]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if is_nan(r.get(k)) else r.get(k)) for k in cols})


def collect(paths: list[str], out: str | Path) -> tuple[list[dict], list[dict], str]:
    """Write ``<out>_runs.csv``, ``<out>.csv`` (aggregated) and ``<out>.md``; return rows and Markdown."""
    runs = find_runs(paths)
    if not runs:
        raise SystemExit(f"collect: no run folders (summary.json) under {', '.join(paths)}")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rcols, rrows = run_rows(runs)
    write_csv(out.with_name(out.name + "_runs.csv"), rcols, rrows)
    acols, arows = aggregate(runs)
    write_csv(out.with_suffix(".csv"), acols, arows)
    md = markdown(acols, arows)
    out.with_suffix(".md").write_text(md + "\n")
    return rrows, arows, md


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m analysis.collect", description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+", help="run or multirun folders")
    ap.add_argument("--out", default="results/table", help="output path stem (default results/table)")
    a = ap.parse_args(argv)
    try:
        rrows, arows, md = collect(a.folders, a.out)
    except FileNotFoundError as exc:
        print(f"collect: error: {exc}", file=sys.stderr)
        return 2
    print(md)
    print(f"\n{len(rrows)} runs, {len(arows)} configurations -> {Path(a.out).with_suffix('.csv')}, "
          f"{Path(a.out).with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    raise SystemExit(main())
