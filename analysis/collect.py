"""Collect run / multirun folders into one table (CSV and Markdown), seeds aggregated.

    python -m analysis.collect logs/multirun/k/2026-... [more folders] --out results/k

writes ``<out>_runs.csv`` (one row per run: overrides, status, metrics, timings, and where it ran:
host, cpu, isa, blas, versions, commit), ``<out>.csv`` and ``<out>.md`` (one row per configuration:
mean and standard deviation over seeds, number of runs and failures). When the runs ran on
different machines, ISA levels or versions, the Markdown ends with one line saying what differs
and how many runs per value (nothing when they agree); when runs of one scene name read different
inputs (summary.json ``inputs``: a frame folder edited between jobs), with one line naming the scene,
the role and the hashes. The runs CSV's ``inputs`` column is each run's inputs hash (12 hex digits).
"""
from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

from diffuser_lab.runs.results import (  # noqa: F401
    METRICS,
    aggregate,
    find_runs,
    is_nan,
    markdown,
    notes,
    run_rows,
    swept_keys,
)


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
    for line in notes(runs, "runs"):  # figures of other machines, versions or inputs may differ at one seed
        md += "\n\n" + line
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
