"""Two runs side by side: where they ran, per-class IoU deltas, the points whose label differs,
and an .rrd showing both label sets on the same cloud.

    python -m analysis.compare RUN_A RUN_B [--rrd compare.rrd]

Both runs must label the same cloud (same scene, same number of points). The first line says
whether they ran on the same machine and versions (summary.json ``provenance``) or which fields
differ (CPU, ISA, numba target, numpy SIMD, BLAS, a package's version, the commit, ...): runs of
one seed on different machines may differ in their figures.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from diffuser_lab.backends import provenance


def _load(run: Path) -> tuple[dict, np.ndarray]:
    run = Path(run)
    s_path, l_path = run / "summary.json", run / "labels.npy"
    for p in (s_path, l_path):
        if not p.is_file():
            raise FileNotFoundError(f"{p}: missing; is {run} a diffuser-lab run folder?")
    return json.loads(s_path.read_text()), np.load(l_path)


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
           "per_class": per_class, "provenance": _provenance(sa, sb)}
    if rrd is not None:
        _write_rrd(Path(run_a), Path(run_b), la, lb, Path(rrd), sa)
        out["rrd"] = str(rrd)
    return out


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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m analysis.compare", description=__doc__.splitlines()[0])
    ap.add_argument("run_a")
    ap.add_argument("run_b")
    ap.add_argument("--rrd", help="write an .rrd with both label sets (open with `rerun FILE`)")
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    a = ap.parse_args(argv)
    try:
        res = compare(a.run_a, a.run_b, a.rrd)
    except (FileNotFoundError, ValueError) as exc:
        print(f"compare: error: {exc}", file=sys.stderr)
        return 2
    if a.json:
        print(json.dumps(res, indent=2))
        return 0
    f = lambda v: "-" if v is None else f"{v:.1f}"  # noqa: E731
    print(f"A: {res['a']}\nB: {res['b']}")
    print("\n".join(provenance_lines(res["provenance"])))
    print(f"mIoU  A {f(res['miou_a'])}  B {f(res['miou_b'])}   labels differ on {res['n_differ']:,} of "
          f"{res['n_points']:,} points ({100 * res['share_differ']:.1f}%)")
    print(f"{'class':16s}{'A':>7s}{'B':>7s}{'B-A':>7s}")
    for r in res["per_class"]:
        print(f"{r['class']:16s}{f(r['a']):>7s}{f(r['b']):>7s}{f(r['delta']):>7s}")
    if "rrd" in res:
        print(f"both label sets: {res['rrd']} (rerun {res['rrd']})")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    raise SystemExit(main())
