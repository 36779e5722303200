"""Online runs (``protocol=online``) frame by frame (matplotlib PNG).

    python -m analysis.online RUN_DIR [RUN_DIR ...] --out online.png

RUN_DIR is a run folder with summary.json, or a folder of runs (the online ones are picked). One
row of two panels per run:

- left: mIoU so far (percent, summary ``online.frames[].diffuser_miou`` / ``bayesian_miou``) of
  the online Diffuser and the online Bayesian against the frame index, skipped frames as gaps with
  a dotted mark; the batch Diffuser and batch Bayesian on the same frames (``batch.diffuser.miou``,
  ``batch.bayesian.miou``) as dashed horizontal lines labelled with their values. A run without
  ground truth says so here instead;
- right: the update's latency per frame (ms; network and file reading excluded) with its median
  and p95 (``online.latency_ms``) as lines, and for a growing map the map's point count on a twin axis.

:func:`online_figure` returns the Figure (its lines labelled as in the legends) for inspection;
:func:`plot_online` saves it. ``python -m analysis.plots`` / ``analysis.report`` add
``online.png`` when the folders hold online runs.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402

from analysis.runs import Run, find_runs  # noqa: E402

DIFFUSER_COLOR = "#4c72b0"  # analysis.plots' method colours
BAYESIAN_COLOR = "#8c8c8c"
SKIP_COLOR = "#c44e52"
POINTS_COLOR = "#55a868"


def is_online(r: Run) -> bool:
    """A finished online run: ``protocol: online`` and its per-frame list (a failed run has none)."""
    return r.summary.get("protocol") == "online" and isinstance(r.metric("online.frames"), list) \
        and r.status in ("ok", "unknown")  # "unknown": a summary written without the CLI's status


def online_runs(paths) -> list[Run]:
    """The online runs under ``paths`` (run folders or folders of runs), sorted by path."""
    return [r for r in find_runs(paths) if is_online(r)]


def frame_series(r: Run) -> dict[str, np.ndarray]:
    """Per-frame arrays of one online run, in frame order: ``index`` (int), ``skipped`` (bool) and
    float ``latency_ms``, ``points``, ``diffuser_miou``, ``bayesian_miou`` (NaN where a frame was
    skipped or has no such value)."""
    frames = sorted(r.metric("online.frames"), key=lambda f: f.get("index", 0))
    skipped = np.array([bool(f.get("skipped")) for f in frames], bool)
    out = {"index": np.array([int(f.get("index", i)) for i, f in enumerate(frames)], int), "skipped": skipped}
    for key in ("latency_ms", "points", "diffuser_miou", "bayesian_miou"):
        v = np.array([f.get(key) if isinstance(f.get(key), (int, float)) else np.nan for f in frames], float)
        out[key] = np.where(skipped, np.nan, v)  # a skipped frame is a gap, not a point
    return out


def _title(r: Run, fs: dict) -> str:
    s = r.summary
    n_skip = int(fs["skipped"].sum())
    return (f"{s.get('scene', '?')} — {s.get('map', '?')} map, {fs['index'].size} frames"
            + (f" ({n_skip} skipped)" if n_skip else ""))


def _mark_skipped(ax, x: np.ndarray) -> None:
    for i, xi in enumerate(x):
        ax.axvline(xi, color=SKIP_COLOR, ls=":", lw=1.2, alpha=0.8, label="skipped frame" if i == 0 else None,
                   gid="skipped")


def _miou_panel(ax, r: Run, fs: dict) -> None:
    x = fs["index"]
    if not np.isfinite(fs["diffuser_miou"]).any():
        ax.text(0.5, 0.5, f"no ground truth for {r.summary.get('scene', 'this scene')}:\nno mIoU per frame "
                "(latency and map size only)", transform=ax.transAxes, ha="center", va="center", fontsize=9,
                color="#555555")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(_title(r, fs), fontsize=9, loc="left")
        return
    ax.plot(x, fs["diffuser_miou"], color=DIFFUSER_COLOR, lw=1.8, marker="o", markersize=2.5,
            label="online diffuser", gid="online_diffuser")
    ax.plot(x, fs["bayesian_miou"], color=BAYESIAN_COLOR, lw=1.5, marker="o", markersize=2.5,
            label="online bayesian", gid="online_bayesian")
    for key, color in (("diffuser", DIFFUSER_COLOR), ("bayesian", BAYESIAN_COLOR)):
        v = r.metric(f"batch.{key}.miou")
        if isinstance(v, (int, float)):
            ax.axhline(v, color=color, ls="--", lw=1.1, alpha=0.9, label=f"batch {key} ({v:.1f})",
                       gid=f"batch_{key}")
            ax.annotate(f"{v:.1f}", (1.0, v), xycoords=("axes fraction", "data"), xytext=(3, 0),
                        textcoords="offset points", va="center", fontsize=7, color=color)
    _mark_skipped(ax, x[fs["skipped"]])
    ax.set_ylim(0, 100)
    ax.set_ylabel("mIoU so far [%]")
    ax.set_title(f"{_title(r, fs)}: mIoU", fontsize=9, loc="left")
    ax.legend(fontsize=7, loc="lower right")


def _latency_panel(ax, r: Run, fs: dict) -> None:
    x, lat = fs["index"], fs["latency_ms"]
    ax.plot(x, lat, color="k", lw=1.2, marker="o", markersize=2.5, label="latency", gid="latency")
    L = r.metric("online.latency_ms") or {}
    for key, ls in (("median", "--"), ("p95", "-.")):
        v = L.get(key)
        if isinstance(v, (int, float)):
            ax.axhline(v, color="#dd8452", ls=ls, lw=1.1, label=f"{key} ({v:.1f} ms)", gid=key)
    _mark_skipped(ax, x[fs["skipped"]])
    finite = lat[np.isfinite(lat)]
    # a first frame that compiles or builds caches can be 100x the rest: log keeps the rest readable
    if finite.size and finite.min() > 0 and finite.max() > 10 * max(float(np.median(finite)), 1e-9):
        ax.set_yscale("log")
    else:
        ax.set_ylim(bottom=0)
    ax.set_ylabel("latency per frame [ms]")
    handles, labels = ax.get_legend_handles_labels()
    pts = fs["points"]
    fin = pts[np.isfinite(pts)]
    twin = bool(fin.size) and (r.summary.get("map") == "growing" or fin.min() != fin.max())
    if twin:
        tw = ax.twinx()
        tw.plot(x, pts, color=POINTS_COLOR, lw=1.5, drawstyle="steps-post", label="map points", gid="points")
        tw.set_ylabel("map points", color=POINTS_COLOR)
        tw.tick_params(axis="y", colors=POINTS_COLOR)
        tw.set_ylim(bottom=0)
        handles.append(Line2D([], [], color=POINTS_COLOR, lw=1.5))
        labels.append("map points (right)")
    else:
        n = r.summary.get("n_points_diffused")
        if n:
            labels[0] = f"latency ({int(n):,} map points)"
    # the point count climbs to the upper right: keep the legend off it
    ax.legend(handles, labels, fontsize=7, loc="upper center" if twin else "upper right", framealpha=0.85)
    gt = "" if np.isfinite(fs["diffuser_miou"]).any() else " (no ground truth: no mIoU)"
    ax.set_title(f"latency (update only){gt}", fontsize=9, loc="left")


def online_figure(runs: list[Run]) -> Figure | None:
    """One row per online run (see the module doc); None when ``runs`` holds no online run."""
    runs = [r for r in runs if is_online(r)]
    if not runs:
        return None
    fig, axes = plt.subplots(len(runs), 2, figsize=(12.5, 0.6 + 3.4 * len(runs)), squeeze=False,
                             layout="constrained")
    for (a_miou, a_lat), r in zip(axes, runs):
        fs = frame_series(r)
        _miou_panel(a_miou, r, fs)
        _latency_panel(a_lat, r, fs)
        for a in (a_miou, a_lat):
            if a.get_xticks().size:
                a.grid(alpha=0.3)
            a.set_xlim(-0.5, max(int(fs["index"].max()), 1) + 0.5)
    for a in axes[-1]:
        a.set_xlabel("frame index")
    fig.suptitle("Online Diffuser frame by frame (batch: the same frames at once)", fontsize=10)
    return fig


def plot_online(runs: list[Run], out: str | Path) -> Path | None:
    """Save :func:`online_figure` at ``out`` (a .png path, or a folder: ``<out>/online.png``)."""
    fig = online_figure(runs)
    if fig is None:
        return None
    out = Path(out)
    if out.suffix.lower() != ".png":
        out = out / "online.png"
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m analysis.online", description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run folders, or folders of runs")
    ap.add_argument("--out", default="online.png", help="PNG path (default online.png)")
    a = ap.parse_args(argv)
    try:
        runs = online_runs(a.runs)
    except FileNotFoundError as exc:
        print(f"online: error: {exc}", file=sys.stderr)
        return 2
    if not runs:
        print(f"online: error: no online run (summary.json with protocol: online) under {', '.join(a.runs)}",
              file=sys.stderr)
        return 2
    print(plot_online(runs, a.out))
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    raise SystemExit(main())
