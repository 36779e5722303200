"""Plots of runs (matplotlib PNG).

    python -m analysis.plots logs/multirun/k/2026-... --out results/k_plots

- ``miou_vs_<param>.png``: mIoU (mean ± std over seeds) against each swept parameter, one line per
  value of the other swept parameters, the Bayesian baseline dashed;
- ``methods.png``: mIoU per method (one bar each, mean ± std over seeds) when the runs have several
  methods; with one method, that method against the Bayesian fusion of the same evidence
  (summary ``baseline.bayesian``) for each swept configuration;
- ``per_class_iou.png``: heat map of per-class IoU for each configuration (and the Bayesian baseline);
- ``reliability.png``: reliability diagrams of the runs' class distributions (summary
  ``metrics.calibration``): one panel per method (and per swept configuration), accuracy per
  confidence bin against the diagonal, ECE in the title;
- ``convergence.png``: mIoU and residual against iteration, read from the runs' run.mcap files: one
  curve per configuration (seeds aggregated: mean, band min-max over seeds), coloured by the swept
  value (sequential colour map for numbers, qualitative for names), a second swept parameter as
  line style (or as panel rows when it has more than four values);
- ``online.png``: for online runs (``protocol=online``), mIoU and latency frame by frame
  (:mod:`analysis.online`);
- ``forest.png`` (:mod:`analysis.report` draws it): each configuration's paired difference from the
  reference with its 95 % interval, per metric (:func:`forest_figure`).

Each ``plot_*`` function saves a PNG; the ``*_figure`` function behind it returns the matplotlib
Figure (or None when there is nothing to draw) for inspection.
"""
from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

from analysis.runs import SEED_KEYS, Run, find_runs, number  # noqa: E402
from diffuser_lab.method.fusion import METHODS  # noqa: E402

METHOD_ORDER = tuple(METHODS)  # the registry's order (paper Table II)
METHOD_COLORS = {"direct": "#dd8452", "bayesian": "#8c8c8c", "ldls": "#55a868", "diffuser": "#4c72b0"}
BASELINE_COLOR = "#a0a0a0"
BASELINE_LABEL = "bayesian (baseline)"
LINESTYLES = ("-", "--", ":", "-.")
BAND = "min–max over seeds"


# --- grouping and ordering -----------------------------------------------------------------------

def _value(r: Run, key: str) -> str:
    """A run's value of an override key; for ``method`` the summary's method when not overridden."""
    if key == "method":
        return str(r.overrides.get("method") or r.summary.get("method", ""))
    return str(r.overrides.get(key, ""))


def sort_key(key: str, value):
    """Sort values of one parameter: methods in the usual order, numbers as numbers, then names."""
    if key == "method" and value in METHOD_ORDER:
        return (0, METHOD_ORDER.index(value), "")
    n = number(value)
    return (0, n, "") if isinstance(n, (int, float)) else (1, 0, str(value))


def _cfg_key(keys: list[str]):
    return lambda cfg: tuple(sort_key(k, v) for k, v in zip(keys, cfg))


def is_numeric(values) -> bool:
    vals = list(values)
    return bool(vals) and all(isinstance(number(v), (int, float)) for v in vals)


def _groups(runs: list[Run], keys: list[str]) -> dict[tuple, list[Run]]:
    g: dict[tuple, list[Run]] = {}
    for r in runs:
        if r.status == "ok":
            g.setdefault(tuple(_value(r, k) for k in keys), []).append(r)
    return g


def swept(runs: list[Run]) -> list[str]:
    vals: dict[str, set] = {}
    for r in runs:
        for k, v in r.overrides.items():
            vals.setdefault(k, set()).add(v)
    return sorted(k for k, v in vals.items() if len(v) > 1 and k not in SEED_KEYS)


def value_colors(key: str, values) -> dict[str, tuple]:
    """Value -> colour: numbers in order along a sequential map (viridis, dark = small), names from
    a qualitative one (methods keep their own colours)."""
    vals = sorted(set(values), key=lambda v: sort_key(key, v))
    if is_numeric(vals):
        cmap = plt.get_cmap("viridis")
        pos = np.linspace(0.0, 0.85, len(vals)) if len(vals) > 1 else [0.35]
        return {v: cmap(p) for v, p in zip(vals, pos)}
    cmap = plt.get_cmap("tab10" if len(vals) <= 10 else "tab20")
    out = {}
    for i, v in enumerate(vals):
        out[v] = matplotlib.colors.to_rgba(METHOD_COLORS[v]) if key == "method" and v in METHOD_COLORS else cmap(i % cmap.N)
    return out


def _split_keys(keys: list[str], runs: list[Run]) -> tuple[str, list[str]]:
    """The key to colour by (the one with most values; numbers before names) and the rest."""
    nvals = {k: len({_value(r, k) for r in runs}) for k in keys}
    colour = max(keys, key=lambda k: (nvals[k], is_numeric({_value(r, k) for r in runs}), -keys.index(k)))
    return colour, [k for k in keys if k != colour]


def _short(keys: list[str]) -> dict[str, str]:
    """Parameter names for crowded labels: the last dotted part (``graph.k`` -> ``k``) when unique."""
    last = [k.split(".")[-1] for k in keys]
    return {k: (s if last.count(s) == 1 else k) for k, s in zip(keys, last)}


def _cfg_label(keys: list[str], cfg: tuple, short: bool = False) -> str:
    names = _short(keys) if short else {k: k for k in keys}
    return ", ".join(f"{names[k]}={v}" for k, v in zip(keys, cfg))


def _n_seeds(counts) -> str:
    counts = sorted(set(counts))
    if not counts:
        return "0 seeds"
    n = f"{counts[0]}" if len(counts) == 1 else f"{counts[0]}–{counts[-1]}"
    return f"{n} seed" + ("" if n == "1" else "s")


def _over(counts, what: str = "mean ± std") -> str:
    """``mean ± std over 3 seeds``, or ``one run per configuration`` when no seed is repeated."""
    counts = set(counts)
    return "one run per configuration" if counts <= {1} else f"{what} over {_n_seeds(counts)}"


def _save(fig: Figure, path: Path) -> Path:
    if fig.get_layout_engine() is None:
        fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _mean_std(runs: list[Run], path: str) -> tuple[float, float]:
    v = np.array([x for x in (r.metric(path) for r in runs) if isinstance(x, (int, float))], float)
    return (float(v.mean()), float(v.std())) if v.size else (np.nan, np.nan)


def _methods(runs: list[Run]) -> list[str]:
    return sorted({str(r.summary.get("method", "?")) for r in runs if r.status == "ok"},
                  key=lambda m: sort_key("method", m))


# --- mIoU against one swept parameter ------------------------------------------------------------

def sweep_figure(runs: list[Run], key: str) -> Figure:
    others = [k for k in swept(runs) if k != key]
    ok = [r for r in runs if r.status == "ok"]
    lines = _groups(ok, others) if others else {(): ok}
    xs_all = sorted({_value(r, key) for r in runs}, key=lambda v: sort_key(key, v))
    numeric = is_numeric(xs_all)
    if len(others) == 1:
        colors = value_colors(others[0], [c[0] for c in lines])
        color_of = {c: colors[c[0]] for c in lines}
    else:
        color_of = {c: f"C{i % 10}" for i, c in enumerate(sorted(lines, key=_cfg_key(others)))}
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    log = numeric and all(number(x) > 0 for x in xs_all) and \
        max(number(x) for x in xs_all) / min(number(x) for x in xs_all) >= 100
    if numeric and not log and len(xs_all) > 1:
        span = max(number(x) for x in xs_all) - min(number(x) for x in xs_all)
    else:
        span = 1.0
    baselines = []
    for li, cfg in enumerate(sorted(lines, key=_cfg_key(others))):
        by_x = _groups(lines[cfg], [key])
        xs = [x for x in xs_all if (x,) in by_x]
        m = [_mean_std(by_x[(x,)], "metrics.miou") for x in xs]
        b = [_mean_std(by_x[(x,)], "baseline.bayesian.miou")[0] for x in xs]
        pos = [number(x) for x in xs] if numeric else [xs_all.index(x) for x in xs]
        base_pos = list(pos)
        if len(lines) > 1:  # dodge the lines a little so that their error bars do not cover each other
            d = (li - (len(lines) - 1) / 2) * 0.012 * min(1.0, 4 / len(lines))
            pos = [x * 10 ** (d * 2) for x in pos] if log else [x + d * span for x in pos]
        if len(others) == 1:
            name = str(cfg[0])
        else:
            name = _cfg_label(others, cfg) or ", ".join(_methods(lines[cfg]))
        ax.errorbar(pos, [v[0] for v in m], yerr=[v[1] for v in m], marker="o", capsize=3, label=name,
                    color=color_of[cfg])
        baselines.append((base_pos, b, color_of[cfg]))
    same = all(len(p) == len(baselines[0][0]) and np.allclose(bb, baselines[0][1], equal_nan=True)
               for p, bb, _ in baselines) if baselines else True
    for pos, b, c in baselines[:1] if same else baselines:
        ax.plot(pos, b, "--", color=BASELINE_COLOR if same else c, alpha=0.8, lw=1.2)
    if log:
        ax.set_xscale("log")
    elif numeric and len(xs_all) <= 12:
        ax.set_xticks([number(x) for x in xs_all], [str(x) for x in xs_all])
    if not numeric:
        long = max(map(len, xs_all)) > 8
        ax.set_xticks(range(len(xs_all)), xs_all, rotation=30 if long else 0, ha="right" if long else "center")
        ax.margins(x=0.12)
    handles, labels = ax.get_legend_handles_labels()
    handles.append(Line2D([], [], ls="--", color=BASELINE_COLOR))
    labels.append(BASELINE_LABEL)
    ax.set_xlabel(key)
    ax.set_ylabel("mIoU [%]")
    ax.set_title(f"mIoU vs {key} ({_over(len(v) for v in _groups(ok, swept(runs)).values())})", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(handles, labels, fontsize=8, title=others[0] if len(others) == 1 else None, title_fontsize=8,
              loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return fig


def plot_sweep(runs: list[Run], key: str, out: Path) -> Path:
    return _save(sweep_figure(runs, key), out / f"miou_vs_{key.replace('/', '_')}.png")


# --- methods (or the one method against the Bayesian baseline) -----------------------------------

def methods_figure(runs: list[Run]) -> Figure | None:
    """Several methods: one bar per method (the Bayesian baseline added when it is not one of them),
    grouped by the other swept parameters if any. One method: that method and the Bayesian fusion of
    the same evidence side by side for each swept configuration. None when that would be one bar."""
    ok = [r for r in runs if r.status == "ok" and r.metric("metrics.miou") is not None]
    if not ok:
        return None
    methods = _methods(ok)
    keys = [k for k in swept(runs) if k != "method"]
    groups = _groups(ok, keys) if keys else {(): ok}
    cfgs = sorted(groups, key=_cfg_key(keys))
    has_baseline = any(r.metric("baseline.bayesian.miou") is not None for r in ok)
    series: list[tuple[str, str, callable]] = []  # (label, colour, runs of a group -> (mean, std))
    for m in methods:
        series.append((m, METHOD_COLORS.get(m, f"C{len(series)}"),
                       lambda rs, m=m: _mean_std([r for r in rs if r.summary.get("method") == m], "metrics.miou")))
    if has_baseline and "bayesian" not in methods:
        series.append((BASELINE_LABEL, BASELINE_COLOR, lambda rs: _mean_std(rs, "baseline.bayesian.miou")))
    if len(series) * len(cfgs) < 2:
        return None
    n = len(series)
    grouped = bool(keys)
    width = 0.8 / n if grouped else 0.7
    n_bars = len(cfgs) * n
    fig, ax = plt.subplots(figsize=(min(16.0, max(5.0, 2.0 + 0.6 * n_bars)), 4.6))
    tops, bars = [], []
    for j, (label, color, stat) in enumerate(series):
        xs = [i + (j - (n - 1) / 2) * width for i in range(len(cfgs))] if grouped else [j]
        vals = [stat(groups[c]) for c in cfgs]
        means = [v[0] for v in vals]
        stds = [0.0 if np.isnan(v[1]) else v[1] for v in vals]
        ax.bar(xs, means, width=width, yerr=stds, capsize=3, color=color, label=label,
               hatch="//" if label == BASELINE_LABEL else None, edgecolor="white", linewidth=0.5)
        bars += [(x, mu, sd) for x, mu, sd in zip(xs, means, stds) if np.isfinite(mu)]
        tops += [mu + sd for mu, sd in zip(means, stds) if np.isfinite(mu)]
    top = max(tops) if tops else 1.0
    pad = 0.015 * top
    small = (fig.get_figwidth() - 2.0) / max(n_bars, 1) < 0.5  # too narrow for a level label
    for x, mu, sd in bars:  # above the error bar's cap, not on it
        ax.text(x, mu + sd + pad, f"{mu:.1f}", ha="center", va="bottom", fontsize=7 if small else 8,
                rotation=90 if small else 0)
    ax.set_ylim(0, top * (1.22 if small else 1.12))
    if grouped:
        ticks = [str(c[0]) if len(keys) == 1 else _cfg_label(keys, c, short=True) for c in cfgs]
        slot = (fig.get_figwidth() - 2.0) / len(cfgs)  # inches per group
        fits = max(map(len, ticks)) * 0.075 < slot
        ax.set_xticks(range(len(cfgs)), ticks, rotation=0 if fits else 35, ha="center" if fits else "right",
                      rotation_mode="anchor", fontsize=10 if len(keys) == 1 and fits else 8 if len(cfgs) <= 12 else 7)
        ax.set_xlabel(keys[0] if len(keys) == 1 else ", ".join(keys))
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    else:
        ax.set_xticks(range(n), [s[0] for s in series])
        ax.set_xlabel("method")
    seeds = _over(len(v) for v in _groups(ok, swept(runs) or ["method"]).values())
    what = "mIoU per method" if len(methods) > 1 else f"{methods[0]} vs Bayesian fusion of the same evidence"
    ax.set_title(f"{what}\n({seeds})", fontsize=10)
    ax.set_ylabel("mIoU [%]")
    ax.grid(axis="y", alpha=0.3)
    ax.set_axisbelow(True)
    return fig


def plot_methods(runs: list[Run], out: Path) -> Path | None:
    fig = methods_figure(runs)
    return None if fig is None else _save(fig, out / "methods.png")


# --- per-class IoU -------------------------------------------------------------------------------

def _class_order(runs: list[Run]) -> list[str]:
    seen: dict[str, None] = {}
    for r in runs:
        for path in ("metrics.per_class_iou", "baseline.bayesian.per_class_iou"):
            for c in r.metric(path) or {}:
                seen.setdefault(c, None)
    taxonomies = {r.summary.get("taxonomy") for r in runs}
    if len(taxonomies) == 1:  # the taxonomy's order (wall, floor, ...), not the alphabet's
        try:
            from diffuser_lab.data.taxonomy import load_taxonomy

            names = load_taxonomy(taxonomies.pop()).names  # shipped ones; file/ids runs keep first-seen order
            order = {c: i for i, c in enumerate(names)}
            return sorted(seen, key=lambda c: order.get(c, len(order)))
        except Exception:  # noqa: BLE001 - first-seen order (the summaries keep the taxonomy's)
            pass
    return list(seen)


def _class_row(members: list[Run], classes: list[str], path: str) -> list[float]:
    row = []
    for c in classes:
        v = [(r.metric(path) or {}).get(c) for r in members]
        v = [x for x in v if isinstance(x, (int, float))]
        row.append(float(np.mean(v)) if v else np.nan)
    return row


def class_heatmap_figure(runs: list[Run]) -> Figure | None:
    keys = swept(runs) or ["method"]  # nothing swept: one row per method
    ok = [r for r in runs if r.status == "ok"]
    groups = _groups(ok, keys)
    classes = _class_order(ok)
    if not classes or not groups:
        return None
    labels, data = [], []
    for cfg in sorted(groups, key=_cfg_key(keys)):
        labels.append(str(cfg[0]) if len(keys) == 1 else _cfg_label(keys, cfg, short=True))
        data.append(_class_row(groups[cfg], classes, "metrics.per_class_iou"))
    methods = _methods(ok)
    baseline = False
    if "bayesian" not in methods and any(r.metric("baseline.bayesian.per_class_iou") for r in ok):
        # the same evidence fused by counting, for reference: one row when it is the same for every
        # configuration (a graph parameter swept), none when the sweep changes the evidence
        rows = np.array([_class_row(groups[c], classes, "baseline.bayesian.per_class_iou") for c in groups], float)
        if np.allclose(rows, rows[0], atol=1e-6, equal_nan=True):
            baseline = True
            labels.append(BASELINE_LABEL)
            data.append(list(rows[0]))
    data = np.array(data, float)
    fig, ax = plt.subplots(figsize=(2.8 + 0.5 * len(classes), 1.9 + 0.34 * len(labels)), layout="constrained")
    im = ax.imshow(data, cmap="viridis", vmin=0, vmax=100, aspect="auto")
    ax.set_xticks(range(len(classes)), classes, rotation=45, ha="right", rotation_mode="anchor", fontsize=8)
    ax.set_yticks(range(len(labels)), labels, fontsize=8)
    for (i, j), v in np.ndenumerate(data):
        if np.isfinite(v):
            ax.text(j, i, f"{v:.0f}", ha="center", va="center", fontsize=7, color="w" if v < 60 else "k")
    if baseline:
        ax.axhline(len(labels) - 1.5, color="white", lw=3)
    ax.set_xlabel("class")
    ax.set_ylabel(keys[0] if len(keys) == 1 else "configuration")
    seeds = _over((len(v) for v in groups.values()), "mean")
    what = "Per-class IoU" + ("" if keys == ["method"] else f" of {', '.join(methods)}")
    blank = "; blank: class not in the scene" if np.isnan(data).any() else ""
    ax.set_title(f"{what} ({seeds}{blank})", fontsize=9)
    fig.colorbar(im, ax=ax, label="IoU [%]", fraction=0.04, pad=0.02)
    return fig


def plot_class_heatmap(runs: list[Run], out: Path) -> Path | None:
    fig = class_heatmap_figure(runs)
    return None if fig is None else _save(fig, out / "per_class_iou.png")


# --- convergence ---------------------------------------------------------------------------------

def _aggregate(curves: list[list[dict]], field: str, log: bool):
    """Curves of one configuration (one per seed) on the union of their iterations: mean, min, max.
    A seed's curve is interpolated between its recorded iterations and holds its last value after
    its last one (a run that stopped earlier, converged); in log10 when ``log`` (geometric mean)."""
    series = []
    for rows in curves:
        pts = [(row["iteration"], row[field]) for row in rows
               if isinstance(row.get(field), (int, float)) and np.isfinite(row[field])]
        if pts:
            series.append(np.array(sorted(pts), float))
    if not series:
        e = np.empty(0)
        return e, e, e, e
    grid = np.unique(np.concatenate([s[:, 0] for s in series]))
    y = np.full((len(series), grid.size), np.nan)
    for i, s in enumerate(series):
        v = np.log10(np.maximum(s[:, 1], 1e-12)) if log else s[:, 1]
        y[i] = np.interp(grid, s[:, 0], v)
        y[i, grid < s[0, 0]] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mean, lo, hi = np.nanmean(y, 0), np.nanmin(y, 0), np.nanmax(y, 0)
    if log:
        mean, lo, hi = 10 ** mean, 10 ** lo, 10 ** hi
    return grid, mean, lo, hi


def _read_curves(runs: list[Run]) -> list[tuple[Run, list[dict]]]:
    recorded = [r for r in runs if r.status == "ok" and (r.path / "run.mcap").is_file()]
    if not recorded:
        return []
    from diffuser_lab.recording.mcap_read import read_run

    out = []
    for r in recorded:
        try:
            rows = read_run(r.path / "run.mcap").metrics  # per recorded iteration: residual, miou, ...
        except Exception as exc:  # noqa: BLE001 - one unreadable record does not stop the plot
            print(f"plots: {r.path / 'run.mcap'}: {exc}", file=sys.stderr)
            continue
        if rows:
            out.append((r, rows))
    return out


def convergence_figure(runs: list[Run]) -> Figure | None:
    """mIoU and relative residual per recorded iteration: one line per configuration (mean over its
    seeds, band min-max), colour = value of the main swept parameter, line style (or panel row) =
    the other swept parameters."""
    curves = _read_curves(runs)
    if not curves:
        return None
    keys = swept(runs) or ["method"]
    cruns = [r for r, _ in curves]
    ckey, skeys = _split_keys(keys, cruns)
    configs: dict[tuple, list[list[dict]]] = {}
    for r, rows in curves:
        configs.setdefault(tuple(_value(r, k) for k in keys), []).append(rows)
    ci = keys.index(ckey)
    si = [keys.index(k) for k in skeys]
    colors = value_colors(ckey, [c[ci] for c in configs])
    styles = sorted({tuple(c[i] for i in si) for c in configs}, key=_cfg_key(skeys))
    panels = len(styles) > len(LINESTYLES)
    nrows = len(styles) if panels else 1
    fig, axes = plt.subplots(nrows, 2, figsize=(11.5, 0.8 + 3.4 * nrows), squeeze=False, sharex=True,
                             sharey="col", layout="constrained")

    def style_label(s: tuple) -> str:
        return ", ".join(f"{k}={v}" for k, v in zip(skeys, s))

    banded = False
    # larger values first, so that where curves coincide (a solver.max_iter sweep: the same
    # iterations, cut earlier) the shorter ones stay visible on top; a dot marks where each ends
    for cfg in sorted(configs, key=_cfg_key(keys), reverse=True):
        style = tuple(cfg[i] for i in si)
        row = styles.index(style) if panels else 0
        ls = "-" if panels else LINESTYLES[styles.index(style)]
        label = ", ".join(f"{k}={v}" for k, v in zip(keys, cfg))
        for ax, field, log in ((axes[row, 0], "miou", False), (axes[row, 1], "residual", True)):
            it, mean, lo, hi = _aggregate(configs[cfg], field, log)
            if not it.size:
                continue
            ax.plot(it, mean, color=colors[cfg[ci]], ls=ls, lw=1.8, label=label, marker="o", markersize=3.5,
                    markevery=[it.size - 1])
            if len(configs[cfg]) > 1:
                ax.fill_between(it, lo, hi, color=colors[cfg[ci]], alpha=0.12, lw=0)
                banded = True
    for row in range(nrows):
        a1, a2 = axes[row]
        a1.set_ylabel("mIoU [%]")
        a2.set_ylabel("relative residual (geometric mean)")
        a2.set_yscale("log")
        for a in (a1, a2):
            a.grid(alpha=0.3)
        if panels:
            a1.set_title(style_label(styles[row]), fontsize=9, loc="left")
    for a in axes[-1]:
        a.set_xlabel("iteration")
    shown = sorted({c[ci] for c in configs}, key=lambda v: sort_key(ckey, v))
    fig.legend(handles=[Line2D([], [], color=colors[v], lw=2.5, label=str(v)) for v in shown],
               title=ckey, loc="outside right upper", fontsize=8, title_fontsize=9)
    extra = [] if panels or len(styles) < 2 else [
        Line2D([], [], color="k", ls=LINESTYLES[i], lw=1.5, label=style_label(s)) for i, s in enumerate(styles)]
    if banded:
        extra.append(Patch(facecolor="grey", alpha=0.3, label=f"band: {BAND}"))
    if extra:
        fig.legend(handles=extra, loc="outside right lower", fontsize=8)
    counts = {len(v) for v in configs.values()}
    how = "one run per configuration" if counts == {1} else \
        f"line = mean over {_n_seeds(counts)}" + (f", band = {BAND}" if banded else "")
    idle = [m for m in _methods(runs) if m not in _methods(cruns)]
    fig.suptitle(f"Convergence of {', '.join(_methods(cruns))} per recorded iteration\n{how}"
                 + (f"; {', '.join(idle)}: no iterations" if idle else ""), fontsize=10)
    return fig


def plot_convergence(runs: list[Run], out: Path) -> Path | None:
    """mIoU and relative residual per recorded iteration, from each run's run.mcap."""
    fig = convergence_figure(runs)
    return None if fig is None else _save(fig, out / "convergence.png")


# --- reliability diagrams -----------------------------------------------------------------------

def _calibrated(key: str) -> tuple:
    """Panel order of a ``metrics.calibration`` key: ``diffuser``, or ``diffuser_5v`` (single frame)."""
    name, _, views = key.rpartition("_")
    if views.endswith("v") and views[:-1].isdigit() and name in METHOD_ORDER:
        return (METHOD_ORDER.index(name), int(views[:-1]), key)
    return (METHOD_ORDER.index(key) if key in METHOD_ORDER else len(METHOD_ORDER), 0, key)


def _panel_title(key: str) -> str:
    name, _, views = key.rpartition("_")
    if views.endswith("v") and views[:-1].isdigit() and name in METHOD_ORDER:
        return f"{name}, {views[:-1]} view{'' if views == '1v' else 's'}"
    return key


def pooled_bins(entries: list[dict]) -> dict:
    """Reliability bins of several runs' ``metrics.calibration.<method>`` pooled: counts summed,
    confidence and accuracy (percent) weighted by count; ``ece`` (percent) of the pooled bins."""
    count = np.array([e["bins"]["count"] for e in entries], float)
    conf = np.array([[np.nan if v is None else v for v in e["bins"]["confidence"]] for e in entries], float)
    acc = np.array([[np.nan if v is None else v for v in e["bins"]["accuracy"]] for e in entries], float)
    n = count.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.where(n > 0, np.nansum(count * conf, 0) / n, np.nan)
        a = np.where(n > 0, np.nansum(count * acc, 0) / n, np.nan)
    ece = float(np.nansum(n * np.abs(a - c)) / n.sum()) if n.sum() else np.nan
    return {"edge": np.array(entries[0]["bins"]["edge"], float), "count": n, "confidence": c, "accuracy": a,
            "ece": ece}


def reliability_figure(runs: list[Run]) -> Figure | None:
    """Reliability diagrams from the runs' ``metrics.calibration``: one panel per method (columns)
    and per configuration of the swept parameters other than ``method`` (rows); bars = accuracy per
    confidence bin (seeds pooled), the gap to the bin's mean confidence hatched, the diagonal =
    perfect calibration, the grey steps the share of points per bin; ECE (mean ± std over the runs)
    in each panel's title. None without figures."""
    ok = [r for r in runs if r.status == "ok" and isinstance(r.metric("metrics.calibration"), dict)]
    if not ok:
        return None
    keys = [k for k in swept(runs) if k != "method"]
    groups = _groups(ok, keys) if keys else {(): ok}
    cfgs = sorted(groups, key=_cfg_key(keys))
    methods = sorted({m for r in ok for m, e in r.metric("metrics.calibration").items()
                      if isinstance(e, dict) and e.get("n_points")}, key=_calibrated)
    if not methods:
        return None
    nrow, ncol = len(cfgs), len(methods)
    fig, axes = plt.subplots(nrow, ncol, figsize=(0.8 + 3.0 * ncol, 1.4 + 3.0 * nrow), squeeze=False,
                             sharex=True, sharey=True, layout="constrained")
    for i, cfg in enumerate(cfgs):
        for j, m in enumerate(methods):
            ax = axes[i, j]
            entries = [e for e in (r.metric(f"metrics.calibration.{m}") for r in groups[cfg])
                       if isinstance(e, dict) and e.get("n_points")]
            if not entries:
                ax.set_axis_off()
                continue
            b = pooled_bins(entries)
            lo = np.concatenate([[0.0], b["edge"][:-1]]) * 100
            width = (b["edge"] * 100 - lo)
            filled = b["count"] > 0
            ax.bar(lo[filled], b["accuracy"][filled], width=width[filled], align="edge", color="#4c72b0",
                   edgecolor="white", linewidth=0.5, label="accuracy")
            gap_lo = np.minimum(b["accuracy"], b["confidence"])[filled]
            ax.bar(lo[filled], np.abs(b["confidence"] - b["accuracy"])[filled], bottom=gap_lo,
                   width=width[filled], align="edge", facecolor="none", edgecolor="#c44e52", hatch="//",
                   linewidth=0.8, label="gap to confidence")
            ax.plot([0, 100], [0, 100], "--", color="k", lw=1, label="perfect calibration")
            ax.stairs(100 * b["count"] / b["count"].sum(), np.concatenate([lo[:1], b["edge"] * 100]),
                      color="#555555", lw=1.2, label="share of points [%]")
            eces = np.array([e["ece"] for e in entries if isinstance(e.get("ece"), (int, float))], float)
            spread = f" ± {eces.std():.1f}" if eces.size > 1 else ""
            head = _panel_title(m) + (f"\n{_cfg_label(keys, cfg, short=True)}" if keys else "")
            ax.set_title(f"{head}\nECE {eces.mean():.1f}{spread}%", fontsize=9)
            ax.set_xlim(0, 100)
            ax.set_ylim(0, 100)
            ax.grid(alpha=0.3)
            if i == nrow - 1:
                ax.set_xlabel("confidence [%]")
            if j == 0:
                ax.set_ylabel("accuracy [%]")
    handles, labels = next((a.get_legend_handles_labels() for a in axes.flat if a.axison), ([], []))
    fig.legend(handles, labels, loc="outside lower center", ncol=4, fontsize=8)
    temps = sorted({e.get("temperature") for r in ok for e in r.metric("metrics.calibration").values()
                    if isinstance(e, dict) and e.get("temperature") is not None})
    t = "" if temps in ([], [1.0]) or "calibration.temperature" in keys else \
        f", temperature {', '.join(f'{x:g}' for x in temps)}"
    n_bins = next(len(e["bins"]["count"]) for r in ok for e in r.metric("metrics.calibration").values()
                  if isinstance(e, dict) and e.get("n_points"))
    fig.suptitle(f"Reliability of the class distributions\n(top-label confidence, {n_bins} equal-width bins{t}; "
                 f"{_over((len(v) for v in groups.values()), 'pooled')})", fontsize=9)
    return fig


def plot_reliability(runs: list[Run], out: Path) -> Path | None:
    """Reliability diagrams of the runs' class distributions (summary ``metrics.calibration``)."""
    fig = reliability_figure(runs)
    return None if fig is None else _save(fig, out / "reliability.png")


# --- paired differences from the reference -------------------------------------------------------

METRIC_TITLES = {"miou": "mIoU", "accuracy": "accuracy", "coverage": "coverage",
                 "miou_common": "mIoU, common support", "accuracy_common": "accuracy, common support",
                 "ece": "ECE", "nll": "NLL (nats)", "brier": "Brier"}
FOREST_COLUMNS = 4  # panels per row
SIGNIFICANT_COLOR = "#4c72b0"
NOT_SIGNIFICANT_COLOR = "#9a9a9a"


def forest_figure(comparison) -> Figure | None:
    """One panel per metric: each configuration's mean paired difference from the reference
    (:class:`analysis.paired.Comparison`) with its 95 % bootstrap interval, the reference at 0;
    significant ones filled blue, the others hollow grey with a dashed interval. None without pairs."""
    rows = [r for r in comparison.rows if any(d.n for d in r.diffs.values())]
    metrics = [m for m in comparison.metrics if any(r.diffs[m].n for r in rows)]
    if not rows or not metrics:
        return None
    ncols = min(FOREST_COLUMNS, len(metrics))
    nrows = -(-len(metrics) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(2.2 + 2.9 * ncols, 0.5 + nrows * (1.3 + 0.36 * len(rows))),
                             sharey=True, squeeze=False)
    for ax in axes.flat[len(metrics):]:
        ax.set_visible(False)
    y = np.arange(len(rows))[::-1]
    for ax, m in zip(axes.flat, metrics):
        ax.axvline(0.0, color="0.25", lw=1.0, zorder=1)
        for yi, row in zip(y, rows):
            d = row.diffs[m]
            if d.mean is None:
                continue
            sig = d.significant
            color = SIGNIFICANT_COLOR if sig else NOT_SIGNIFICANT_COLOR
            lo, hi = (d.low, d.high) if d.low is not None else (d.mean, d.mean)
            bars = ax.errorbar(d.mean, yi, xerr=[[d.mean - lo], [hi - d.mean]], fmt="o", ms=6, color=color,
                               mfc=color if sig else "white", mew=1.5, ecolor=color, elinewidth=1.6, capsize=3, zorder=3)
            if not sig:
                for lc in bars[2]:
                    lc.set_linestyle("--")
        ends = [x for r in rows for x in (r.diffs[m].low, r.diffs[m].high, r.diffs[m].mean) if x is not None]
        if ends and max(abs(x) for x in ends) < 1e-9:  # all zero (a metric the swept key leaves alone)
            ax.set_xlim(-1.0, 1.0)
        ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(5))
        ax.set_title(METRIC_TITLES.get(m, m), fontsize=10)
        ax.set_xlabel("difference" + (" (points)" if m not in ("nll", "brier") else ""), fontsize=9)
        ax.grid(axis="x", alpha=0.3)
        ax.margins(x=0.12)
    keys = [k for k in comparison.keys if len({r.config.get(k) for r in rows}) > 1] or comparison.keys
    labels = [", ".join(f"{k}={r.config[k]}" for k in keys) + f"  (n={max(d.n for d in r.diffs.values())})"
              for r in rows]
    for ax in axes[:, 0]:
        ax.set_yticks(y, labels, fontsize=9)
    axes[0][0].set_ylim(-0.7, len(rows) - 0.3)
    ref = ", ".join(f"{k}={v}" for k, v in comparison.reference.items())
    held = f"; same {', '.join(comparison.held)}" if comparison.held else ""
    handles = [Line2D([], [], marker="o", color=SIGNIFICANT_COLOR, ls="-", label="significant (interval excludes 0, p < 0.05)"),
               Line2D([], [], marker="o", color=NOT_SIGNIFICANT_COLOR, mfc="white", ls="--", label="not significant")]
    fig.legend(handles=handles, loc="lower center", ncol=2, fontsize=8, frameon=False)
    fig.suptitle(f"Paired difference from the reference ({ref}{held}; matched seeds and scenes): "
                 "mean, 95 % bootstrap interval", fontsize=10)
    h = fig.get_figheight()
    fig.tight_layout(rect=(0, 0.3 / h, 1, 1 - 0.15 / h))
    return fig


def plot_forest(comparison, out: Path) -> Path | None:
    """:func:`forest_figure` saved as ``forest.png``."""
    fig = forest_figure(comparison)
    return None if fig is None else _save(fig, out / "forest.png")


# --- all of them ---------------------------------------------------------------------------------

def make_plots(paths: list[str], out: str | Path) -> list[Path]:
    runs = find_runs(paths)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    made = [plot_sweep(runs, k, out) for k in swept(runs) if k != "method"]
    for fn in (plot_methods, plot_class_heatmap, plot_convergence, plot_reliability):
        p = fn(runs, out)
        if p is not None:
            made.append(p)
    from analysis.online import plot_online

    p = plot_online(runs, out / "online.png")
    if p is not None:
        made.append(p)
    return made


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m analysis.plots", description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+")
    ap.add_argument("--out", default="results/plots")
    a = ap.parse_args(argv)
    for p in make_plots(a.folders, a.out):
        print(p)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    raise SystemExit(main())
