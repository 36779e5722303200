"""Depth diagnostics, beside the sensor model rather than in it: what a model did to rendered depth
against the perfect render (:func:`depth_error_report`, by range bin) and the holes of any depth image
set on its own, real or modelled (:func:`depth_hole_stats`); ``diffuser-lab-depth-report`` prints them.

Conventions: depth (H, W) float32 z-depth in metres along the optical axis, 0 = no depth; K (3, 3)
pixels with pixel centres at integer coordinates.
"""
from __future__ import annotations

from typing import Iterable, Optional, Sequence

import numpy as np
from scipy import ndimage

from .geometry import normals_from_depth
from .sensor import axial_sigma, incidence_angles

__all__ = ["depth_error_report", "format_depth_report", "depth_hole_stats", "format_hole_stats", "share_of",
           "DEFAULT_BINS", "HOLE_ANGLE_BINS", "GAP_BINS", "HOLE_RANGE_BINS"]

DEFAULT_BINS = (0.5, 1.0, 2.0, 3.0, 4.5)  # metres, the report's range bins


def depth_error_report(perfect: np.ndarray | Iterable[np.ndarray], noisy: np.ndarray | Iterable[np.ndarray],
                       bins: Sequence[float] = DEFAULT_BINS, outlier: float = 0.1) -> dict:
    """What a sensor model did to depth, against the perfect render, by range of the perfect depth.

    Args:
        perfect, noisy: (H, W) depth images in metres (0 = none), or equal-length iterables of them.
        bins: increasing range-bin edges, metres; pixels outside them form no bin but count in ``all``.
        outlier: |error| in metres above which a pixel counts as an outlier (edge pixels that took
            another surface's depth).

    Returns:
        ``{"bins": [row, ...], "all": row}``, each row with ``range`` [lo, hi] m, ``pixels`` (perfect
        depth in range), ``holes`` (share of them without sensor depth), ``rmse`` and ``bias`` (metres,
        over pixels with both), ``inlier_rmse`` (m, |error| <= outlier), ``outliers`` (share with
        |error| > outlier), and for the bins ``sigma_model`` (Nguyen's sigma_z at the bin's centre,
        theta = 0). ``spurious``: pixels with sensor but no perfect depth.
    """
    if isinstance(perfect, np.ndarray) and perfect.ndim == 2:
        perfect, noisy = [perfect], [noisy]
    p = np.concatenate([np.asarray(a, np.float64).ravel() for a in perfect])
    q = np.concatenate([np.asarray(a, np.float64).ravel() for a in noisy])
    if p.shape != q.shape:
        raise ValueError(f"perfect and noisy depth differ in size ({p.size} vs {q.size} pixels)")
    edges = np.asarray(bins, np.float64)
    if edges.ndim != 1 or len(edges) < 2 or np.any(np.diff(edges) <= 0):
        raise ValueError(f"bins={list(bins)}: expected at least two increasing edges (metres)")

    def row(sel: np.ndarray, lo: float, hi: float) -> dict:
        n = int(sel.sum())
        both = sel & (q > 0)
        err = q[both] - p[both]
        inl = np.abs(err) <= outlier
        out = {"range": [float(lo), float(hi)], "pixels": n,
               "holes": float(1.0 - both.sum() / n) if n else None,
               "rmse": float(np.sqrt(np.mean(err**2))) if err.size else None,
               "bias": float(np.mean(err)) if err.size else None,
               "inlier_rmse": float(np.sqrt(np.mean(err[inl] ** 2))) if inl.any() else None,
               "outliers": float(np.mean(~inl)) if err.size else None}
        return out

    rows = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        r = row((p >= lo) & (p < hi), lo, hi)
        r["sigma_model"] = float(axial_sigma(np.array(0.5 * (lo + hi))))
        rows.append(r)
    all_row = row(p > 0, 0.0, float(p.max(initial=0.0)))
    return {"bins": rows, "all": all_row, "spurious": int(((p <= 0) & (q > 0)).sum())}


def format_depth_report(rep: dict) -> str:
    """The report of :func:`depth_error_report` as a markdown table (millimetres and percent)."""
    def mm(x):
        return "-" if x is None else f"{1000 * x:.1f}"

    def pc(x):
        return "-" if x is None else f"{100 * x:.1f}"

    lines = ["| range [m] | pixels | holes % | RMSE mm | inlier RMSE mm | sigma_z(bin centre, 0 deg) mm | bias mm | outliers % |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rep["bins"] + [rep["all"]]:
        lo, hi = r["range"]
        name = "all" if r is rep["all"] else f"{lo:g}-{hi:g}"
        lines.append(f"| {name} | {r['pixels']:,} | {pc(r['holes'])} | {mm(r['rmse'])} | {mm(r['inlier_rmse'])} | "
                     f"{mm(r.get('sigma_model'))} | {mm(r['bias'])} | {pc(r['outliers'])} |")
    return "\n".join(lines)


HOLE_ANGLE_BINS = (0.0, 45.0, 60.0, 70.0, 75.0, 80.0, 90.0)  # degrees, the hole report's incidence bins
GAP_BINS = (0, 1, 3, 5, 9)  # hole-gap lengths (640-px pixels): 0, 1-2, 3-4, 5-8, >= 9 (up to max_gap_px)
HOLE_RANGE_BINS = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.5)  # metres, the hole report's range bins


def _jump_gaps(d: np.ndarray, rel: float, max_gap: int) -> np.ndarray:
    """Hole gaps across depth jumps along the rows of ``d`` (H, W; 0 = no depth).

    Consecutive valid pixels of a row, ``(r, a)`` and ``(r, b)`` with ``b - a - 1 <= max_gap`` holes
    between them, whose depths differ by more than ``rel`` x the nearer: returns the (J,) int gaps
    ``b - a - 1`` (0 = the jump is between two valid neighbours, no hole).
    """
    r, c = np.nonzero(d > 0)  # row-major: consecutive entries of a row are its consecutive valid pixels
    same = r[1:] == r[:-1]
    gap = c[1:] - c[:-1] - 1
    za, zb = d[r[:-1], c[:-1]], d[r[1:], c[1:]]
    jump = same & (gap <= max_gap) & (np.abs(za - zb) > rel * np.minimum(za, zb))
    return gap[jump]


def depth_hole_stats(depths: np.ndarray | Iterable[np.ndarray], Ks: np.ndarray | Iterable[np.ndarray],
                     ignore: Optional[Iterable[Optional[np.ndarray]]] = None, edge_jump: float = 0.05,
                     radius_px: float = 2.0, blob_px: float = 400.0, max_gap_px: int = 16,
                     bins: Sequence[float] = HOLE_RANGE_BINS, angle_bins: Sequence[float] = HOLE_ANGLE_BINS,
                     normals_window: int = 5) -> dict:
    """The holes of a depth image set on its own (no perfect reference: real or modelled depth alike).

    Pixel sizes are given for a 640-px-wide image and scaled by ``W / 640`` (areas by its square), so
    a 320x240 render and a 640x480 sensor frame are measured over the same angles. Every pixel
    (``ignore`` and dead-border pixels excepted) falls in one class, from the valid depths of its
    ``(2r+1) x (2r+1)`` window, ``r = max(1, round(radius_px W / 640))`` (5x5 at 640 px, 3x3 at 320):

    - ``discontinuity``: the window's valid depths span more than ``edge_jump`` x its nearest one
      (``max - min > edge_jump * min``: the model's ``edge_jump`` rule, over a window instead of a
      4-neighbour pair, so that a hole band between the two sides still sees both);
    - ``smooth``: the window holds valid depth that spans less;
    - ``interior``: the window holds no valid depth (inside a hole wider than the window).

    Args:
        depths: (H, W) metres, 0 = no depth, or an iterable of them.
        Ks: (3, 3) intrinsics (pixels) of each image, or one for all.
        ignore: per image, None or (H, W) bool pixels that count nowhere and give no depth (e.g. where
            a render hit no mesh: those are not the sensor's holes).
        edge_jump: relative depth span of a discontinuity (the model's ``depth.edge_jump``).
        radius_px: window radius, 640-px pixels.
        blob_px: a hole's 8-connected component larger than this (640-px pixels^2) is a ``blob``
            (window, mirror, out of range, dead margin piece), else ``thin``.
        max_gap_px: the longest hole run (640-px pixels) still counted as a gap across one jump.
        bins: range-bin edges, metres: a pixel's range is its depth, for a hole the depth of its
            nearest valid pixel (Euclidean in the image; ties: scipy's ``distance_transform_edt``).
        angle_bins: incidence-bin edges, degrees: the angle between the ray and the normal estimated
            from the depth (:func:`normals_from_depth`, box-smoothed over ``normals_window`` 640-px
            pixels); a hole takes its nearest valid pixel's; over ``smooth`` pixels only (normals
            across a discontinuity are meaningless).

    Returns:
        A dict of shares (0-1) and counts: ``frames``, ``pixels`` (counted), ``holes`` (share of all
        pixels not ignored, dead border included), ``holes_in`` (share of counted pixels), ``border`` (the dead
        margin: the rows/columns, running in from an image edge, without depth in any image of a
        same-size set of >= 2 images; share of all pixels), ``classes`` {class: {pixels, holes (share of the class's pixels without depth),
        of_holes (share of all counted holes)}}, ``blobs`` {blob, thin: share of counted holes},
        ``gaps`` {jumps (row-wise, 640-px units; see :func:`_jump_gaps`), mean_px, hist [(lo, hi,
        share)]}, ``range`` and ``angle`` [{range/deg [lo, hi], pixels, holes}], ``valid_beyond``
        {deg: share of valid smooth pixels with incidence above deg, for 70 75 80},
        ``valid_below_0_5m`` (share of valid depth < 0.5 m).
    """
    if isinstance(depths, np.ndarray) and depths.ndim == 2:
        depths = [depths]
    ds = [np.asarray(a, np.float64) for a in depths]
    if not ds:
        raise ValueError("depth_hole_stats: no depth images")
    if any(d.ndim != 2 for d in ds):
        raise ValueError(f"depth images have shapes {sorted({d.shape for d in ds})}, expected (H, W)")
    Ks = [np.asarray(Ks, np.float64)] * len(ds) if np.ndim(Ks) == 2 else [np.asarray(k, np.float64) for k in Ks]
    igs = [None] * len(ds) if ignore is None else list(ignore)
    if len(Ks) != len(ds) or len(igs) != len(ds):
        raise ValueError(f"{len(ds)} depth images but {len(Ks)} intrinsics and {len(igs)} ignore masks")
    edges, aedges = np.asarray(bins, np.float64), np.asarray(angle_bins, np.float64)
    # dead margin (ScanNet's registered depth: 27 columns, 5 rows): edge rows/columns no image has depth in
    same = len({d.shape for d in ds}) == 1 and len(ds) >= 2
    border = None
    if same:
        anyv = np.any([d > 0 for d in ds], axis=0)

        def margin(has: np.ndarray) -> np.ndarray:  # the empty lines running in from either edge
            lead = np.cumsum(has) == 0
            return lead | (np.cumsum(has[::-1]) == 0)[::-1]

        border = margin(anyv.any(axis=0))[None, :] | margin(anyv.any(axis=1))[:, None]

    cls_names = ("discontinuity", "smooth", "interior")
    tot = dict(all=0, seen=0, all_holes=0, pixels=0, holes=0, blob=0, border=0, below=0, valid=0)
    cls_n, cls_h = np.zeros(3, np.int64), np.zeros(3, np.int64)
    rng_n, rng_h = np.zeros(len(edges) - 1, np.int64), np.zeros(len(edges) - 1, np.int64)
    ang_n, ang_h = np.zeros(len(aedges) - 1, np.int64), np.zeros(len(aedges) - 1, np.int64)
    beyond = {70.0: 0, 75.0: 0, 80.0: 0}
    valid_smooth = 0
    gaps = []
    for d, K, ig in zip(ds, Ks, igs):
        h, w = d.shape
        s = w / 640.0
        ig = np.zeros((h, w), bool) if ig is None else np.asarray(ig, bool)
        if ig.shape != d.shape:
            raise ValueError(f"ignore mask has shape {ig.shape}, expected {d.shape}")
        d = np.where(ig, 0.0, d)
        valid = d > 0
        counted = ~ig if border is None else ~ig & ~border
        hole = counted & ~valid
        tot["all"] += h * w
        tot["seen"] += int((~ig).sum())
        tot["all_holes"] += int((~valid & ~ig).sum())
        tot["border"] += 0 if border is None else int(border.sum())
        tot["pixels"] += int(counted.sum())
        tot["holes"] += int(hole.sum())
        tot["valid"] += int(valid.sum())
        tot["below"] += int((valid & (d < 0.5)).sum())

        # classes from the window's valid depths
        size = 2 * max(1, int(round(radius_px * s))) + 1
        dmax = ndimage.maximum_filter(np.where(valid, d, -np.inf), size=size, mode="constant", cval=-np.inf)
        dmin = ndimage.minimum_filter(np.where(valid, d, np.inf), size=size, mode="constant", cval=np.inf)
        has = np.isfinite(dmax)
        disc = has & (dmax - dmin > edge_jump * np.where(has, dmin, 1.0))
        cls = np.where(disc, 0, np.where(has, 1, 2))
        cls_n += np.bincount(cls[counted], minlength=3)
        cls_h += np.bincount(cls[hole], minlength=3)

        # blobs: 8-connected hole components
        lab, n = ndimage.label(hole, structure=np.ones((3, 3), bool))
        if n:
            area = np.bincount(lab.ravel())
            tot["blob"] += int(area[1:][area[1:] > blob_px * s * s].sum())

        # gaps across jumps, along rows (the projector's baseline is horizontal) and columns
        mg = int(round(max_gap_px * s))
        g = np.concatenate([_jump_gaps(d, edge_jump, mg), _jump_gaps(d.T, edge_jump, mg)])
        gaps.append(g / s)

        if not valid.any():
            continue
        # range: own depth, or the nearest valid pixel's
        near = ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)
        zr = d[near[0], near[1]]
        bi = np.digitize(zr, edges) - 1
        inb = counted & (bi >= 0) & (bi < len(edges) - 1)
        rng_n += np.bincount(bi[inb], minlength=len(edges) - 1)
        rng_h += np.bincount(bi[inb & hole], minlength=len(edges) - 1)

        # incidence from normals estimated on the depth; smooth pixels with a known normal only
        win = max(1, int(round(normals_window * s)) | 1)
        nrm = normals_from_depth(d, K, window=win)
        known = np.linalg.norm(nrm, axis=-1) > 0
        th = np.rad2deg(incidence_angles(nrm, K))
        th_near, known_near = th[near[0], near[1]], known[near[0], near[1]]
        ai = np.digitize(th_near, aedges) - 1
        ina = counted & (cls == 1) & known_near & (ai >= 0) & (ai < len(aedges) - 1)
        ang_n += np.bincount(ai[ina], minlength=len(aedges) - 1)
        ang_h += np.bincount(ai[ina & hole], minlength=len(aedges) - 1)
        vs = counted & (cls == 1) & valid & known
        valid_smooth += int(vs.sum())
        for a in beyond:
            beyond[a] += int((vs & (th > a)).sum())

    def share(a, b):
        return float(a / b) if b else None

    g = np.concatenate(gaps) if gaps else np.zeros(0)
    gb = np.asarray(GAP_BINS + (np.inf,), np.float64)
    hist = [(float(lo), float(hi), share(int(((g >= lo) & (g < hi)).sum()), g.size))
            for lo, hi in zip(gb[:-1], gb[1:])]
    return {
        "frames": len(ds), "pixels": tot["pixels"],
        "holes": share(tot["all_holes"], tot["seen"]),
        "holes_in": share(tot["holes"], tot["pixels"]),
        "border": share(tot["border"], tot["all"]),
        "classes": {c: {"pixels": int(cls_n[i]), "holes": share(cls_h[i], cls_n[i]),
                        "of_holes": share(cls_h[i], tot["holes"])} for i, c in enumerate(cls_names)},
        "blobs": {"blob": share(tot["blob"], tot["holes"]), "thin": share(tot["holes"] - tot["blob"], tot["holes"])},
        "gaps": {"jumps": int(g.size), "mean_px": float(g.mean()) if g.size else None, "hist": hist},
        "range": [{"range": [float(lo), float(hi)], "pixels": int(n), "holes": share(k, n)}
                  for lo, hi, n, k in zip(edges[:-1], edges[1:], rng_n, rng_h)],
        "angle": [{"deg": [float(lo), float(hi)], "pixels": int(n), "holes": share(k, n)}
                  for lo, hi, n, k in zip(aedges[:-1], aedges[1:], ang_n, ang_h)],
        "valid_beyond": {f"{a:g}": share(v, valid_smooth) for a, v in beyond.items()},
        "valid_below_0_5m": share(tot["below"], tot["valid"]),
    }


def format_hole_stats(columns: Sequence[tuple[str, dict]]) -> str:
    """:func:`depth_hole_stats` of one or more depth sets side by side, a markdown table (percent)."""
    def pc(x):
        return "-" if x is None else f"{100 * x:.1f}"

    cols = list(columns)
    rows = [("frames", lambda r: f"{r['frames']}"),
            ("counted pixels", lambda r: f"{r['pixels']:,}"),
            ("holes %, all pixels", lambda r: pc(r["holes"])),
            ("dead border % of the image", lambda r: pc(r["border"])),
            ("holes %, counted pixels (border out)", lambda r: pc(r["holes_in"]))]
    for c in ("discontinuity", "smooth", "interior"):
        rows.append((f"{c} pixels: % of counted", lambda r, c=c: pc(share_of(r, c))))
        rows.append((f"{c} pixels: holes %", lambda r, c=c: pc(r["classes"][c]["holes"])))
        rows.append((f"{c}: % of the holes", lambda r, c=c: pc(r["classes"][c]["of_holes"])))
    rows += [("holes in blobs > 400 px (640-px) %", lambda r: pc(r["blobs"]["blob"])),
             ("jumps crossed (rows + cols)", lambda r: f"{r['gaps']['jumps']:,}"),
             ("mean hole gap across a jump, 640-px", lambda r: "-" if r["gaps"]["mean_px"] is None
              else f"{r['gaps']['mean_px']:.2f}")]
    for i, (lo, hi, _) in enumerate(cols[0][1]["gaps"]["hist"]):
        name = f"{lo:g}" if hi == lo + 1 else (f">= {lo:g}" if not np.isfinite(hi) else f"{lo:g}-{hi - 1:g}")
        rows.append((f"jumps with a gap of {name} px %", lambda r, i=i: pc(r["gaps"]["hist"][i][2])))
    for i, b in enumerate(cols[0][1]["range"]):
        rows.append((f"holes % at range {b['range'][0]:g}-{b['range'][1]:g} m (pixels)",
                     lambda r, i=i: f"{pc(r['range'][i]['holes'])} ({r['range'][i]['pixels']:,})"))
    for i, b in enumerate(cols[0][1]["angle"]):
        rows.append((f"smooth holes % at incidence {b['deg'][0]:g}-{b['deg'][1]:g} deg (pixels)",
                     lambda r, i=i: f"{pc(r['angle'][i]['holes'])} ({r['angle'][i]['pixels']:,})"))
    for a in cols[0][1]["valid_beyond"]:
        rows.append((f"valid smooth depth beyond {a} deg %", lambda r, a=a: pc(r["valid_beyond"][a])))
    rows.append(("valid depth < 0.5 m %", lambda r: pc(r["valid_below_0_5m"])))
    lines = ["| statistic | " + " | ".join(n for n, _ in cols) + " |", "|---|" + "---:|" * len(cols)]
    lines += [f"| {name} | " + " | ".join(f(r) for _, r in cols) + " |" for name, f in rows]
    return "\n".join(lines)


def share_of(rep: dict, cls: str) -> Optional[float]:
    """The share of counted pixels in class ``cls`` of a :func:`depth_hole_stats` report."""
    return rep["classes"][cls]["pixels"] / rep["pixels"] if rep["pixels"] else None
