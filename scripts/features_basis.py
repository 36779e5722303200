"""Features at the cost of labels (issue 49): time, peak memory and agreement of features runs
against the labels run of the same scene, side by side in one script, repeated.

    python scripts/features_basis.py speed [--repeat 3] [--tree NAME=PATH ...] [--case 'NAME=[@TREE] OVERRIDES' ...]
        [-- KEY=VALUE ...]
    python scripts/features_basis.py agree [--variant 'NAME=OVERRIDES' ...] [--json FILE] -- SCENE_OVERRIDES ...

``speed`` runs each case (``diffuser-lab ... record=off output.labels_ply=false`` plus the case's
overrides and the common ones after ``--``) in its own process, in turn, ``--repeat`` rounds
(round-robin: a load change hits every case alike), under ``/usr/bin/time -f %M`` (the peak RSS
of the command's process, KB); it prints per case the median of the command's wall time, of
``end_to_end`` (summary.json's ``timings_s.total`` + ``write``: the run and its files), of
``timings_s`` (total, evidence, diffusion, ...) and of the peak, and the ratio of each case to the
first (the labels run) per round, median over rounds. Each case may run on its
own source tree (``--tree``: PYTHONPATH, e.g. a checkout of the commit before a change), so a
before/after pair is measured in the same rounds on the same machine.

``agree`` runs ``predictions=features`` with ``predictions.basis=full`` and each ``--variant`` on one
scene in this process (the scene loaded once) and compares each variant with full: query labels
equal (Diffuser's and the average's), threshold decisions equal (the run's best cosine >= T, at T =
full's 10th ... 90th percentile of Diffuser's best cosine), the saved features' cosine to full's
(median, 5th percentile, min; Diffuser's, the average's, the best view's), mIoU and calibration
figures side by side.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

VENV = Path(os.environ.get("DIFFUSER_VENV", "/work/main/.venv"))
BASE = ("record=off", "output.labels_ply=false")


def _run_case(tree: str, overrides: list[str], run_dir: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=tree, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "2"))
    cmd = ["/usr/bin/time", "-f", "MAXRSS_KB %M", str(VENV / "bin" / "diffuser-lab"), *BASE, *overrides,
           f"hydra.run.dir={run_dir}"]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, env=env, cwd=tree, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"failed ({p.returncode}): {' '.join(cmd)}\n{p.stderr[-3000:]}")
    kb = [int(line.split()[1]) for line in p.stderr.splitlines() if line.startswith("MAXRSS_KB")]
    s = json.loads((run_dir / "summary.json").read_text())
    out = {"wall": wall, "peak_gb": kb[-1] / 2**20 if kb else float("nan")}
    out.update({k: float(v) for k, v in s["timings_s"].items()})
    out["end_to_end"] = out.get("total", 0.0) + out.get("write", 0.0)  # the run and writing its files
    out["miou"] = s.get("metrics", {}).get("miou")
    out["basis_info"] = (s.get("features") or {}).get("basis")
    return out


def speed(args) -> None:
    trees = dict(t.split("=", 1) for t in args.tree) or {"here": str(Path(__file__).resolve().parents[1])}
    cases = []
    for c in args.case:
        name, _, ov = c.partition("=")
        words = ov.split()
        tree = next(iter(trees.values()))
        if words and words[0].startswith("@"):  # @TREE: the case runs on that tree
            tree = trees[words.pop(0)[1:]]
        cases.append((name, tree, words))
    tmp = Path(args.out or tempfile.mkdtemp(prefix="features_basis_"))
    rows: dict[str, list[dict]] = {name: [] for name, _, _ in cases}
    for r in range(args.repeat):
        for name, tree, ov in cases:
            res = _run_case(tree, ov + list(args.common), tmp / f"{name}_{r}")
            rows[name].append(res)
            print(f"round {r} {name}: wall {res['wall']:.2f} s total {res.get('total', 0):.2f} evidence "
                  f"{res.get('evidence', 0):.2f} diffusion {res.get('diffusion', 0):.2f} peak {res['peak_gb']:.2f} GB "
                  f"mIoU {res['miou']}", flush=True)
    keys = ("wall", "end_to_end", "total", "predictions", "evidence", "diffusion", "write", "metrics", "peak_gb")
    ref = cases[0][0]
    print(f"\nmedians of {args.repeat} rounds (load average at the end: {os.getloadavg()[0]:.1f}); "
          f"ratio = case / {ref} per round, median")
    print(f"{'case':14s}" + "".join(f"{k:>12s}" for k in keys) + "".join(f"{'x ' + k:>12s}" for k in keys))
    for name, _, _ in cases:
        med = [statistics.median(x.get(k, 0.0) for x in rows[name]) for k in keys]
        rat = [statistics.median(x.get(k, 0.0) / max(y.get(k, 0.0), 1e-9) for x, y in zip(rows[name], rows[ref]))
               for k in keys]
        print(f"{name:14s}" + "".join(f"{v:12.2f}" for v in med) + "".join(f"{v:12.2f}" for v in rat))
    print(json.dumps({name: rows[name] for name, _, _ in cases}, default=str)[:200000], file=open(tmp / "speed.json", "w"))
    print(f"runs and speed.json in {tmp}")


def _compose(overrides: list[str]):
    from hydra import compose, initialize_config_dir

    from diffuser_lab.cli.main import config_dir
    from diffuser_lab.config import register, to_object

    register()
    with initialize_config_dir(config_dir=config_dir(), version_base="1.3", job_name="features_basis"):
        return to_object(compose("config", overrides=[*overrides, "record=off"]))


def _cos_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row cosines of two (N, D) float16 unit-row arrays, rows where both are non-zero, in chunks."""
    out = []
    for lo in range(0, len(a), 65536):
        x, y = a[lo:lo + 65536].astype(np.float32), b[lo:lo + 65536].astype(np.float32)
        nx, ny = np.linalg.norm(x, axis=1), np.linalg.norm(y, axis=1)
        ok = (nx > 0) & (ny > 0)
        out.append((x[ok] * y[ok]).sum(1) / (nx[ok] * ny[ok]))
    return np.concatenate(out)


def agree(args) -> dict:
    """Runs ``full`` (predictions.basis=full) and each variant on one scene in this process, and
    compares them (module docstring)."""
    from diffuser_lab.runs.pipeline import reuse_scenes, run

    reuse_scenes(True)
    common = list(args.common)
    variants = [("full", ["predictions.basis=full"])] + [
        (v.split("=", 1)[0], v.split("=", 1)[1].split()) for v in (args.variant or ["auto=predictions.basis=auto"])]
    res = {}
    for name, ov in variants:
        t0 = time.perf_counter()
        r = run(_compose(["predictions=features", *common, *ov]))
        lf = r.lifted
        cos = lf.cosines(lf.method)
        res[name] = dict(labels=r.labels, bayes=r.bayesian_labels, rows=r.rows, lift=lf, cos=cos,
                         metrics=r.metrics, baseline=r.baseline, time=time.perf_counter() - t0,
                         best=np.nanmax(np.where(np.isnan(cos), -np.inf, cos), axis=1), timings=r.timings_s)
        print(f"{name}: {time.perf_counter() - t0:.1f} s, basis {lf.basis_info}", flush=True)
    full = res["full"]
    seen = np.isfinite(full["best"]) & (full["best"] > -np.inf)
    thr = {f"p{p}": float(np.percentile(full["best"][seen], p)) for p in (10, 25, 50, 75, 90)}
    F_full = {k: full["lift"].unit_rows(getattr(full["lift"], k)) for k in ("method", "average", "best_view")}
    report = {"scene": common, "thresholds": thr, "variants": {}}
    for name, v in res.items():
        if name == "full":
            continue
        lf = v["lift"]
        both = seen & np.isfinite(v["best"])
        row = {
            "basis": lf.basis_info,
            "labels_equal_%": 100 * float((v["labels"] == full["labels"]).mean()),
            "average_labels_equal_%": 100 * float((v["bayes"] == full["bayes"]).mean()),
            "threshold_equal_%": {k: 100 * float(((v["best"][both] >= t) == (full["best"][both] >= t)).mean())
                                  for k, t in thr.items()},
            "best_cos_abs_err": {"median": float(np.median(np.abs(v["best"][both] - full["best"][both]))),
                                 "p99": float(np.percentile(np.abs(v["best"][both] - full["best"][both]), 99))},
            "miou": {"diffuser": v["metrics"]["miou"], "average": v["baseline"]["bayesian"]["miou"],
                     "best_view": v["baseline"].get("best_view", {}).get("miou")},
            "miou_full": {"diffuser": full["metrics"]["miou"], "average": full["baseline"]["bayesian"]["miou"],
                          "best_view": full["baseline"].get("best_view", {}).get("miou")},
            "calibration": {m: {k: (c.get(k), full["metrics"]["calibration"][m].get(k)) for k in ("ece", "nll", "brier")
                                if k in c} for m, c in v["metrics"]["calibration"].items()},
            "timings": {k: round(x, 2) for k, x in v["timings"].items()},
        }
        for k in ("method", "average", "best_view"):
            c = _cos_rows(lf.unit_rows(getattr(lf, k)), F_full[k])
            row[f"saved_cos_{k}"] = {"median": float(np.median(c)), "p5": float(np.percentile(c, 5)),
                                     "min": float(c.min())}
        report["variants"][name] = row
    print(json.dumps(report, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return report


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("speed")
    s.add_argument("--repeat", type=int, default=3)
    s.add_argument("--tree", action="append", default=[], help="NAME=PATH: a source tree (PYTHONPATH)")
    s.add_argument("--case", action="append", default=[],
                   help="NAME=[@TREE] OVERRIDES (space-separated); the first case is the reference (labels)")
    s.add_argument("--out", help="folder for the runs (default: a new temporary folder)")
    s.add_argument("common", nargs="*", help="overrides for every case (after --)")
    a = sub.add_parser("agree")
    a.add_argument("--variant", action="append", default=[], help="NAME=OVERRIDES (space-separated), beside full (default: auto=predictions.basis=auto)")
    a.add_argument("--json", help="write the report here")
    a.add_argument("common", nargs="*", help="the scene's overrides (after --)")
    args = ap.parse_args(argv)
    if args.cmd == "speed":
        speed(args)
    else:
        agree(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
