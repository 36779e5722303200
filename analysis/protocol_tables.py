"""Both protocols' tables from run folders: every method's mIoU (mean ± std over seeds) and its
calibration (ECE, NLL), one row per configuration, as docs/regimes.md prints them.

    python -m analysis.protocol_tables RUN_DIR [RUN_DIR ...] [--per-class]

A configuration is a run's overrides less ``seed``, ``record``, ``output.*`` and ``scene.options.root`` (the seeds of
one configuration are aggregated); global runs and single-frame runs (``protocol=single_frame``)
get a table each. Read from summary.json: global ``metrics`` (Diffuser), ``baseline.bayesian``,
``predictions_2d``, ``metrics.calibration.{diffuser,bayesian}``; single-frame ``rows`` (one per
method and window) with their ``calibration``. mIoU and ECE in percent, NLL in nats.
``--per-class`` adds each configuration's per-class IoU (mean over seeds). std: the sample standard deviation
(ddof 1), as the earlier tables of docs/regimes.md.
"""
from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from typing import Sequence

import numpy as np

from analysis.runs import Run, find_runs

IGNORED = ("seed", "record", "output.", "scene.options.root")
SF_METHODS = (("direct", 1), ("ldls", 1), ("bayesian", 5), ("diffuser", 1), ("diffuser", 5))


def config_of(run: Run) -> str:
    """The run's overrides that define its configuration (seed, record and output keys dropped)."""
    return " ".join(o for o in run.raw_overrides if not o.startswith(IGNORED))


def method_scores(run: Run) -> dict:
    """{method: {"miou", "ece", "nll", "per_class"}} of one run (percent, nats); "2D" = the 2D input."""
    s = run.summary
    out = {"2D": {"miou": s["predictions_2d"]["miou"], "per_class": s["predictions_2d"].get("per_class_iou", {})}}
    if s.get("protocol") == "single_frame":
        for r in s["rows"]:
            c = r.get("calibration") or {}
            out[f"{r['method']}_{r['views']}v"] = {"miou": r["miou"], "ece": c.get("ece"), "nll": c.get("nll"),
                                                  "per_class": r.get("per_class_iou", {})}
        return out
    cal = s["metrics"].get("calibration") or {}
    out["diffuser"] = {"miou": s["metrics"]["miou"], "per_class": s["metrics"].get("per_class_iou", {}),
                       **{k: cal.get("diffuser", {}).get(k) for k in ("ece", "nll")}}
    b = s["baseline"]["bayesian"]
    out["bayesian"] = {"miou": b["miou"], "per_class": b.get("per_class_iou", {}),
                       **{k: cal.get("bayesian", {}).get(k) for k in ("ece", "nll")}}
    return out


def _ms(values: Sequence[float], digits: int = 1) -> str:
    v = np.array([x for x in values if x is not None], float)
    if v.size == 0:
        return "-"
    return f"{v.mean():.{digits}f} ± {v.std(ddof=1):.{digits}f}" if v.size > 1 else f"{v.mean():.{digits}f}"


def _mean(values: Sequence[float], digits: int = 1) -> str:
    v = np.array([x for x in values if x is not None], float)
    return f"{v.mean():.{digits}f}" if v.size else "-"


def tables(runs: list[Run], per_class: bool = False) -> str:
    """The Markdown tables of these runs (module docstring)."""
    groups: dict[tuple[bool, str], list[dict]] = defaultdict(list)
    for r in runs:
        if r.summary.get("status", "ok") not in ("ok", "done", "completed") and "metrics" not in r.summary:
            continue
        groups[(r.summary.get("protocol") == "single_frame", config_of(r))].append(method_scores(r))
    lines = []
    g = [(k, v) for k, v in groups.items() if not k[0]]
    if g:
        lines += ["### Global protocol (3D mIoU, mean ± std over seeds)", "",
                  "| configuration | seeds | 2D | Bayesian | Diffuser | Diffuser - Bayesian | ECE D / B | NLL D / B |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- |"]
        for (_, cfg), sc in sorted(g, key=lambda kv: kv[0][1]):
            gain = [s["diffuser"]["miou"] - s["bayesian"]["miou"] for s in sc]
            lines.append(f"| {cfg} | {len(sc)} | {_ms([s['2D']['miou'] for s in sc])} | "
                         f"{_ms([s['bayesian']['miou'] for s in sc])} | {_ms([s['diffuser']['miou'] for s in sc])} | "
                         f"{_ms(gain)} | {_mean([s['diffuser']['ece'] for s in sc])} / "
                         f"{_mean([s['bayesian']['ece'] for s in sc])} | {_mean([s['diffuser']['nll'] for s in sc], 2)} / "
                         f"{_mean([s['bayesian']['nll'] for s in sc], 2)} |")
        lines.append("")
    f = [(k, v) for k, v in groups.items() if k[0]]
    if f:
        keys = [f"{m}_{v}v" for m, v in SF_METHODS]
        lines += ["### Single-frame protocol (2D mIoU over the target frames, mean ± std over seeds)", "",
                  "| configuration | seeds | 2D input | " + " | ".join(keys) + " | D-1 - direct | D-5 - B-5 | "
                  "ECE dir1 / ldl1 / bay5 / dif1 / dif5 | NLL dir1 / ldl1 / bay5 / dif1 / dif5 |",
                  "| --- " * (len(keys) + 7) + "|"]
        for (_, cfg), sc in sorted(f, key=lambda kv: kv[0][1]):
            d1 = [s["diffuser_1v"]["miou"] - s["direct_1v"]["miou"] for s in sc]
            d5 = [s["diffuser_5v"]["miou"] - s["bayesian_5v"]["miou"] for s in sc]
            lines.append(f"| {cfg} | {len(sc)} | {_ms([s['2D']['miou'] for s in sc])} | "
                         + " | ".join(_ms([s[k]["miou"] for s in sc]) for k in keys)
                         + f" | {_ms(d1)} | {_ms(d5)} | "
                         + " / ".join(_mean([s[k]["ece"] for s in sc]) for k in keys) + " | "
                         + " / ".join(_mean([s[k]["nll"] for s in sc], 2) for k in keys) + " |")
        lines.append("")
    if per_class:
        for (sf, cfg), sc in sorted(groups.items(), key=lambda kv: kv[0]):
            methods = list(sc[0])
            classes = sorted({c for s in sc for m in methods for c in s[m]["per_class"]})
            lines += [f"Per-class IoU (mean over {len(sc)} seeds): {cfg}", "",
                      "| class | " + " | ".join(methods) + " |", "| --- " * (len(methods) + 1) + "|"]
            for c in classes:
                lines.append(f"| {c} | " + " | ".join(_mean([s[m]["per_class"].get(c) for s in sc]) for m in methods) + " |")
            lines.append("")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="run folders, or folders holding them")
    ap.add_argument("--per-class", action="store_true", help="add per-class IoU tables")
    a = ap.parse_args(argv)
    print(tables(find_runs(a.runs), a.per_class))
    return 0


if __name__ == "__main__":
    sys.exit(main())
