"""Two runs side by side: where they ran, per-class IoU deltas, the points whose label differs,
both scored on the points both label, and an .rrd showing both label sets on the same cloud; or two
groups of runs: their paired differences over matched seeds and scenes.

    python -m analysis.compare RUN_A RUN_B [--rrd compare.rrd]
    python -m analysis.compare SWEEP SWEEP --where-a method=bayesian --where-b method=diffuser

Two runs must label the same cloud (same scene, same number of points). The first line says
whether they ran on the same machine and versions (summary.json ``provenance``) or which fields
differ (CPU, ISA, numba target, numpy SIMD, BLAS, a package's version, the commit, ...): runs of
one seed on different machines may differ in their figures.

Two groups (a folder of runs on either side, or ``--where-a`` / ``--where-b KEY=VALUE`` picking
runs by their overrides): B - A per metric and per class over the seeds and scenes both ran, with a
95 % bootstrap interval and the sign-flip p-value (:mod:`analysis.paired`), every run scored on the
points all of them label; runs without a partner are listed. Runs of the validation and the test
split (summary.json ``split``): one error line, unless ``--mix-splits``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from analysis import paired
from analysis.runs import find_runs
from diffuser_lab.backends import provenance
from diffuser_lab.data.arrays import read_array
from diffuser_lab.runs.results import provenance_line


def _load(run: Path) -> tuple[dict, np.ndarray]:
    run = Path(run)
    s_path, l_path = run / "summary.json", run / "labels.npy"
    for p in (s_path, l_path):
        if not p.is_file():
            raise FileNotFoundError(f"{p}: missing; is {run} a diffuser-lab run folder?")
    return json.loads(s_path.read_text()), read_array(l_path, "labels", role=None)


def compare(run_a: str | Path, run_b: str | Path, rrd: str | Path | None = None) -> dict:
    """Per-class IoU of both runs and their difference (b - a), and label disagreement."""
    sa, la = _load(run_a)
    sb, lb = _load(run_b)
    if la.shape != lb.shape:
        raise ValueError(f"the runs label different clouds: {la.shape[0]} vs {lb.shape[0]} points")
    ia = (sa.get("metrics") or {}).get("per_class_iou") or {}
    ib = (sb.get("metrics") or {}).get("per_class_iou") or {}
    classes = sorted(set(ia) | set(ib), key=lambda c: -(ib.get(c, 0) - ia.get(c, 0)))
    per_class = [{"class": c, "a": ia.get(c), "b": ib.get(c),
                  "delta": None if c not in ia or c not in ib else ib[c] - ia[c]} for c in classes]
    differ = la != lb
    out = {"a": str(run_a), "b": str(run_b), "miou_a": (sa.get("metrics") or {}).get("miou"),
           "miou_b": (sb.get("metrics") or {}).get("miou"), "n_points": int(la.size),
           "n_differ": int(differ.sum()), "share_differ": float(differ.mean()) if la.size else 0.0,
           "per_class": per_class, "provenance": _provenance(sa, sb), "common": _common(run_a, run_b)}
    if rrd is not None:
        _write_rrd(Path(run_a), Path(run_b), la, lb, Path(rrd), sa)
        out["rrd"] = str(rrd)
    return out


def _common(run_a, run_b) -> dict | None:
    """Both runs scored on the points both label (and their Bayesian baselines, when saved):
    ``{"points", "of", "a": {miou, accuracy}, "b": {...}}``; None without gt_labels.npy."""
    runs = find_runs([run_a])[:1] + find_runs([run_b])[:1]
    support = paired.common_support(runs, unit=lambda r: ())
    if len(support.scores) != 2 or len(support.sizes) != 1:
        return None
    _, points, of = support.sizes[0]
    side = lambda r: {"miou": support.scores[r.path]["miou_common"], "accuracy": support.scores[r.path]["accuracy_common"]}  # noqa: E731
    return {"points": points, "of": of, "baseline": support.baseline, "a": side(runs[0]), "b": side(runs[1])}


def _select(path: str | Path, where: dict | None, side: str) -> list:
    """The finished runs under ``path`` whose overrides match ``where``; one line when none."""
    runs = [r for r in find_runs([path]) if r.status == "ok"]
    if where:
        runs = [r for r in runs if all(paired.config_value(r, k) == v for k, v in where.items())]
    if not runs:
        picked = f" with {paired.config_label(where)}" if where else ""
        raise ValueError(f"{path}: no finished run{picked} for group {side}")
    return runs


def compare_groups(a: str | Path, b: str | Path, where_a: dict | None = None, where_b: dict | None = None,
                   mix_splits: bool = False) -> dict:
    """B - A over the seeds and scenes both groups ran (module docstring): ``differences`` metric ->
    :meth:`analysis.paired.Difference.as_dict`, ``per_class`` [{class, ...}], ``units`` paired,
    ``unmatched`` lines, ``support`` the common support's sentence."""
    ra, rb = _select(a, where_a, "A"), _select(b, where_b, "B")
    paired.check_splits(ra + rb, mix_splits)
    for side, runs, flag in (("A", ra, "--where-a"), ("B", rb, "--where-b")):
        seen: dict = {}
        for r in runs:
            u = paired.unit_of(r)
            if u in seen:
                keys = paired.config_keys(runs)
                hint = f" (they differ in {', '.join(keys)})" if keys else ""
                raise ValueError(f"group {side} holds two runs at {paired.unit_label(u)}: `{seen[u].path}` and `{r.path}`"
                                 f"{hint}; pick one configuration with {flag} KEY=VALUE")
            seen[u] = r
    support = paired.common_support(ra + rb)
    metrics = paired.metrics_of(ra + rb, support)
    unmatched: list[str] = []
    diffs, per_class, units = paired.pair_up(rb, ra, unmatched, metrics, support, "group A")
    unmatched += [f"`{r.path.name}`: no run of group B at {paired.unit_label(u)}"
                  for u, r in ((paired.unit_of(r), r) for r in ra) if u not in set(units)]
    return {"a": str(a), "b": str(b), "where_a": where_a or {}, "where_b": where_b or {}, "runs_a": len(ra),
            "runs_b": len(rb), "units": [paired.unit_label(u) for u in units],
            "differences": {m: d.as_dict() for m, d in diffs.items()},
            "per_class": [{"class": c, **d.as_dict()} for c, d in sorted(per_class.items(), key=lambda kv: kv[0])],
            "unmatched": sorted(set(unmatched)), "support": support.line(),
            "machines": provenance_line(ra + rb, "runs")}


def _cell(d: dict, digits: int = 1) -> str:
    return paired.Difference(**{k: d[k] for k in ("n", "mean", "low", "high", "p", "exact")}).cell(digits)


def group_lines(res: dict) -> list[str]:
    """What :func:`main` prints of :func:`compare_groups`'s dict."""
    pick = lambda w: f" ({paired.config_label(w)})" if w else ""  # noqa: E731
    lines = [f"A: {res['a']}{pick(res['where_a'])}: {res['runs_a']} runs",
             f"B: {res['b']}{pick(res['where_b'])}: {res['runs_b']} runs"]
    if res["machines"]:
        lines.append(res["machines"])
    lines.append(f"B - A over {len(res['units'])} pairs ({'; '.join(res['units']) or 'none'}): mean [95 % bootstrap "
                 "interval] two-sided sign-flip p; n.s.: the interval crosses 0 or p >= 0.05")
    lines += [f"  {m:18s}{_cell(d, paired.digits(m))}" for m, d in res["differences"].items()]
    if res["support"]:
        lines.append(res["support"])
    lines.append(f"{'class':16s}B - A (IoU)")
    lines += [f"{r['class']:16s}{_cell(r)}" for r in res["per_class"]]
    if res["unmatched"]:
        lines.append("without a partner: " + "; ".join(res["unmatched"]))
    return lines


def _provenance(sa: dict, sb: dict) -> dict:
    """Where both ran (:func:`diffuser_lab.backends.provenance.summary_line`), ``same`` (None when a
    run has no block), ``differs``: [{field, a, b}] of the compared fields that differ, and the tile
    machines unlike its driver's of a tiled run (``tiles_a``, ``tiles_b``: [{tiles, nodes, differs}])."""
    pa, pb = sa.get("provenance"), sb.get("provenance")
    differs = [{"field": f, "a": va, "b": vb} for f, va, vb in provenance.blocks_differ(pa, pb)]
    out = {"a": provenance.summary_line(pa), "b": provenance.summary_line(pb),
           "same": None if not pa or not pb else not differs, "differs": differs}
    for side, s in (("tiles_a", sa), ("tiles_b", sb)):
        other = [m for m in ((s.get("tiling") or {}).get("machines") or []) if m.get("differs")]
        if other:
            out[side] = [{k: m.get(k) for k in ("tiles", "nodes", "differs")} for m in other]
    return out


def provenance_lines(p: dict) -> list[str]:
    """What :func:`main` prints of :func:`_provenance`'s dict."""
    if p["same"] is None:
        lines = [f"ran on: A {p['a']}", f"        B {p['b']}"]
    elif p["same"]:
        lines = [f"ran on the same machine and versions: {p['a']}"]
    else:
        lines = [f"ran on different machines or versions: {', '.join(d['field'] for d in p['differs'])} differ"]
        lines += [f"  {d['field']:22s} A {d['a']}\n  {'':22s} B {d['b']}" for d in p["differs"]]
    for side in ("a", "b"):
        for m in p.get(f"tiles_{side}", []):
            lines.append(f"{side.upper()}: {len(m['tiles'])} tiles ran on {', '.join(map(str, m['nodes']))} "
                         f"({', '.join(m['differs'])} differ from the run's)")
    return lines


def _write_rrd(run_a: Path, run_b: Path, la: np.ndarray, lb: np.ndarray, rrd: Path, summary: dict) -> None:
    """world/a and world/b: the cloud coloured by each run's labels (same class colours);
    world/differ: the points whose labels differ, in red."""
    import open3d as o3d
    import rerun as rr

    ply = run_a / "labels.ply"
    if not ply.is_file():
        raise FileNotFoundError(f"{ply}: missing (run with output.labels_ply=true to compare in Rerun)")
    pcd = o3d.t.io.read_point_cloud(str(ply))
    if "positions" not in pcd.point or pcd.point.positions.shape[0] != la.size:
        raise ValueError(f"{run_a / 'labels.ply'}: missing, or not the {la.size} points of labels.npy")
    pts = pcd.point.positions.numpy()
    from diffuser_lab.recording.rerun_log import annotation_context, class_ids

    names, colors = _classes(summary, pcd, la)
    rec = rr.RecordingStream("diffuser-lab-compare")
    rrd.parent.mkdir(parents=True, exist_ok=True)  # --rrd results/x.rrd on a fresh checkout
    rec.save(str(rrd))
    rec.log("world", annotation_context(names, colors), static=True)
    rec.log("world/a", rr.Points3D(pts, class_ids=class_ids(la)), static=True)
    rec.log("world/b", rr.Points3D(pts, class_ids=class_ids(lb)), static=True)
    d = la != lb
    rec.log("world/differ", rr.Points3D(pts[d], colors=np.tile([255, 0, 0], (int(d.sum()), 1)).astype(np.uint8),
                                        radii=0.01), static=True)
    rec.flush()


def _classes(summary: dict, pcd, labels: np.ndarray) -> tuple[tuple, np.ndarray]:
    """Class names and colours of run A's taxonomy: a shipped one by its summary.json name; for
    taxonomy=file / ids runs, names class_<c> and the colours labels.ply gave each class."""
    from diffuser_lab.data.taxonomy import load_taxonomy

    try:
        tax = load_taxonomy(summary.get("taxonomy") or "scannet20")
        return tax.names, tax.colors
    except FileNotFoundError:
        n = int(summary.get("n_classes") or labels.max() + 1)
        colors = np.zeros((n, 3), np.uint8)
        if "colors" in pcd.point:
            c = pcd.point.colors.numpy()
            c = (c * 255).round() if c.dtype.kind == "f" else c
            ok = (labels >= 0) & (labels < n)
            colors[labels[ok]] = c[ok].astype(np.uint8)
        return tuple(f"class_{i}" for i in range(n)), colors


def _is_run(path: str) -> bool:
    return (Path(path) / "summary.json").is_file()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m analysis.compare", description=__doc__.splitlines()[0])
    ap.add_argument("run_a", help="a run folder, or a folder of runs (group A)")
    ap.add_argument("run_b", help="a run folder, or a folder of runs (group B)")
    ap.add_argument("--where-a", action="append", default=[], metavar="KEY=VALUE",
                    help="group A: the runs with these overrides (repeat or comma-separate)")
    ap.add_argument("--where-b", action="append", default=[], metavar="KEY=VALUE", help="group B: likewise")
    ap.add_argument("--mix-splits", action="store_true",
                    help="allow runs of the validation and the test split (summary.json split) together")
    ap.add_argument("--rrd", help="two runs: write an .rrd with both label sets (open with `rerun FILE`)")
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    a = ap.parse_args(argv)
    groups = a.where_a or a.where_b or not (_is_run(a.run_a) and _is_run(a.run_b))
    try:
        if groups:
            if a.rrd:
                raise ValueError("--rrd: two run folders only (a folder of runs or --where-a/-b compares groups)")
            res = compare_groups(a.run_a, a.run_b, paired.parse_assignments(a.where_a, "--where-a"),
                                 paired.parse_assignments(a.where_b, "--where-b"), a.mix_splits)
        else:
            paired.check_splits(find_runs([a.run_a, a.run_b]), a.mix_splits)
            res = compare(a.run_a, a.run_b, a.rrd)
    except (FileNotFoundError, ValueError) as exc:
        print(f"compare: error: {exc}", file=sys.stderr)
        return 2
    if a.json:
        print(json.dumps(res, indent=2))
        return 0
    if groups:
        print("\n".join(group_lines(res)))
        return 0
    f = lambda v: "-" if v is None else f"{v:.1f}"  # noqa: E731
    print(f"A: {res['a']}\nB: {res['b']}")
    print("\n".join(provenance_lines(res["provenance"])))
    print(f"mIoU  A {f(res['miou_a'])}  B {f(res['miou_b'])}   labels differ on {res['n_differ']:,} of "
          f"{res['n_points']:,} points ({100 * res['share_differ']:.1f}%)")
    c = res["common"]
    if c:
        both = "both runs" + (" and their Bayesian baselines" if c["baseline"] else "")
        print(f"on the {c['points']:,} points {both} label ({100 * c['points'] / max(c['of'], 1):.1f}%): "
              f"mIoU A {f(c['a']['miou'])}  B {f(c['b']['miou'])}, accuracy A {f(c['a']['accuracy'])}  "
              f"B {f(c['b']['accuracy'])}")
    print(f"{'class':16s}{'A':>7s}{'B':>7s}{'B-A':>7s}")
    for r in res["per_class"]:
        print(f"{r['class']:16s}{f(r['a']):>7s}{f(r['b']):>7s}{f(r['delta']):>7s}")
    if "rrd" in res:
        print(f"both label sets: {res['rrd']} (rerun {res['rrd']})")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    raise SystemExit(main())
