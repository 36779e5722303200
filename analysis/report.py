"""An experiment folder -> one Markdown report with its tables and plots.

    python -m analysis.report logs/multirun/k/2026-... [--out results/k] [--reference graph.k=16] [--html]

writes ``<out>/report.md`` (paste-ready), ``<out>/table.csv``, ``<out>/table_runs.csv``,
``<out>/paired.csv`` and the PNGs; ``--html`` also ``<out>/report.html``, one self-contained page
(the plots inlined). The title names the experiment the runs were started with (``+experiment=NAME``;
the folder's name when the runs do not say) and the scene when the runs share one.

Beside the mean ± std table: each configuration's paired difference from the reference row (the
default run's values, or ``--reference KEY=VALUE``) over matched seeds and scenes, with a bootstrap
interval and a sign-flip p-value, per metric and per class, and as a forest plot; every method
scored on the points all of them label (the common support); each method against the Bayesian
baseline of the same runs (:mod:`analysis.paired`). Runs of the validation and the test split
(summary.json ``split``) in one report: one error line, unless ``--mix-splits``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from analysis import paired
from analysis.collect import collect, write_csv
from analysis.plots import METRIC_TITLES, make_plots, plot_forest, sort_key, swept
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
PAIRED_NOTE = ("Each cell: the configuration's runs minus the reference's at the same seed and scene{held}, the mean "
               "over the pairs with its 95 % percentile bootstrap interval and the two-sided sign-flip p-value "
               "(exact over all 2^n sign flips); `n.s.`: the interval crosses 0 or p >= 0.05. With n pairs the "
               "smallest p is 2/2^n (0.25 at 3 pairs, 0.0625 at 5): with 5 pairs or fewer nothing is significant, "
               "a statement about the design. mIoU, accuracy, coverage, ECE in points; `_common`: on the common "
               "support (below).")


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


def _head(keys: list[str], names: list[str]) -> list[str]:
    head = [*keys, *names]
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]


def _cells(config: dict, keys: list[str]) -> list[str]:
    return [str(config.get(k, "")) for k in keys]


def _delta(m: str) -> str:
    return f"Δ {m}"


def paired_sections(runs: list[Run], out: Path, reference: dict | None = None) -> list[str]:
    """The report's paired comparisons (Markdown lines; the forest plot ``<out>/forest.png``): the configurations
    against the reference, the unmatched runs, the common support's scores and size, each method
    against its runs' Bayesian baseline, the per-class differences; ``<out>/paired.csv`` holds every
    difference (configuration, metric or class, n, mean, low, high, p, significant)."""
    ok = [r for r in runs if r.status == "ok"]
    support = paired.common_support(ok)
    cmp = paired.compare_configurations(ok, reference, support)
    lines, csv_rows = [], []
    keys = cmp.keys
    if cmp.rows:
        held = f" (the other swept keys equal: {', '.join(f'`{k}`' for k in cmp.held)})" if cmp.held else ""
        lines += ["## Paired differences against the reference", "",
                  f"Reference: {cmp.how}." + (" References per value of the held keys: "
                                             + "; ".join(f"`{paired.config_label(c)}`" for c in cmp.references) + "."
                                             if len(cmp.references) > 1 else ""), "",
                  PAIRED_NOTE.format(held=held), ""]
        lines += _head(keys, ["pairs", *[_delta(m) for m in cmp.metrics]])
        for row in cmp.rows:
            n = max((d.n for d in row.diffs.values()), default=0)
            lines.append("| " + " | ".join([*_cells(row.config, keys), str(n),
                                            *[row.diffs[m].cell(paired.digits(m)) for m in cmp.metrics]]) + " |")
            csv_rows += [{**row.config, "versus": paired.config_label(row.reference), "metric": m,
                          **row.diffs[m].as_dict()} for m in cmp.metrics]
            csv_rows += [{**row.config, "versus": paired.config_label(row.reference), "metric": f"iou {c}",
                          **d.as_dict()} for c, d in row.per_class.items()]
        if cmp.unmatched:
            lines += ["", "Runs without a partner (left out of the pairs): " + "; ".join(cmp.unmatched) + "."]
        lines.append("")
        forest = plot_forest(cmp, out)
        if forest is not None:
            lines += [f"![forest]({forest.name})", "",
                      "Each configuration's paired difference from the reference (at 0), per metric: the mean and "
                      "its 95 % bootstrap interval; filled: significant, hollow with a dashed interval: not.", ""]
    lines += _support_section(ok, support, keys)
    lines += _baseline_section(ok, support, keys, csv_rows)
    lines += _class_section(cmp)
    if csv_rows:
        cols = [*keys, "versus", "metric", "n", "mean", "low", "high", "p", "exact", "significant", "why"]
        write_csv(out / "paired.csv", cols, csv_rows)
    return lines


def _support_section(ok: list[Run], support: paired.Support, keys: list[str]) -> list[str]:
    if not support.scores:
        why = "; ".join(support.left_out[:3]) + (f"; {len(support.left_out) - 3} more" if len(support.left_out) > 3 else "")
        return ["## The same points (common support)", "",
                f"Not computed: no run holds labels.npy and {paired.GT_FILE} ({why}).", ""] if support.left_out else []
    from diffuser_lab.runs.results import markdown

    groups: dict[tuple, list] = {}
    for r in ok:
        if r.path in support.scores:
            groups.setdefault(tuple(paired.config_value(r, k) for k in keys), []).append(support.scores[r.path])
    rows = []
    for cfg in sorted(groups, key=lambda c: tuple(sort_key(k, v) for k, v in zip(keys, c))):
        row = {**dict(zip(keys, cfg)), "runs": len(groups[cfg]), "failed": 0}
        for name in paired.COMMON:
            v = np.array([s[name] for s in groups[cfg] if s.get(name) is not None], float)
            row[name], row[name + "_std"] = (float(v.mean()), float(v.std())) if v.size else (None, None)
        rows.append(row)
    names = [n for n in paired.COMMON if any(r[n] is not None for r in rows)]
    lines = ["## The same points (common support)", "", support.line(), "",
             "mIoU and accuracy of each configuration's method and of its runs' Bayesian baseline on those points "
             "(mean ± std over seeds; coverage there is 100 % by definition): every method scored on the same points, "
             "beside the all-points table above.", "",
             markdown(list(keys), rows, metrics=tuple(names)), ""]
    if support.left_out:
        lines += ["Not on a common support: " + "; ".join(support.left_out) + ".", ""]
    return lines


def _baseline_section(ok: list[Run], support: paired.Support, keys: list[str], csv_rows: list) -> list[str]:
    base = paired.baseline_differences(ok, support)
    if not base:
        return []
    metrics = [m for m in ("miou", "miou_common", *paired.CALIBRATION) if any(m in d for _, d in base)]
    lines = ["## Against the Bayesian baseline of the same runs", "",
             "Each configuration's method minus the Bayesian fusion of the same evidence in the same run (pairs: "
             "its runs), as above: mean, 95 % bootstrap interval, sign-flip p; `miou_common` on the common support.", ""]
    lines += _head(keys, ["runs", *[_delta(m) for m in metrics]])
    for config, diffs in base:
        n = max(d.n for d in diffs.values())
        lines.append("| " + " | ".join([*_cells(config, keys), str(n),
                                        *[diffs[m].cell(paired.digits(m)) if m in diffs else "-" for m in metrics]]) + " |")
        csv_rows += [{**config, "versus": "bayesian (baseline)", "metric": m, **d.as_dict()} for m, d in diffs.items()]
    return lines + [""]


def _class_section(cmp: paired.Comparison) -> list[str]:
    rows = [r for r in cmp.rows if r.per_class]
    if not rows:
        return []
    classes = sorted({c for r in rows for c in r.per_class})
    heads = [", ".join(f"{k}={v}" for k, v in r.config.items() if k not in cmp.held or len(cmp.references) > 1)
             for r in rows]
    lines = ["## Per-class IoU, paired differences against the reference", "",
             "Each configuration's per-class IoU minus the reference's over the same pairs (points; interval and p "
             "as above; a class counts where both runs of a pair have it in their ground truth).", ""]
    lines += _head(["class"], heads)
    for c in classes:
        lines.append("| " + " | ".join([c, *[r.per_class[c].cell() if c in r.per_class else "-" for r in rows]]) + " |")
    return lines + [""]


def report(paths: list[str], out: str | Path, title: str | None = None, reference: dict | None = None,
           html: bool = False, mix_splits: bool = False) -> Path:
    """Write ``<out>/report.md`` (and with ``html`` ``<out>/report.html``) for the runs under
    ``paths``; ``reference``: the reference row's keys and values (default: the default run's).
    Raises ValueError (one line) on runs of both splits without ``mix_splits``, a bad reference."""
    out = Path(out)
    runs = find_runs(paths)
    paired.check_splits(runs, mix_splits)
    out.mkdir(parents=True, exist_ok=True)
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
    lines += paired_sections(runs, out, reference)
    if plots:
        lines += ["## Plots", ""]
        for p in plots:
            lines += [f"![{p.stem}]({p.name})", ""]
            if _caption(p.stem, runs):
                lines += [_caption(p.stem, runs), ""]
    path = out / "report.md"
    path.write_text("\n".join(lines))
    if html:
        from analysis.html import write_html

        write_html(path, out / "report.html", title)
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m analysis.report", description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+")
    ap.add_argument("--out", default=None, help="output folder (default results/<experiment name>)")
    ap.add_argument("--title", default=None)
    ap.add_argument("--reference", action="append", default=[], metavar="KEY=VALUE",
                    help="the reference row's value of a swept key (repeat or comma-separate for several keys; "
                         "default: the default run's values, the paper's)")
    ap.add_argument("--html", action="store_true", help="also write report.html: one page, plots inlined")
    ap.add_argument("--mix-splits", action="store_true",
                    help="allow runs of the validation and the test split (summary.json split) in one report")
    a = ap.parse_args(argv)
    try:
        out = a.out or Path("results") / experiment_name(find_runs(a.folders), a.folders).replace(", ", "_")
        ref = paired.parse_assignments(a.reference) if a.reference else None
        path = report(a.folders, out, a.title, reference=ref, html=a.html, mix_splits=a.mix_splits)
    except (FileNotFoundError, ValueError) as exc:
        print(f"report: error: {exc}", file=sys.stderr)
        return 2
    print(path)
    if a.html:
        print(path.with_suffix(".html"))
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    raise SystemExit(main())
