"""run.rrd: the diffusion as a Rerun recording (rerun-sdk >= 0.41, one explicit stream per run).

Entity tree (``world`` is z-up, metres; class colours come from the AnnotationContext on ``world``)::

    world                          AnnotationContext (taxonomy names + colours; id 65535 = unlabeled)
    world/scene/points             Points3D, static: the input cloud (input colours, else grey)
    world/scene/ground_truth       Points3D, static: ground-truth class ids (when known)
    world/cameras/<i>              Transform3D + Pinhole, static; children labels (SegmentationImage,
                                   the 2D predictions), rgb (Image, if any)
    world/depth/<i>                Transform3D + Pinhole + DepthImage (mm), static: the same frame's
                                   depth, apart so that views can leave its back-projected cloud out,
                                   coarser (record.max_depth_side) under a pinhole of its own
    world/evidence/bayesian        Points3D, static: work points that received pixel mass, Bayesian labels
    world/evidence/unseen          Points3D, static: work points no pixel reached
    world/diffusion/labels         Points3D: positions static, class ids per recorded iteration
    world/diffusion/confidence     Points3D: positions static, class id = max_c Z / sum_c Z in 1/64 steps
                                   per iteration (its own AnnotationContext: viridis colours, labels)
    world/diffusion/wrong          Points3D per iteration: annotated points whose label is wrong, in
                                   :func:`wrong_color` (a colour no class of the taxonomy has)
    world/result/confidence        Points3D, static (``output.scores=true``): the original points coloured
                                   by their top score (viridis), its values as components ``confidence``
                                   (top score), ``margin`` (top - second) and ``entropy`` (nats) of the
                                   distribution scores.npy saves (NaN entropy: no distribution)
    world/scores/<class>           Points3D: positions static, colour = Z_ic / sum_c Z_ic (viridis) and
                                   the value (component ``score``) per iteration; only in a re-logged
                                   .rrd (``diffuser-lab-inspect RUN --to-rrd OUT --scores chair,table``)
    legend                     Image + values (classes, colors), static: the classes present (ground
                               truth, labels), unlabeled, wrong label; the confidence scale
    metrics/miou|accuracy|confidence       Scalars at every iteration (the backend's statistics in its step:
                                           :func:`~.steps.metrics_rows`), the clouds above on the schedule
    metrics/residual_log10                 log10 of the relative residual (none where it is 0)
    metrics/changed_per_iter_log10         log10 of the labels changed per iteration since the previous
                                           one logged, n_changed / (iteration - previous) (none where 0)

Every per-iteration entity is on the ``diffusion_step`` sequence timeline.

An online run (protocol=online, :meth:`RerunRecorder.log_online_frame`) has, besides the static
``world``, ``world/scene/*``, on the ``frame`` sequence timeline (= the frame's index)::

    world/online/labels/<b>        Points3D: block b of the map (rows b x B ... (b + 1) x B - 1 in map
                                   order, B = :data:`ONLINE_BLOCK_ROWS`; a given map is one block
                                   0000), class ids of the online Diffuser every frame, positions
                                   logged again only on frames that added points to the block
    world/online/bayesian/<b>      Points3D: the same blocks, online Bayesian labels
    world/online/ground_truth/<b>  Points3D: growing map with ground truth: the map points' classes
    world/online/wrong             Points3D: annotated points whose label is wrong (given map: scene points)
    world/online/camera            Transform3D + Pinhole: the frame's camera (one entity that moves),
                                   child labels (SegmentationImage, the 2D predictions)
    metrics/latency_ms|points_k|changed|diffuser_miou|bayesian_miou   Scalars per frame (points_k: thousands)
    metrics/budget_ms, metrics/latency/{map,graph,evidence,steps}_ms  the frame budget (1 / online.rate) and the latency's parts

Application ids: :data:`APP_BATCH`, :data:`APP_ONLINE` (and :data:`APP_TILED`, :mod:`.tiled`).
"""
from __future__ import annotations

import json
import logging
import sys
import uuid
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from diffuser_lab import seeding
from diffuser_lab.data.scene import IGNORE

from .eyes import eye_kw, follow_eye, overview_eye, scene_up
from .live import live_target
from .online import FINISH_TIMELINE
from .online import TIMELINE as FRAME_TIMELINE
from .steps import Step

log = logging.getLogger("diffuser_lab.recording")

UNLABELED_ID = 65535
"""Class id logged for IGNORE (-1) in run.rrd (Rerun class ids are unsigned 16-bit)."""
TIMELINE = "diffusion_step"
BATCH_SECONDS = 1.0
BATCH_BYTES = 16 * 2**20
"""Rerun's batcher: chunks are cut every second or 16 MiB (default 0.2 s / 2 MiB), so a run's
per-iteration logs land in a few large chunks and the batching work runs less often."""

# viridis at 9 stops; the confidence colour map (no matplotlib import on the hot path)
_VIRIDIS = np.array([(68, 1, 84), (71, 44, 122), (59, 81, 139), (44, 113, 142), (33, 144, 141),
                     (39, 173, 129), (92, 200, 99), (170, 220, 50), (253, 231, 37)], np.float32)
_LUT = np.stack([np.interp(np.linspace(0, 8, 256), np.arange(9), _VIRIDIS[:, c]) for c in range(3)], 1)
CONFIDENCE_LUT = np.round(_LUT).astype(np.uint8)
_CONFIDENCE_RGBA = ((CONFIDENCE_LUT[:, 0].astype(np.uint32) << 24) | (CONFIDENCE_LUT[:, 1].astype(np.uint32) << 16)
                    | (CONFIDENCE_LUT[:, 2].astype(np.uint32) << 8) | np.uint32(255))
"""CONFIDENCE_LUT packed as 0xRRGGBBAA (the --scores layers' colours: Rerun takes these as they are)."""
CONFIDENCE_BINS = 64
FEATURES_ENTITY = "world/features"
"""A features run's PCA-to-RGB view (:mod:`.features`); its query heat map is ``world/query/<query>``."""
_SIMILARITY_RGBA = np.concatenate([_CONFIDENCE_RGBA[np.round(np.linspace(0, 255, 255)).astype(int)],
                                   np.asarray([(128 << 24) | (128 << 16) | (128 << 8) | 255], np.uint32)])
"""The query similarity byte -> viridis 0xRRGGBBAA (0..254), grey for 255 (no feature)."""
"""Confidence is logged as a class id 0..63 (bin of max_c Z / sum_c Z) whose colour and label an
AnnotationContext on the entity gives: 2 bytes a point per iteration instead of 4 for a colour,
and far fewer after compression (a colour map of 64 steps shows no banding on a point cloud)."""


def confidence_context():
    """AnnotationContext of world/diffusion/confidence: bin i -> viridis colour, 'confidence a-b'."""
    import rerun as rr

    lut = CONFIDENCE_LUT[np.round(np.linspace(0, 255, CONFIDENCE_BINS)).astype(int)]
    return rr.AnnotationContext([
        rr.AnnotationInfo(id=i, label=f"confidence {i / CONFIDENCE_BINS:.3f}-{(i + 1) / CONFIDENCE_BINS:.3f}",
                          color=tuple(int(x) for x in lut[i])) for i in range(CONFIDENCE_BINS)])

UNLABELED_RGB = (230, 230, 230)
"""Unlabelled points (class id 65535) where no class has a colour near it (:func:`unlabeled_color`):
a light grey that reads on the viewer's black background (the (70, 70, 70) of before looked like
holes in the cloud, and was cityscapes' ``building``)."""
UNLABELED_MIN_DELTA_E = 15.0
"""The least CIE76 distance of the unlabelled grey to every class colour (:func:`unlabeled_color`)."""
RIGHT_RGB = (95, 95, 95)
"""The errors tab draws every diffused point in this grey (a view override: no extra data)."""
LIVE_PORT = 9876
"""record.live=spawn: the port of the spawned viewer (Rerun's default)."""
LIVE_FLUSH_S = 60.0
"""record.live: how long closing waits for the viewer to take what is still queued."""
FILE_FLUSH_STALL_S = 10.0
"""Closing run.rrd waits for Rerun's file writer as long as the file grows, and gives up (an error
of the record, not of the run) after this many seconds in which it did not: on a full disk the
writer's thread can end without answering the flush, which then waited for ever (seen under
RLIMIT_FSIZE in one run of three, Rerun 0.41; the other two raised "File-writer thread shut down
prematurely")."""
_ABANDONED: list = []
"""Recording streams whose file writer stopped, kept to the process's end: dropping one makes Rerun
disconnect it, which waits on the same dead writer (seen: the recording process hung there)."""


def _lab(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) sRGB uint8 -> (..., 3) CIE L*a*b* (D65)."""
    c = np.asarray(rgb, np.float64) / 255.0
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    m = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
    t = (lin @ m.T) / np.array([0.95047, 1.0, 1.08883])
    f = np.where(t > 0.008856, np.cbrt(t), 7.787 * t + 16.0 / 116.0)
    return np.stack([116.0 * f[..., 1] - 16.0, 500.0 * (f[..., 0] - f[..., 1]), 200.0 * (f[..., 1] - f[..., 2])], -1)


def unlabeled_color(class_colors: np.ndarray) -> tuple[int, int, int]:
    """The unlabelled points' colour for a taxonomy's (C, 3) uint8 ``class_colors``:
    :data:`UNLABELED_RGB` when no class is within :data:`UNLABELED_MIN_DELTA_E` (CIE76) of it, else
    the light grey (levels 150 to 255) farthest from every class (ade20k150's ``windowpane`` is
    (230, 230, 230))."""
    lab = _lab(np.asarray(class_colors, np.float64).reshape(-1, 3))
    d = np.linalg.norm(_lab(np.asarray(UNLABELED_RGB, np.float64)) - lab, axis=1)
    if len(d) == 0 or d.min() >= UNLABELED_MIN_DELTA_E:
        return UNLABELED_RGB
    greys = np.arange(150, 256, dtype=np.float64)
    g = _lab(np.repeat(greys[:, None], 3, 1))
    far = np.linalg.norm(g[:, None, :] - lab[None, :, :], axis=2).min(1)
    v = int(greys[int(np.argmax(far))])
    return (v, v, v)


def wrong_color(class_colors: np.ndarray) -> tuple[tuple[int, int, int], float]:
    """The colour of wrong points: of bright, saturated candidates (a 9-level RGB grid) the one
    farthest (CIE76 delta E, Lab units) from every class colour and from the greys the viewer
    draws (unlabeled, right points in the errors tab). Returns (rgb, its smallest distance)."""
    levels = np.round(np.linspace(0, 255, 9))
    cand = np.stack(np.meshgrid(levels, levels, levels, indexing="ij"), -1).reshape(-1, 3)
    lab = _lab(cand)
    ok = (lab[:, 0] >= 55) & (np.hypot(lab[:, 1], lab[:, 2]) >= 40)  # visible on the dark background, not grey
    cand, lab = cand[ok], lab[ok]
    avoid = np.concatenate([np.asarray(class_colors, np.float64).reshape(-1, 3),
                            [unlabeled_color(class_colors), RIGHT_RGB]])
    d = np.linalg.norm(lab[:, None, :] - _lab(avoid)[None, :, :], axis=2).min(1)
    best = int(np.argmax(d))
    return tuple(int(x) for x in cand[best]), float(d[best])


def score_entity(name: str, taken: Sequence[str] = (), under: str = "world/scores") -> str:
    """<under>/<name> with the name reduced to [A-Za-z0-9_-] (a suffix if already taken)."""
    import re

    base = f"{under}/" + (re.sub(r"[^A-Za-z0-9_-]+", "_", str(name)).strip("_") or "class")
    path, k = base, 2
    while path in taken:
        path, k = f"{base}_{k}", k + 1
    return path


def class_ids(labels: np.ndarray) -> np.ndarray:
    """(...,) int labels with IGNORE -> uint16 Rerun class ids (IGNORE -> UNLABELED_ID)."""
    lab = np.asarray(labels)
    return np.where(lab == IGNORE, UNLABELED_ID, lab).astype(np.uint16)


def depth_mm(depth: np.ndarray) -> np.ndarray:
    """(H, W) float depth in metres -> uint16 millimetres (0 where invalid or beyond 65.5 m): half
    the bytes of float32, the resolution of the sensors' own depth files."""
    d = np.rint(np.nan_to_num(np.asarray(depth, np.float32) * np.float32(1000.0), nan=0.0, posinf=0.0, neginf=0.0))
    d[(d < 0) | (d > 65535)] = 0
    return d.astype(np.uint16)


def annotation_context(names: Sequence[str], colors: np.ndarray):
    """Rerun AnnotationContext: class id -> name and colour, plus UNLABELED_ID for IGNORE."""
    import rerun as rr

    infos = [rr.AnnotationInfo(id=i, label=str(n), color=tuple(int(x) for x in colors[i]))
             for i, n in enumerate(names)]
    infos.append(rr.AnnotationInfo(id=UNLABELED_ID, label="unlabeled", color=unlabeled_color(colors)))
    return rr.AnnotationContext(infos)


def point_radius(points: np.ndarray) -> float:
    """Half the mean nearest-neighbour spacing (on a sample), metres: points that just touch."""
    from scipy.spatial import cKDTree

    if len(points) < 2:
        return 0.01
    sample = points[seeding.rng(0, "records.point_radius").choice(len(points), min(len(points), 2000), replace=False)]
    # an unbalanced tree builds in half the time and answers 2,000 queries as well
    d, _ = cKDTree(points, balanced_tree=False, compact_nodes=False).query(sample, k=2)
    return float(max(0.5 * np.mean(d[:, 1]), 1e-4))


LEGEND = "legend"
"""The legend's entity (every kind of run): an Image (:func:`legend_image`: a swatch and the
name of each class present, ``unlabeled``, ``wrong label`` with ground truth, and the
confidence colour scale) with the same entries as values (``classes``: names, ``colors``:
0xRRGGBBAA), drawn in the layout's ``legend`` 2D view, a strip under the 3D tabs. A picture:
Rerun's 2D labels keep their size in pixels while the view scales the positions, so
labelled points overlapped or fell apart with the view's size; an image scales as a whole."""
LEGEND_ROWS = 5
"""Entries per column of the legend."""
LEGEND_BG = (18, 18, 18)
"""The legend's background: the viewer's."""


def legend_entries(names: Sequence[str], colors: np.ndarray, present: Optional[np.ndarray] = None,
                   wrong_rgb: Optional[tuple] = None) -> tuple[list[str], np.ndarray]:
    """(labels, (K, 3) uint8 colours) of the legend: the classes ``present`` (class ids, e.g. those
    of the ground truth and the labels; None: all), ``unlabeled`` and, given ``wrong_rgb``,
    ``wrong label``."""
    ids = np.arange(len(names)) if present is None else np.unique(np.asarray(present, np.int64))
    ids = ids[(ids >= 0) & (ids < len(names))]
    labels = [str(names[i]) for i in ids] + ["unlabeled"]
    cols = [np.asarray(colors, np.uint8).reshape(-1, 3)[ids], np.asarray([unlabeled_color(colors)], np.uint8)]
    if wrong_rgb is not None:
        labels.append("wrong label")
        cols.append(np.asarray([wrong_rgb], np.uint8))
    return labels, np.concatenate(cols)


def legend_image(labels: Sequence[str], colors: np.ndarray, confidence: bool = True,
                 rows: int = LEGEND_ROWS) -> np.ndarray:
    """(H, W, 3) uint8 picture of the legend: ``labels`` with their (K, 3) uint8 ``colors`` as
    swatches in columns of ``rows``, and with ``confidence`` the viridis scale 0..1 right of them
    (matplotlib's Agg canvas, no pyplot: safe in the recording thread)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    row_px, font = 34, 13  # points at 100 dpi: ~10 px a character
    n_cols = -(-len(labels) // rows)
    col_px = 44 + 10 * max(len(s) for s in labels)
    cbar_px = 320 if confidence else 0
    W, H = n_cols * col_px + cbar_px + 20, rows * row_px + 16
    fig = Figure(figsize=(W / 100, H / 100), dpi=100, facecolor=np.asarray(LEGEND_BG) / 255)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_xlim(0, W)
    ax.set_ylim(H, 0)
    ax.axis("off")
    cols = np.asarray(colors, np.float64).reshape(-1, 3) / 255
    for k, name in enumerate(labels):  # a few dozen entries
        x, y = 12 + (k // rows) * col_px, 8 + (k % rows) * row_px
        ax.add_patch(Rectangle((x, y + 4), 22, 22, facecolor=cols[k], edgecolor=(0.85, 0.85, 0.85), linewidth=0.6))
        ax.text(x + 32, y + 15, name, color=(0.9, 0.9, 0.9), fontsize=font, va="center")
    if confidence:
        x0, w = W - cbar_px + 20, cbar_px - 60
        ax.imshow(CONFIDENCE_LUT[None, np.linspace(0, 255, w).astype(int)], extent=(x0, x0 + w, 66, 42),
                  aspect="auto", interpolation="nearest")
        ax.text(x0, 28, "confidence max_c Z / sum_c Z", color=(0.9, 0.9, 0.9), fontsize=font, va="center")
        for v in (0.0, 0.5, 1.0):
            ax.text(x0 + v * w, 84, f"{v:g}", color=(0.9, 0.9, 0.9), fontsize=font, va="center", ha="center")
    fig.canvas.draw()
    return np.ascontiguousarray(np.asarray(fig.canvas.buffer_rgba())[..., :3])


def log_legend(rec, names: Sequence[str], colors: np.ndarray, present: Optional[np.ndarray] = None,
               wrong_rgb: Optional[tuple] = None, confidence: bool = True) -> None:
    """Static :data:`LEGEND` on the recording stream ``rec``: :func:`legend_image` of
    :func:`legend_entries` and the entries as values (``classes``, ``colors`` 0xRRGGBBAA)."""
    import rerun as rr

    labels, cols = legend_entries(names, colors, present, wrong_rgb)
    c = cols.astype(np.uint32)
    packed = (c[:, 0] << 24) | (c[:, 1] << 16) | (c[:, 2] << 8) | np.uint32(255)
    rec.log(LEGEND, rr.Image(legend_image(labels, cols, confidence)),
            rr.AnyValues(classes=labels, colors=packed), static=True)


def legend_view():
    """The ``legend`` 2D view of every layout."""
    import rerun.blueprint as rrb

    return rrb.Spatial2DView(name="legend", origin=f"/{LEGEND}", contents=[f"/{LEGEND}"])


def y_range(ranges: Optional[dict], contents: Sequence[str], pad: float = 0.12) -> Optional[tuple]:
    """(lo, hi) over the ``ranges`` {entity: (lo, hi)} of the ``contents`` with ``pad`` of their
    span (at least 5% of the largest magnitude, and 0.5 for spans of 1 or more, else 0.02) on
    both sides: the tick labels at the ends stay inside the plot (fitted to the data, Rerun cut
    its end ticks in half); None where none has values (Rerun's own fit)."""
    got = [ranges[c] for c in contents if ranges and c in ranges]
    if not got:
        return None
    lo, hi = min(g[0] for g in got), max(g[1] for g in got)
    p = max(pad * (hi - lo), 0.05 * max(abs(lo), abs(hi)), 0.5 if hi - lo >= 1 else 0.02)
    return (float(lo - p), float(hi + p))


def plot(name: str, contents: Sequence[str], ranges: Optional[dict] = None, legend: bool = False,
         corner: str = "RightBottom", origin: str = "/metrics"):
    """A time series view, its y axis over :func:`y_range` of ``ranges`` (None: Rerun's, fitted to
    the data) and, with ``legend``, its legend in ``corner`` (off the curves: where they end)."""
    import rerun.blueprint as rrb

    yr = y_range(ranges, contents)
    kw = {} if yr is None else {"axis_y": rrb.ScalarAxis(range=yr, zoom_lock=False)}
    return rrb.TimeSeriesView(name=name, origin=origin, contents=list(contents),
                              plot_legend=rrb.PlotLegend(corner=corner, visible=bool(legend)), **kw)


RESULT_CONFIDENCE = "world/result/confidence"
"""``output.scores=true``: each original point's top score, margin and entropy (:meth:`RerunRecorder.log_confidence`)."""


def blueprint(score_layers: Sequence[tuple[str, str]] = (), eye=None, feature_tabs: Sequence[tuple[str, str]] = (),
              ranges: Optional[dict] = None, confidence: bool = False):
    """The default layout: the labelled points in 3D beside the time series; other 3D views
    (confidence, with ``confidence`` the result's (:data:`RESULT_CONFIDENCE`), errors, ground truth,
    input + cameras, depth, evidence, and one per
    ``score_layers`` (class name, entity path), and a features run's ``feature_tabs`` (tab name,
    entity path)) in tabs behind it; ``ranges`` {entity: (lo, hi)}: the plotted scalars' (the
    layout is sent again at the end with them, :func:`y_range`). Every 3D view opens on ``eye``
    (:func:`~.eyes.overview_eye`: from above one side, looking down into the scene), None:
    Rerun's own (from outside the scene's box, which in a room shows the walls' backs).

    Rerun's entity filters have no wildcard inside a path (only a trailing ``/**``), so the
    depth images live under ``world/depth`` and the camera tabs take ``world/cameras/**`` whole:
    frustums and label images, no back-projected depth."""
    import rerun as rr
    import rerun.blueprint as rrb

    def view3d(name: str, contents: list[str], **kw):
        return rrb.Spatial3DView(name=name, origin="/world", contents=contents, **eye_kw(eye), **kw)

    # the errors tab draws the labels cloud in one grey (an override of this view only), so that
    # the wrong points are the only colour in it
    dim = {"/world/diffusion/labels": rr.Points3D.from_fields(colors=RIGHT_RGB).visualizer()}
    scores = [view3d(f"scores: {name}", [f"/{path}"]) for name, path in score_layers]
    feats = [view3d(name, [f"/{path}"]) for name, path in feature_tabs]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(rrb.Tabs(
                view3d("diffusion: labels", ["/world/diffusion/labels"]),
                view3d("confidence", ["/world/diffusion/confidence"]),
                *([view3d("confidence: scores.npy", [f"/{RESULT_CONFIDENCE}"])] if confidence else []),
                *feats,
                view3d("errors", ["/world/diffusion/labels", "/world/diffusion/wrong"], overrides=dim),
                view3d("ground truth", ["/world/scene/ground_truth"]),
                view3d("input + cameras", ["/world/scene/points", "/world/cameras/**"]),
                view3d("depth (back-projected)", ["/world/depth/**"]),
                view3d("evidence (Bayesian)", ["/world/evidence/**", "/world/cameras/**"]),
                *scores,
                active_tab="diffusion: labels",
            ), legend_view(), row_shares=[4, 1]),
            rrb.Vertical(
                plot("mIoU and accuracy so far [%]", ["/metrics/miou", "/metrics/accuracy"], ranges, legend=True),
                plot("mean confidence", ["/metrics/confidence"], ranges),
                plot("labels changed per iteration, log10", ["/metrics/changed_per_iter_log10"], ranges),
                plot("relative residual |Z_t - Z_t-1|, log10", ["/metrics/residual_log10"], ranges),
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(state="collapsed", timeline=TIMELINE, play_state="following"),
        collapse_panels=True,
    )


ONLINE_BLOCK_ROWS = 4096
"""A growing map in run.rrd is logged in blocks of map rows (map order only appends): a frame that
adds points re-logs the positions of the block(s) it filled, not the whole map's (on scene0470,
40 frames, 59k points: 65 MB as one entity). The first :data:`ONLINE_BLOCKS_PER_SIZE` blocks
have this many rows, the next as many twice that, and so on (:func:`online_blocks`). Each layer
(labels, Bayesian, ground truth) re-logs its growing block, so the bytes per map point grow with
the block: on the demo's growing map (64k points, 30 frames) both records together hold 364
bytes per map point with blocks of 16,384 rows, 304 with 8,192, 266 with 4,096 (issue 50's
budget: 300); the larger blocks of a large map keep the blocks few."""
ONLINE_BLOCKS_PER_SIZE = 16
ONLINE_MAX_BLOCKS = 64
"""Blocks whose labels the errors tab draws grey (its overrides name each block; 64 blocks:
983,040 map rows; the blocks after those keep the sixty-fourth's size). The Rerun 0.41 viewer
refuses a blueprint with 128 such overrides ("Data source finished without loading a
recording"); 64 load. (A default colour of the view does not do it: the class ids' colours
win over a view's default, seen in the viewer, 2026-12-07.)"""


def online_blocks(n: int) -> list[tuple[int, int]]:
    """The (lo, hi) map rows of each run.rrd block of a growing map of ``n`` rows (see
    :data:`ONLINE_BLOCK_ROWS`); the same for every n (blocks only fill and get added)."""
    out, lo, b = [], 0, 0
    while lo < n:
        size = ONLINE_BLOCK_ROWS << (min(b, ONLINE_MAX_BLOCKS - 1) // ONLINE_BLOCKS_PER_SIZE)
        out.append((lo, min(n, lo + size)))
        lo += size
        b += 1
    return out


APP_BATCH, APP_ONLINE, APP_TILED = "diffuser_lab_batch", "diffuser_lab_online", "diffuser_lab_tiled"
APP_SINGLE_FRAME = "diffuser_lab_single_frame"
"""run.rrd's application id per kind of run (Rerun turns a dot in one into a hash): the viewer keeps
a layout per application id. What makes a record opened into a running viewer (``rerun run.rrd``
with one on port 9876) show its own layout is the blueprint sent as the *active* one
(``send_blueprint(make_active=True)``): checked in the viewer (Xvfb, 2026-12-04), an online record
streamed into a viewer showing a tiled one got Rerun's automatic layout with its own application
id and a default-only blueprint, and its layout with the active blueprint, with either id."""

FOLLOW_CAMERA = "/world/online/camera"
"""The entity of an online run's moving camera, which the "through the camera" tab's eye tracks."""


def online_blueprint(has_gt: bool, growing: bool, eye=None, budget_ms: Optional[float] = None,
                     ranges: Optional[dict] = None):
    """The layout of an online run: the map's labels (with the moving camera) seen from ``eye``
    (:func:`~.eyes.overview_eye`; None: Rerun's own), the same labels through the moving camera
    (its eye tracks :data:`FOLLOW_CAMERA`: pose and field of view of the frame shown), the
    Bayesian labels, errors and ground truth (with ground truth) from ``eye``, in tabs beside
    the per-frame plots and the camera's label image. The latency plot has a row of its own, its
    y axis up to 3 ``budget_ms`` (a first frame that loads the kernels does not flatten the others)."""
    import rerun as rr
    import rerun.blueprint as rrb

    def view3d(name: str, contents: list[str], view_eye=eye, **kw):
        return rrb.Spatial3DView(name=name, origin="/world", contents=contents, **eye_kw(view_eye), **kw)

    cam = "/world/online/camera/**"
    # through the camera: its frustum but not its label image, which would fill the view at 0.25 m
    follow = view3d("through the camera", ["/world/online/labels/**", FOLLOW_CAMERA],
                    view_eye=follow_eye(FOLLOW_CAMERA))
    tabs = [view3d("online: labels", ["/world/online/labels/**", cam]), follow,
            view3d("bayesian", ["/world/online/bayesian/**", cam])]
    if has_gt:
        grey = rr.Points3D.from_fields(colors=RIGHT_RGB).visualizer()
        dim = {f"/world/online/labels/{b:04d}": grey for b in range(ONLINE_MAX_BLOCKS if growing else 1)}
        tabs.append(view3d("errors", ["/world/online/labels/**", "/world/online/wrong"], overrides=dim))
        tabs.append(view3d("ground truth", ["/world/online/ground_truth/**" if growing else "/world/scene/ground_truth"]))
    # two views a row: a plot needs ~25 px per labelled tick and egui's are decades (10, 20, ...
    # of a 0-70 range), so five plots stacked showed no number on their y axes
    rows = [plot("mIoU so far [%]", ["/metrics/diffuser_miou", "/metrics/bayesian_miou"], ranges,
                 legend=True)] if has_gt else []
    lat = plot("latency against the frame budget [ms]", ["/metrics/latency_ms", "/metrics/budget_ms",
                                                         "/metrics/latency/**"],
               ranges if not budget_ms else {"/metrics/budget_ms": (0.0, 3.0 * budget_ms)}, legend=True,
               corner="RightTop")
    rows += [lat,
             rrb.Horizontal(plot("labels changed", ["/metrics/changed"], ranges),
                            plot("finishing pass: relative residual, log10", ["/metrics/finish_residual_log10"],
                                 ranges)),
             rrb.Horizontal(plot("map points [thousands]", ["/metrics/points_k"], ranges),
                            rrb.Spatial2DView(name="camera: 2D labels", origin="/world/online/camera"))]
    return rrb.Blueprint(
        rrb.Horizontal(rrb.Vertical(rrb.Tabs(*tabs, active_tab="online: labels"), legend_view(), row_shares=[4, 1]),
                       rrb.Vertical(*rows), column_shares=[3, 2]),
        rrb.TimePanel(state="collapsed", timeline=FRAME_TIMELINE, play_state="following"),
        collapse_panels=True,
    )


LATENCY_PARTS = (("map_ms", (188, 189, 34)), ("graph_ms", (23, 190, 207)), ("evidence_ms", (227, 119, 194)),
                 ("steps_ms", (127, 60, 20)))
"""An online frame's parts of its latency (:class:`~diffuser_lab.method.online.FrameStats`), plotted
under ``metrics/latency/`` with these colours."""


class RerunRecorder:
    """Writes run.rrd. Methods take plain arrays so that a run can be re-logged from its MCAP.

    Args:
        live: also stream to a viewer: None (off), "spawn" (start one on :data:`LIVE_PORT`) or a
            gRPC URL such as ``rerun+http://127.0.0.1:9876/proxy`` (see ``record.live``).
        score_classes: (name, class index) of the classes whose scores :meth:`log_scores` logs
            (``world/scores/<name>``, one blueprint tab each).
        confidence: the layout has the result's confidence tab (:meth:`log_confidence`; ``output.scores``).
    """

    file_key = "rrd"

    def __init__(self, path: Path, *, application_id: Optional[str] = None, recording_id: Optional[str] = None,
                 max_image_side: int = 320, max_depth_side: int = 160, live: Optional[str] = None,
                 score_classes: Sequence[tuple[str, int]] = (), online: bool = False, confidence: bool = False):
        import rerun as rr

        self.rr = rr
        self.confidence = bool(confidence)
        self.path = Path(path)
        self.online = bool(online)
        self.max_image_side = int(max_image_side)
        self.max_depth_side = int(max_depth_side)  # 0: no depth images
        self.score_paths: list[str] = []
        for _name, _ in score_classes:
            self.score_paths.append(score_entity(_name, self.score_paths))
        self.score_index = np.asarray([int(c) for _, c in score_classes], np.int64)
        # the layout is sent once the scene is known (its eye frames the scene): a batch run's with
        # log_scene (else at close), an online run's with log_online_start (it depends on ground truth)
        self._layers = [(str(n), p) for (n, _), p in zip(score_classes, self.score_paths)]
        self._eye_up: Optional[np.ndarray] = None  # the up of the batch blueprint sent; None: none sent
        self._poses: list[np.ndarray] = []  # a batch run's cameras (T_cw), for the up of its eye
        self._feature_tabs: list[tuple[str, str]] = []  # a features run's (tab, entity): log_feature_view
        self._query_path = ""
        self._work_points: Optional[np.ndarray] = None
        self._taxonomy: Optional[tuple[list, np.ndarray]] = None  # (names, (C, 3) colours): log_taxonomy
        self._extent: dict[str, list[float]] = {}  # /metrics/<key> -> [min, max] logged: the plots' y ranges
        self._bp_args: Optional[tuple] = None  # the layout's arguments, sent again with the ranges at close
        self._online_bp: Optional[tuple] = None
        self._budget_ms: Optional[float] = None  # an online run: the frame budget (1 / online.rate), ms
        bp = None
        batcher = rr.ChunkBatcherConfig(flush_tick=BATCH_SECONDS, flush_num_bytes=BATCH_BYTES)
        if application_id is None:
            application_id = APP_ONLINE if online else APP_BATCH
        self.rec = rr.RecordingStream(application_id, recording_id=recording_id or str(uuid.uuid4()),
                                      batcher_config=batcher)
        target = live_target(live)
        if target == "bad":
            raise ValueError(f"live={live!r}: expected None, 'off', 'spawn' or a Rerun gRPC URL")
        self.live = self._spawn() if target == "spawn" else target
        grpc = None
        if self.live is not None:
            try:
                grpc = rr.GrpcSink(self.live)
            except Exception as exc:  # noqa: BLE001 - a URL Rerun refuses: the file still gets written
                log.warning("record.live=%s: %s; writing %s only", self.live, exc, self.path.name)
                self.live = None
        if grpc is None:
            self.rec.save(str(self.path), default_blueprint=bp)
        else:  # both sinks get everything logged from here on
            self.rec.set_sinks(rr.FileSink(str(self.path)), grpc, default_blueprint=bp)
        self.radius = 0.01
        self._work_radius = 0.01
        self.wrong_rgb = (255, 0, 255)
        self.unlabeled_rgb = UNLABELED_RGB
        self._closed = False

    def _spawn(self) -> str:
        """Start a viewer (or find the one on LIVE_PORT) and return its gRPC URL."""
        from rerun.sinks import spawn

        exe = Path(sys.executable).with_name("rerun")  # the venv's, when not on PATH
        spawn(port=LIVE_PORT, connect=False, hide_welcome_screen=True, recording=self.rec,
              executable_path=str(exe) if exe.is_file() else None)
        return f"rerun+http://127.0.0.1:{LIVE_PORT}/proxy"

    # -- static -----------------------------------------------------------------------------
    def log_taxonomy(self, names: Sequence[str], colors: np.ndarray) -> None:
        rr = self.rr
        self.rec.log("world", annotation_context(names, colors), rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.wrong_rgb = wrong_color(colors)[0]
        self.unlabeled_rgb = unlabeled_color(colors)
        self._taxonomy = (list(names), np.asarray(colors, np.uint8))
        rr_series = [("miou", "mIoU so far [%]", (31, 119, 180)), ("accuracy", "accuracy [%]", (44, 160, 44)),
                     ("changed_per_iter_log10", "log10 labels changed per iteration", (214, 39, 40)),
                     ("residual_log10", "log10 relative residual", (148, 103, 189)),
                     ("confidence", "mean confidence", (255, 127, 14))]
        for key, name, color in rr_series if not self.online else ():  # an online run's: log_online_start
            self.rec.log(f"metrics/{key}", rr.SeriesLines(names=name, colors=color), static=True)

    def _send_batch_blueprint(self, T_cw: Optional[np.ndarray] = None) -> None:
        """A batch run's blueprint, its eye over the scene's points, up from the cameras ``T_cw``
        (F, 4, 4) where given (else +z, as ``world``'s ViewCoordinates say)."""
        pts = getattr(self, "_scene_points", None)
        eye = overview_eye(pts, T_cw) if pts is not None else None
        self._bp_args = (self._layers, eye, self._feature_tabs)
        self.rec.send_blueprint(blueprint(*self._bp_args, confidence=self.confidence), make_active=True,
                                make_default=True)
        self._eye_up = scene_up(T_cw)

    def _scalar(self, key: str, value: float) -> None:
        """``metrics/<key>`` at the current time, its extent kept for the plots' ranges."""
        v = float(value)
        self.rec.log(f"metrics/{key}", self.rr.Scalars(v))
        e = self._extent.setdefault(f"/metrics/{key}", [v, v])
        e[0], e[1] = min(e[0], v), max(e[1], v)

    def log_scene(self, points: np.ndarray, colors: Optional[np.ndarray], gt: Optional[np.ndarray]) -> None:
        """points (N, 3) world m; colors (N, 3) uint8 or None; gt (N,) int class ids or None."""
        rr = self.rr
        self.radius = point_radius(points)
        self._scene_points = points
        if not self.online:
            self._send_batch_blueprint()
        cols = colors if colors is not None else np.full((1, 3), 160, np.uint8)
        self.rec.log("world/scene/points", rr.Points3D(points, colors=cols, radii=self.radius), static=True)
        if gt is not None:
            self.rec.log("world/scene/ground_truth",
                         rr.Points3D(points, class_ids=class_ids(gt), radii=self.radius), static=True)
        self._gt_present = None if gt is None else np.unique(np.asarray(gt))
        if self.online:  # a batch run's comes with its evidence (the classes of its Bayesian labels too)
            self.log_legend()

    def log_legend(self, labels: Optional[np.ndarray] = None) -> None:
        """The static ``legend`` (:func:`log_legend`): the classes of the ground truth and of
        ``labels`` (class ids; both None: all classes), the wrong colour where there is ground truth."""
        if self._taxonomy is None:
            return
        gt = getattr(self, "_gt_present", None)
        parts = [np.asarray(a).ravel() for a in (gt, labels) if a is not None]
        present = np.unique(np.concatenate(parts)) if parts else None
        log_legend(self.rec, *self._taxonomy, present, self.wrong_rgb if gt is not None else None)

    def _shrink(self, img: np.ndarray, K: np.ndarray, side: int = 0) -> tuple[np.ndarray, np.ndarray]:
        h, w = img.shape[:2]
        s = int(np.ceil(max(h, w) / (side or self.max_image_side)))
        if s <= 1:
            return img, K
        K = K.astype(np.float64).copy()
        K[0, :] /= s
        K[1, :] /= s  # pixel (u, v) of the full image is (u / s, v / s) of the strided one
        return img[::s, ::s], K

    def log_camera(self, index: int, name: str, K: np.ndarray, T_cw: np.ndarray, width: int, height: int,
                   depth: Optional[np.ndarray] = None, labels: Optional[np.ndarray] = None,
                   rgb: Optional[np.ndarray] = None) -> None:
        """One frame: pose (T_cw world -> camera), pinhole, and its images (strided down to
        ``max_image_side``). The depth image goes to ``world/depth/<i>`` with its own copy of the
        pose and pinhole (a few hundred bytes), the label and colour images under the camera."""
        rr = self.rr
        path = f"world/cameras/{index:04d}"
        self._poses.append(np.asarray(T_cw, np.float64))
        T_wc = np.linalg.inv(np.asarray(T_cw, np.float64))
        K_img = np.asarray(K, np.float64)
        res = (int(width), int(height))
        pose = rr.Transform3D(translation=T_wc[:3, 3], mat3x3=T_wc[:3, :3])
        if labels is not None:
            lab, K_img = self._shrink(labels, np.asarray(K, np.float64))
            res = (lab.shape[1], lab.shape[0])
            self.rec.log(f"{path}/labels", rr.SegmentationImage(class_ids(lab)), static=True)
        if rgb is not None:
            im, _ = self._shrink(rgb, np.asarray(K, np.float64))
            self.rec.log(f"{path}/rgb", rr.Image(np.ascontiguousarray(im)), static=True)
        self.rec.log(path, pose, rr.Pinhole(image_from_camera=K_img, resolution=res, image_plane_distance=0.25),
                     static=True)
        if depth is not None and self.max_depth_side:
            # coarser than the labels (depth compresses ~5x worse), with the pinhole of the
            # strided image, which back-projects it
            d, K_d = self._shrink(np.asarray(depth, np.float32), np.asarray(K, np.float64), self.max_depth_side)
            self.rec.log(f"world/depth/{index:04d}", pose,
                         rr.Pinhole(image_from_camera=K_d, resolution=(d.shape[1], d.shape[0]), image_plane_distance=0.25),
                         rr.DepthImage(depth_mm(d), meter=1000.0), static=True)

    def log_evidence(self, work_points: np.ndarray, seen: np.ndarray, bayesian: np.ndarray) -> None:
        """Work cloud (M, 3); seen (M,) bool; bayesian (M,) labels. Also logs the static
        positions of the per-iteration entities."""
        rr = self.rr
        if not self.online and self._poses:
            # the cameras are in (a batch run reads its frames first): where their up is not the
            # +z the eye was set up with (a COLMAP capture's world), the layout again with theirs
            T = np.stack(self._poses)
            if self._eye_up is None or float(scene_up(T) @ self._eye_up) < np.cos(np.radians(10.0)):
                self._send_batch_blueprint(T)
        same = work_points is getattr(self, "_scene_points", None)
        self._work_radius = self.radius if same else point_radius(work_points)
        self._work_points = work_points
        r = self._work_radius
        seen = np.asarray(seen, bool)
        self.rec.log("world/evidence/bayesian",
                     rr.Points3D(work_points[seen], class_ids=class_ids(bayesian[seen]), radii=r), static=True)
        self.log_legend(bayesian[seen])
        self.rec.log("world/evidence/unseen",
                     rr.Points3D(work_points[~seen], colors=self.unlabeled_rgb, radii=r), static=True)
        self.rec.log("world/diffusion/labels", rr.Points3D(work_points, radii=r), static=True)
        self.rec.log("world/diffusion/confidence", confidence_context(), rr.Points3D(work_points, radii=r), static=True)
        for p in self.score_paths:
            self.rec.log(p, rr.Points3D(work_points, radii=r), static=True)

    # -- per iteration -------------------------------------------------------------------------
    def log_metrics(self, iteration: int, residual: float, changed: int, confidence: float,
                    miou: Optional[float] = None, accuracy: Optional[float] = None, per: int = 1) -> None:
        """The scalars of one iteration (``metrics/*``); ``changed``: labels changed over the
        last ``per`` iterations (logged per iteration, log10)."""
        self.rec.set_time(TIMELINE, sequence=int(iteration))
        # log10: after the first iteration (~all labels change, residual 1) both fall by orders of
        # magnitude, which a linear axis shows as a flat line (Rerun 0.41's plots have no log axis)
        if residual > 0 and np.isfinite(residual):
            self._scalar("residual_log10", np.log10(residual))
        if changed > 0:
            self._scalar("changed_per_iter_log10", np.log10(changed / max(int(per), 1)))
        self._scalar("confidence", confidence)
        if miou is not None:
            self._scalar("miou", miou)
            self._scalar("accuracy", accuracy)

    def log_metrics_columns(self, rows: np.ndarray) -> None:
        """The scalars of consecutive iterations at once: (k, 6) rows of iteration, residual,
        labels changed per iteration since the one before, mean confidence, mIoU, accuracy (NaN: none),
        as :meth:`log_metrics` logs them one by one."""
        rr = self.rr
        rows = np.asarray(rows, np.float64).reshape(-1, 6)
        it = rows[:, 0].astype(np.int64)
        with np.errstate(divide="ignore", invalid="ignore"):
            series = {"residual_log10": np.log10(rows[:, 1]), "changed_per_iter_log10": np.log10(rows[:, 2]),
                      "confidence": rows[:, 3], "miou": rows[:, 4], "accuracy": rows[:, 5]}
        for key, v in series.items():  # five series
            ok = np.isfinite(v)
            if not ok.any():
                continue
            rr.send_columns(f"metrics/{key}", indexes=[rr.TimeColumn(TIMELINE, sequence=it[ok])],
                            columns=rr.Scalars.columns(scalars=v[ok]), recording=self.rec)
            e = self._extent.setdefault(f"/metrics/{key}", [float(v[ok].min()), float(v[ok].max())])
            e[0], e[1] = min(e[0], float(v[ok].min())), max(e[1], float(v[ok].max()))

    def log_step(self, step: Step, points: Optional[np.ndarray] = None, metrics: bool = True) -> None:
        """One recorded iteration; ``points`` (N, 3) are the original points (for ``wrong``);
        ``metrics``: also its scalars (False: the run's side sends them every iteration)."""
        rr = self.rr
        rec = self.rec
        rec.set_time(TIMELINE, sequence=step.iteration)
        rec.log("world/diffusion/labels", rr.Points3D.from_fields(class_ids=class_ids(step.labels)))
        q = np.minimum(np.multiply(step.confidence, CONFIDENCE_BINS, dtype=np.float32), CONFIDENCE_BINS - 1)
        rec.log("world/diffusion/confidence", rr.Points3D.from_fields(class_ids=q.astype(np.uint16)))
        if step.wrong is not None and points is not None:
            rec.log("world/diffusion/wrong", rr.Points3D(points[step.wrong], colors=self.wrong_rgb,
                                                         radii=1.2 * self.radius))
        if metrics:  # per iteration, as recorded iterations need not be evenly spaced
            self.log_metrics(step.iteration, step.residual, step.n_changed, step.mean_confidence, step.miou,
                             step.accuracy, per=step.iteration - step.previous)

    # -- a features run (predictions=features) ------------------------------------------------------
    def log_feature_view(self, view) -> None:
        """A features run's projection (:class:`~.features.FeatureView`): the static positions of
        ``world/features`` (PCA to RGB) and ``world/query/<query>`` (the query's cosine, viridis
        over the run's fixed range), their tabs, and the basis itself as static values."""
        rr = self.rr
        pts, r = self._work_points, self._work_radius
        self._query_path = score_entity(view.query, under="world/query")
        if pts is not None:
            self.rec.log(FEATURES_ENTITY, rr.Points3D(pts, radii=r), static=True)
            self.rec.log(self._query_path, rr.Points3D(pts, radii=r), static=True)
        self.rec.log(f"{FEATURES_ENTITY}/pca", rr.AnyValues(
            basis=view.basis.ravel(), mean=view.mean, lo=view.lo, hi=view.hi,
            query_cosine_range=np.asarray([view.sim_lo, view.sim_hi], np.float32)), static=True)
        self._feature_tabs = [("features: PCA to RGB", FEATURES_ENTITY),
                              (f"query: {view.query}", self._query_path)]
        if not self.online:
            self._send_batch_blueprint(np.stack(self._poses) if self._poses else None)

    def log_features(self, iteration: int, rgb: np.ndarray, sim: np.ndarray) -> None:
        """One recorded iteration's (M, 3) uint8 RGB projection and (M,) uint8 query similarity
        (:func:`~.features.project`) as the colours of ``world/features`` and ``world/query/<query>``."""
        if not self._query_path:
            return
        rr = self.rr
        self.rec.set_time(TIMELINE, sequence=int(iteration))
        rgb = np.asarray(rgb, np.uint32)
        packed = (rgb[:, 0] << 24) | (rgb[:, 1] << 16) | (rgb[:, 2] << 8) | np.uint32(255)
        self.rec.log(FEATURES_ENTITY, rr.Points3D.from_fields(colors=packed))
        self.rec.log(self._query_path, rr.Points3D.from_fields(colors=_SIMILARITY_RGBA[np.asarray(sim)]))

    # -- protocol=online ------------------------------------------------------------------------
    def log_online_start(self, has_gt: bool, growing: bool, points: Optional[np.ndarray] = None,
                         spacing: Optional[float] = None, budget_ms: Optional[float] = None) -> None:
        """An online run: its blueprint (:func:`online_blueprint`, the overview eye over ``points``
        (N, 3) world m, the scene's cloud; None or empty: Rerun's eye) and plot styles.
        ``spacing``: a growing map's voxel size, m (its points are drawn with half of it as radius);
        ``budget_ms``: the sensor's time between frames (1 / ``online.rate``), drawn beside each
        frame's latency and its parts (None: no line)."""
        rr = self.rr
        eye = overview_eye(points) if points is not None and len(points) else None
        self._online_bp = (has_gt, growing, eye, budget_ms)
        self.rec.send_blueprint(online_blueprint(*self._online_bp), make_active=True, make_default=True)
        for key, name, color in (("diffuser_miou", "online Diffuser mIoU so far [%]", (31, 119, 180)),
                                 ("bayesian_miou", "online Bayesian mIoU so far [%]", (255, 127, 14)),
                                 ("latency_ms", "latency [ms]", (214, 39, 40)),
                                 ("changed", "labels changed", (148, 103, 189)),
                                 ("points_k", "map points [thousands]", (44, 160, 44)),
                                 ("finish_residual_log10", "finishing pass: log10 relative residual",
                                  (140, 86, 75)),
                                 ("budget_ms", "frame budget (1 / online.rate)", (127, 127, 127)),
                                 *((f"latency/{part}", f"{part[:-3]} [ms]", color) for part, color in LATENCY_PARTS)):
            self.rec.log(f"metrics/{key}", rr.SeriesLines(names=name, colors=color), static=True)
        self._budget_ms = budget_ms
        # a growing map's points are its voxels' centroids: half the voxel touch. (Estimated from
        # the first frame's map, the radius came out 3x that: its points are far sparser than the
        # map's, and the walls were drawn as a shell of overlapping balls.)
        self._online_radius: Optional[float] = 0.5 * float(spacing) if growing and spacing else None
        self._block_rows: dict[int, int] = {}  # block -> map rows its positions were logged with

    def log_online_frame(self, rec, mirror, changed: bool) -> None:
        """One frame taken (:class:`.online.FrameRecord`) on the ``frame`` timeline; ``mirror``
        (:class:`.online.MapMirror`) holds the map after it, ``changed``: it has new points."""
        rr, log = self.rr, self.rec.log
        self.rec.set_time(FRAME_TIMELINE, sequence=rec.index)
        ids, bids = class_ids(rec.labels), class_ids(rec.bayesian)
        pts = mirror.points
        n = len(pts)
        gt = None if mirror.gt is None or len(mirror.gt) != n else class_ids(mirror.gt)
        if changed and self._online_radius is None and n:
            self._online_radius = point_radius(pts)
        r = self._online_radius or 0.01
        for b, (lo, hi) in enumerate(online_blocks(n) if mirror.growing else [(0, n)] if n else []):
            path = f"{b:04d}"
            if self._block_rows.get(b) != hi:  # new rows in this block: its positions again
                self._block_rows[b] = hi
                log(f"world/online/labels/{path}", rr.Points3D(pts[lo:hi], class_ids=ids[lo:hi], radii=r))
                log(f"world/online/bayesian/{path}", rr.Points3D(pts[lo:hi], class_ids=bids[lo:hi], radii=r))
                if gt is not None:
                    log(f"world/online/ground_truth/{path}", rr.Points3D(pts[lo:hi], class_ids=gt[lo:hi], radii=r))
            else:  # the positions logged last still hold
                log(f"world/online/labels/{path}", rr.Points3D.from_fields(class_ids=ids[lo:hi]))
                log(f"world/online/bayesian/{path}", rr.Points3D.from_fields(class_ids=bids[lo:hi]))
        wrong = mirror.wrong(rec.labels)
        if wrong is not None:
            log("world/online/wrong", rr.Points3D(wrong, colors=self.wrong_rgb, radii=1.2 * r))
        T_wc = np.linalg.inv(np.asarray(rec.T_cw, np.float64))
        log("world/online/camera", rr.Transform3D(translation=T_wc[:3, 3], mat3x3=T_wc[:3, :3]),
            rr.Pinhole(image_from_camera=rec.K, resolution=(rec.width, rec.height), image_plane_distance=0.25))
        if rec.image is not None:
            log("world/online/camera/labels", rr.SegmentationImage(class_ids(rec.image)))
        st, m = rec.stats, rec.metrics or {}
        self._scalar("latency_ms", st["latency_ms"])
        if self._budget_ms:
            self._scalar("budget_ms", self._budget_ms)
        for part, _ in LATENCY_PARTS:
            if st.get(part) is not None:
                self._scalar(f"latency/{part}", st[part])
        self._scalar("points_k", rec.n / 1000.0)  # thousands: the axis' numbers fit
        self._scalar("changed", st["changed"])
        for key in ("diffuser_miou", "bayesian_miou"):
            if m.get(key) is not None:
                self._scalar(key, m[key])

    def log_online_labels(self, last_index: int, step: int, labels: np.ndarray, mirror) -> None:
        """The map's (n,) labels after step ``step`` of the finishing pass (``online.finish``), on
        the ``frame`` timeline at ``last_index + step`` (``last_index``: the last frame taken) and
        the ``finish_step`` timeline at ``step``: each block's class ids (its positions stand) and
        the wrong points."""
        rr, log = self.rr, self.rec.log
        self.rec.set_time(FRAME_TIMELINE, sequence=int(last_index) + int(step))
        self.rec.set_time(FINISH_TIMELINE, sequence=int(step))
        ids = class_ids(labels)
        n = len(ids)
        for b, (lo, hi) in enumerate(online_blocks(n) if mirror.growing else [(0, n)] if n else []):
            log(f"world/online/labels/{b:04d}", rr.Points3D.from_fields(class_ids=ids[lo:hi]))
        wrong = mirror.wrong(labels)
        if wrong is not None:
            log("world/online/wrong", rr.Points3D(wrong, colors=self.wrong_rgb,
                                                  radii=1.2 * (self._online_radius or 0.01)))
        self.rec.disable_timeline(FINISH_TIMELINE)

    def log_online_finish_metrics(self, last_index: int, rows: np.ndarray) -> None:
        """The finishing pass's scalars: (k, 6) rows of step, relative residual, labels changed,
        mean confidence, mIoU, accuracy (:func:`~.steps.metrics_rows`), on the ``frame`` timeline
        at ``last_index + step`` and the ``finish_step`` timeline: ``metrics/changed`` and
        ``metrics/diffuser_miou`` go on after the frames', ``metrics/finish_residual_log10`` is the pass's own."""
        rr = self.rr
        rows = np.asarray(rows, np.float64).reshape(-1, 6)
        step = rows[:, 0].astype(np.int64)
        with np.errstate(divide="ignore", invalid="ignore"):
            series = {"changed": rows[:, 2], "diffuser_miou": rows[:, 4], "finish_residual_log10": np.log10(rows[:, 1])}
        for key, v in series.items():
            ok = np.isfinite(v)
            if not ok.any():
                continue
            rr.send_columns(f"metrics/{key}", indexes=[rr.TimeColumn(FRAME_TIMELINE, sequence=int(last_index) + step[ok]),
                                                      rr.TimeColumn(FINISH_TIMELINE, sequence=step[ok])],
                            columns=rr.Scalars.columns(scalars=v[ok]), recording=self.rec)
            e = self._extent.setdefault(f"/metrics/{key}", [float(v[ok].min()), float(v[ok].max())])
            e[0], e[1] = min(e[0], float(v[ok].min())), max(e[1], float(v[ok].max()))

    def log_confidence(self, points: np.ndarray, confidence: np.ndarray) -> None:
        """Static :data:`RESULT_CONFIDENCE`: the (N, 3) original ``points`` coloured by the top score of
        their (N, 3) float32 ``confidence`` (top score, margin, entropy; viridis over 0..1), the three as
        its components ``confidence``, ``margin``, ``entropy``."""
        rr = self.rr
        c = np.asarray(confidence, np.float32)
        q = np.multiply(np.clip(c[:, 0], 0.0, 1.0), 255.0, dtype=np.float32).astype(np.uint8)
        self.rec.log(RESULT_CONFIDENCE, rr.Points3D(points, colors=_CONFIDENCE_RGBA[q], radii=self.radius),
                     rr.AnyValues(confidence=np.ascontiguousarray(c[:, 0]), margin=np.ascontiguousarray(c[:, 1]),
                                  entropy=np.ascontiguousarray(c[:, 2])), static=True)

    def score_values(self, Z: np.ndarray) -> np.ndarray:
        """(M, C) scores -> (M, k) float32 Z_ic / sum_c Z_ic of the score classes, 0 where the row is 0."""
        tot = Z.sum(1, dtype=np.float32)[:, None]
        out = np.zeros((Z.shape[0], len(self.score_index)), np.float32)
        np.divide(Z[:, self.score_index], tot, out=out, where=tot > 0)
        return np.clip(out, 0.0, 1.0, out=out)

    def log_scores(self, step: Step) -> None:
        """The score classes' row-normalised Z of one recorded iteration: colour (viridis) and
        value (component ``score``) per point of ``world/scores/<class>``."""
        if not self.score_paths:
            return
        rr = self.rr
        self.rec.set_time(TIMELINE, sequence=step.iteration)
        vals = self.score_values(step.Z)
        q = np.multiply(vals, 255.0, dtype=np.float32).astype(np.uint8)
        for j, p in enumerate(self.score_paths):
            self.rec.log(p, rr.Points3D.from_fields(colors=_CONFIDENCE_RGBA[q[:, j]]),
                         rr.AnyValues(score=np.ascontiguousarray(vals[:, j])))

    def log_provenance(self, block: dict) -> None:
        """What made the run (``provenance``, ``inputs``, ``outputs``: summary.json's blocks) as the
        recording property :data:`PROVENANCE`, one JSON text per key (:func:`read_provenance`); a
        later call replaces it (Rerun's viewer shows the last with the recording's info)."""
        self.rec.send_property(PROVENANCE, self.rr.AnyValues(
            **{k: json.dumps(v, sort_keys=True, default=str) for k, v in block.items()}))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if not self.online and self._eye_up is None:  # no scene came (a run that failed early): the layout
            self.rec.send_blueprint(blueprint(self._layers, feature_tabs=self._feature_tabs, confidence=self.confidence),
                                    make_active=True, make_default=True)
        elif self._extent:  # the layout again with the plots' y ranges, now known
            bp = (blueprint(*self._bp_args, ranges=self._extent, confidence=self.confidence)
                  if self._bp_args and not self.online
                  else online_blueprint(*self._online_bp, ranges=self._extent) if self._online_bp else None)
            if bp is not None:
                self.rec.send_blueprint(bp, make_active=True, make_default=True)
        if self.live is None:
            self._flush_file()
        else:
            try:
                self.rec.flush(timeout_sec=LIVE_FLUSH_S)
            except Exception as exc:  # noqa: BLE001 - the viewer went away or never came: the file is whole
                log.warning("record.live: the viewer at %s did not get all of the run (%s); %s is complete",
                            self.live, exc, self.path.name)
        self.rec.disconnect()

    def _flush_file(self) -> None:
        """Flush to run.rrd, :data:`FILE_FLUSH_STALL_S` at a time while the file grows (see there)."""
        size = self.path.stat().st_size if self.path.is_file() else -1
        while True:
            try:
                self.rec.flush(timeout_sec=FILE_FLUSH_STALL_S)
                return
            except RuntimeError as exc:
                now = self.path.stat().st_size if self.path.is_file() else -1
                if "timed out" not in str(exc) or now <= size:
                    _ABANDONED.append(self.rec)
                    raise RuntimeError(f"Rerun's file writer stopped ({exc}; the file has "
                                       f"{max(now, 0):,} bytes)") from exc
                size = now


PROVENANCE = "diffuser_lab.provenance"
"""run.rrd's recording property (entity ``/__properties/diffuser_lab.provenance``) of what made the run."""


def read_provenance(path: Path | str) -> Optional[dict]:
    """The :data:`PROVENANCE` property of an .rrd (the last one sent: at close, the inputs and
    outputs; a killed run's: the machine and the config's hash) as {key: decoded JSON}; None
    without one. Reads the file's chunks through Rerun's reader (a truncated file: those before the cut)."""
    from rerun.chunk import RrdReader

    rows: list[dict] = []
    try:
        for ch in RrdReader(str(path)).stream():  # every chunk; only the property's decoded
            if ch.entity_path == "/__properties/" + PROVENANCE:
                rows += ch.to_record_batch().to_pylist()
    except Exception:  # noqa: BLE001 - a cut file: the chunks read before the cut
        if not rows:
            raise
    if not rows:
        return None
    # chunks are not in the order sent: the last sent has the largest row id (time-ordered TUIDs)
    last = max(rows, key=lambda r: bytes(r.get("rerun.controls.RowId") or b""))
    return {k: json.loads(v[0]) for k, v in last.items() if not k.startswith("rerun.") and isinstance(v, list) and v}


__all__ = ["RerunRecorder", "PROVENANCE", "read_provenance", "blueprint", "RESULT_CONFIDENCE", "unlabeled_color", "log_legend", "legend_entries", "LEGEND", "APP_BATCH", "APP_ONLINE", "APP_TILED", "APP_SINGLE_FRAME", "online_blueprint", "class_ids", "wrong_color", "score_entity", "UNLABELED_ID", "TIMELINE",
           "CONFIDENCE_LUT"]
