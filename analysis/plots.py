"""Plots of runs (matplotlib PNG).

    python -m analysis.plots logs/multirun/k/2026-... --out results/k_plots

- ``miou_vs_<param>.png``: mIoU (mean ± std over seeds) against each swept parameter, one line per
  value of the other swept parameters, the Bayesian baseline dashed;
- ``methods.png``: mIoU per method with the Bayesian baseline;
- ``per_class_iou.png``: heat map of per-class IoU for each configuration;
- ``convergence.png``: mIoU and residual against iteration, read from the runs' run.mcap files.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from analysis.runs import SEED_KEYS, Run, find_runs, number  # noqa: E402


def _groups(runs: list[Run], keys: list[str]) -> dict[tuple, list[Run]]:
    g: dict[tuple, list[Run]] = {}
    for r in runs:
        if r.status == "ok":
            g.setdefault(tuple(r.overrides.get(k, "") for k in keys), []).append(r)
    return g


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _mean_std(runs: list[Run], path: str) -> tuple[float, float]:
    v = np.array([x for x in (r.metric(path) for r in runs) if isinstance(x, (int, float))], float)
    return (float(v.mean()), float(v.std())) if v.size else (np.nan, np.nan)


def swept(runs: list[Run]) -> list[str]:
    vals: dict[str, set] = {}
    for r in runs:
        for k, v in r.overrides.items():
            vals.setdefault(k, set()).add(v)
    return sorted(k for k, v in vals.items() if len(v) > 1 and k not in SEED_KEYS)


def plot_sweep(runs: list[Run], key: str, out: Path) -> Path:
    others = [k for k in swept(runs) if k != key]
    fig, ax = plt.subplots(figsize=(6, 4))
    lines = _groups(runs, others) if others else {(): [r for r in runs if r.status == "ok"]}
    xs_all = sorted({r.overrides.get(key, "") for r in runs}, key=lambda v: (isinstance(number(v), str), number(v)))
    numeric = all(isinstance(number(v), (int, float)) for v in xs_all)
    for label, members in sorted(lines.items()):
        by_x = _groups(members, [key])
        xs = [x for x in xs_all if (x,) in by_x]
        m = [_mean_std(by_x[(x,)], "metrics.miou") for x in xs]
        b = [_mean_std(by_x[(x,)], "baseline.bayesian.miou") for x in xs]
        pos = [number(x) for x in xs] if numeric else [xs_all.index(x) for x in xs]
        name = ", ".join(f"{k}={v}" for k, v in zip(others, label)) or "diffusion"
        ax.errorbar(pos, [v[0] for v in m], yerr=[v[1] for v in m], marker="o", capsize=3, label=name)
        ax.plot(pos, [v[0] for v in b], "--", color="grey", alpha=0.7)
    if numeric and all(number(x) > 0 for x in xs_all) and max(number(x) for x in xs_all) / min(number(x) for x in xs_all) >= 100:
        ax.set_xscale("log")
    if not numeric:
        ax.set_xticks(range(len(xs_all)), xs_all)
    ax.plot([], [], "--", color="grey", label="bayesian (baseline)")
    ax.set_xlabel(key)
    ax.set_ylabel("mIoU [%] (mean ± std over seeds)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, out / f"miou_vs_{key.replace('/', '_')}.png")


def plot_methods(runs: list[Run], out: Path) -> Path | None:
    by = {}
    for r in runs:
        if r.status == "ok" and r.metric("metrics.miou") is not None:
            by.setdefault(r.summary.get("method", "?"), []).append(r)
    if not by:
        return None
    names = sorted(by, key=lambda n: ["direct", "bayesian", "ldls", "diffuser"].index(n)
                   if n in ("direct", "bayesian", "ldls", "diffuser") else 9)
    m = [_mean_std(by[n], "metrics.miou") for n in names]
    bayes = _mean_std([r for rs in by.values() for r in rs], "baseline.bayesian.miou")
    fig, ax = plt.subplots(figsize=(5, 4))
    ax.bar(names, [v[0] for v in m], yerr=[v[1] for v in m], capsize=4, color="#4c72b0")
    ax.axhline(bayes[0], ls="--", color="grey", label=f"bayesian baseline {bayes[0]:.1f}")
    for i, v in enumerate(m):
        ax.text(i, v[0] + 1, f"{v[0]:.1f}", ha="center", fontsize=9)
    ax.set_ylabel("mIoU [%]")
    ax.legend(fontsize=8)
    return _save(fig, out / "methods.png")


def plot_class_heatmap(runs: list[Run], out: Path) -> Path | None:
    keys = swept(runs)
    if keys:
        groups = _groups(runs, keys)
    else:  # nothing swept: one row per method
        keys, groups = ["method"], {}
        for r in runs:
            if r.status == "ok":
                groups.setdefault((r.summary.get("method", "?"),), []).append(r)
    classes = sorted({c for rs in groups.values() for r in rs for c in (r.metric("metrics.per_class_iou") or {})})
    if not classes or not groups:
        return None
    labels, data = [], []
    for cfg, members in sorted(groups.items(), key=lambda kv: [str(number(x)) for x in kv[0]]):
        labels.append(", ".join(f"{k}={v}" for k, v in zip(keys, cfg)))
        row = []
        for c in classes:
            v = [r.metric("metrics.per_class_iou").get(c) for r in members if r.metric("metrics.per_class_iou")]
            v = [x for x in v if x is not None]
            row.append(np.mean(v) if v else np.nan)
        data.append(row)
    data = np.array(data)
    fig, ax = plt.subplots(figsize=(1.0 + 0.6 * len(classes), 1.2 + 0.35 * len(labels)))
    im = ax.imshow(data, cmap="viridis", vmin=0, vmax=100, aspect="auto")
    ax.set_xticks(range(len(classes)), classes, rotation=45, ha="right")
    ax.set_yticks(range(len(labels)), labels, fontsize=8)
    for (i, j), v in np.ndenumerate(data):
        if np.isfinite(v):
            ax.text(j, i, f"{v:.0f}", ha="center", va="center", fontsize=7, color="w" if v < 60 else "k")
    fig.colorbar(im, ax=ax, label="IoU [%]")
    return _save(fig, out / "per_class_iou.png")


def plot_convergence(runs: list[Run], out: Path) -> Path | None:
    """mIoU and relative residual per recorded iteration, from each run's run.mcap."""
    recorded = [r for r in runs if r.status == "ok" and (r.path / "run.mcap").is_file()]
    if not recorded:
        return None
    from diffuser_lab.recording.mcap_log import read_run

    curves = []
    keys = swept(runs)
    for r in recorded:
        rows = read_run(r.path / "run.mcap").metrics  # per recorded iteration: residual, miou, ...
        if rows:
            curves.append((", ".join(f"{k}={r.overrides.get(k)}" for k in keys) or r.path.name, rows))
    if not curves:
        return None
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
    for label, rows in curves:
        it = [row["iteration"] for row in rows]
        if any(row.get("miou") is not None for row in rows):
            a1.plot(it, [row.get("miou") for row in rows], label=label, alpha=0.8)
        a2.semilogy(it, [max(row.get("residual") or np.nan, 1e-12) for row in rows], alpha=0.8)
    a1.set_xlabel("iteration")
    a1.set_ylabel("mIoU [%]")
    a2.set_xlabel("iteration")
    a2.set_ylabel("relative residual")
    for a in (a1, a2):
        a.grid(alpha=0.3)
    if len(curves) <= 12:
        a1.legend(fontsize=7)
    return _save(fig, out / "convergence.png")


def make_plots(paths: list[str], out: str | Path) -> list[Path]:
    runs = find_runs(paths)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    made = [plot_sweep(runs, k, out) for k in swept(runs) if k != "method"]
    for fn in (plot_methods, plot_class_heatmap, plot_convergence):
        p = fn(runs, out)
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
