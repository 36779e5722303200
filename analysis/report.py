"""An experiment folder -> one Markdown report with its tables and plots.

    python -m analysis.report logs/multirun/k/2026-... [--out results/k]

writes ``<out>/report.md`` (paste-ready), ``<out>/table.csv``, ``<out>/table_runs.csv`` and the PNGs.
The title names the experiment the runs were started with (``+experiment=NAME``; the folder's name
when the runs do not say) and the scene when the runs share one.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from analysis.collect import collect
from analysis.plots import make_plots, sort_key, swept
from analysis.runs import SEED_KEYS, Run, experiment_name, find_runs, scene_name, scenes

CALIBRATION_COLUMNS = ("ece", "bayesian_ece", "nll", "bayesian_nll", "brier", "bayesian_brier")
COLUMNS = {  # an experiment's own results table (default: collect's)
    "lifters": ("miou", "accuracy", "coverage", "ece", "total_s", "load_s", "peak_rss_gb"),
}
"""The results-table columns of experiments whose question needs others than the sweep table's."""
CAPTIONS = {
    "reliability": "Reliability diagrams: accuracy per confidence bin (seeds pooled) against the diagonal, the "
                   "gap to the bin's mean confidence hatched, the share of points per bin in grey; ECE in the titles.",
    "per_class_iou": "Per-class IoU for each configuration (mean over seeds).",
    "convergence": "mIoU and relative residual per recorded iteration, one line per configuration: mean "
                   "over seeds (residual: geometric mean), band min–max over seeds.",
    "online": "Online runs frame by frame: mIoU so far of the online Diffuser and Bayesian (batch runs on the "
              "same frames dashed), the update's latency per frame with its median and p95, a growing map's size.",
}


def _caption(stem: str, runs: list[Run]) -> str:
    if stem == "methods":
        methods = sorted({str(r.summary.get("method", "?")) for r in runs if r.status == "ok"})
        if len(methods) > 1:
            return "mIoU per method (mean ± std over seeds)."
        return (f"`{methods[0]}` against the Bayesian fusion of the same evidence (`baseline.bayesian` of "
                "the same runs) for each swept configuration (mean ± std over seeds).")
    if stem.startswith("miou_vs_"):
        return f"mIoU against `{stem[len('miou_vs_'):]}` (mean ± std over seeds), Bayesian baseline dashed."
    return CAPTIONS.get(stem, "")


def _span(values) -> str:
    vals = sorted({v for v in values if isinstance(v, (int, float))})
    if not vals:
        return "?"
    return f"{vals[0]}" if len(vals) == 1 else f"{vals[0]}-{vals[-1]}"


def _scene_line(runs: list[Run], ok: list[Run]) -> str:
    src = ok or runs
    names = scenes(src)
    one = scene_name(runs)
    sizes = f"{_span(r.summary.get('n_points') for r in src)} points, {_span(r.summary.get('n_frames') for r in src)} frames"
    if len(names) <= 1:
        return f"Scene `{one or (names[0] if names else '?')}` ({sizes})"
    listed = ", ".join(f"`{n}`" for n in names)
    if one:  # one scene option with several instances (the demo room is generated from the seed)
        per_seed: dict[str, set] = {}
        for r in src:
            per_seed.setdefault(r.overrides.get("seed", ""), set()).add(r.summary.get("scene"))
        how = "one per seed" if all(len(v) == 1 for v in per_seed.values()) and len(per_seed) == len(names) \
            else f"{len(names)} instances"
        return f"Scene `{one}` ({how}: {listed}; {sizes})"
    return f"Scenes {listed} ({sizes})"


def _sweep_line(runs: list[Run]) -> str:
    keys = swept(runs)
    parts = []
    for k in [*keys, *[s for s in SEED_KEYS if s not in keys]]:
        vals = sorted({r.overrides[k] for r in runs if k in r.overrides}, key=lambda v: sort_key(k, v))
        if len(vals) > 1 or (k in SEED_KEYS and vals):
            parts.append(f"`{k}` ∈ {{{', '.join(vals)}}}")
    fixed = {}
    for r in runs:
        for k, v in r.overrides.items():
            if k not in keys and k not in SEED_KEYS:
                fixed.setdefault(k, set()).add(v)
    fixed_s = ", ".join(f"`{k}={next(iter(v))}`" for k, v in sorted(fixed.items()) if len(v) == 1)
    line = ("Swept: " + " × ".join(parts) + ".") if parts else "Nothing swept."
    return line + (f" Fixed overrides: {fixed_s}." if fixed_s else "")


def report(paths: list[str], out: str | Path, title: str | None = None) -> Path:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    runs = find_runs(paths)
    rrows, arows, md = collect(paths, out / "table")
    columns = COLUMNS.get(experiment_name(runs, paths))
    if columns:  # the experiment's own columns (the CSVs hold every metric)
        from diffuser_lab.runs.results import aggregate, markdown, notes

        md = markdown(*aggregate(runs), metrics=columns) + "".join(f"\n\n{line}" for line in notes(runs, "runs"))
    plots = make_plots(paths, out)
    ok = [r for r in runs if r.status == "ok"]
    s0 = ok[0].summary if ok else {}
    if not title:
        scene = scene_name(runs)
        title = f"Experiment {experiment_name(runs, paths)}" + (f" — scene {scene}" if scene else "")
    lines = [f"# {title}", ""]
    lines.append(f"{_scene_line(runs, ok)}; {len(runs)} runs, {len(runs) - len(ok)} failed; source folders: "
                 + ", ".join(f"`{p}`" for p in paths) + ".")
    lines.append(_sweep_line(runs))
    if s0.get("predictions_2d"):
        m2 = [r.metric("predictions_2d.miou") for r in ok if r.metric("predictions_2d.miou") is not None]
        lines.append(f"2D input mIoU {min(m2):.1f}-{max(m2):.1f} across runs." if m2 else "")
    lines += ["", "## Results (mean ± std over seeds)", "",
              "mIoU, accuracy and coverage in percent over the scene's points; `bayesian_miou` is Bayesian "
              "fusion of the same evidence in the same run; `miou_2d` scores the 2D inputs; times in seconds"
              + ("; `ece` the top-label calibration error in percent; `load_s` the part of `total_s` that loaded "
                 "the scene (a sweep's later jobs reuse it); `peak_rss_gb` the job's peak resident memory (GB, in "
                 "the sweep's process: scenes kept for later jobs included)" if columns else "") + ".", "",
              md, ""]
    if any(r.metric("metrics.calibration") for r in ok):
        from diffuser_lab.runs.results import aggregate, markdown

        lines += ["## Calibration (mean ± std over seeds)", "",
                  "The class distribution of each point (Diffuser, LDLS: Z row-normalised; Bayesian, direct: the "
                  "normalised pixel mass) against the ground truth: `ece` top-label expected calibration error in "
                  "percent (`calibration.bins`, default 15), `nll` nats per point (p floored at 1e-6), `brier` "
                  "multi-class Brier score; "
                  "`bayesian_*` the Bayesian baseline of the same runs (summary `metrics.calibration`).", "",
                  markdown(*aggregate(runs), metrics=CALIBRATION_COLUMNS), ""]
    if plots:
        lines += ["## Plots", ""]
        for p in plots:
            lines += [f"![{p.stem}]({p.name})", ""]
            if _caption(p.stem, runs):
                lines += [_caption(p.stem, runs), ""]
    path = out / "report.md"
    path.write_text("\n".join(lines))
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m analysis.report", description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+")
    ap.add_argument("--out", default=None, help="output folder (default results/<experiment name>)")
    ap.add_argument("--title", default=None)
    a = ap.parse_args(argv)
    try:
        out = a.out or Path("results") / experiment_name(find_runs(a.folders), a.folders).replace(", ", "_")
        path = report(a.folders, out, a.title)
    except FileNotFoundError as exc:
        print(f"report: error: {exc}", file=sys.stderr)
        return 2
    print(path)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    raise SystemExit(main())
