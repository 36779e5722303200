"""An experiment folder -> one Markdown report with its tables and plots.

    python -m analysis.report logs/multirun/k/2026-... [--out results/k]

writes ``<out>/report.md`` (paste-ready), ``<out>/table.csv``, ``<out>/table_runs.csv`` and the PNGs.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from analysis.collect import collect
from analysis.plots import make_plots
from analysis.runs import find_runs


def report(paths: list[str], out: str | Path, title: str | None = None) -> Path:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    runs = find_runs(paths)
    rrows, arows, md = collect(paths, out / "table")
    plots = make_plots(paths, out)
    ok = [r for r in runs if r.status == "ok"]
    s0 = ok[0].summary if ok else {}
    title = title or f"Experiment {Path(paths[0]).resolve().parent.name if len(paths) == 1 else 'report'}"
    lines = [f"# {title}", ""]
    lines.append(f"Scene `{s0.get('scene', '?')}` ({s0.get('n_points', '?')} points, {s0.get('n_frames', '?')} frames); "
                 f"{len(runs)} runs, {len(runs) - len(ok)} failed; source folders: "
                 + ", ".join(f"`{p}`" for p in paths) + ".")
    if s0.get("predictions_2d"):
        m2 = [r.metric("predictions_2d.miou") for r in ok if r.metric("predictions_2d.miou") is not None]
        lines.append(f"2D input mIoU {min(m2):.1f}-{max(m2):.1f} across runs." if m2 else "")
    lines += ["", "## Results (mean ± std over seeds)", "",
              "mIoU, accuracy and coverage in percent over the scene's points; `bayesian_miou` is Bayesian "
              "fusion of the same evidence in the same run; `miou_2d` scores the 2D inputs; times in seconds.", "",
              md, ""]
    if plots:
        lines += ["## Plots", ""]
        for p in plots:
            lines += [f"![{p.stem}]({p.name})", ""]
    path = out / "report.md"
    path.write_text("\n".join(lines))
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m analysis.report", description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+")
    ap.add_argument("--out", default=None, help="output folder (default results/<experiment name>)")
    ap.add_argument("--title", default=None)
    a = ap.parse_args(argv)
    out = a.out or Path("results") / Path(a.folders[0]).resolve().parent.name
    try:
        path = report(a.folders, out, a.title)
    except FileNotFoundError as exc:
        print(f"report: error: {exc}", file=sys.stderr)
        return 2
    print(path)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    raise SystemExit(main())
