"""run.rrd: the diffusion as a Rerun recording (rerun-sdk >= 0.41, one explicit stream per run).

Entity tree (``world`` is z-up, metres; class colours come from the AnnotationContext on ``world``)::

    world                          AnnotationContext (taxonomy names + colours; id 65535 = unlabeled)
    world/scene/points             Points3D, static: the input cloud (input colours, else grey)
    world/scene/ground_truth       Points3D, static: ground-truth class ids (when known)
    world/cameras/<i>              Transform3D + Pinhole, static; children labels (SegmentationImage,
                                   the 2D predictions), rgb (Image, if any)
    world/depth/<i>                the same camera, Pinhole of the coarser depth image; child depth
                                   (DepthImage, mm, at most record.max_depth_side pixels)
    world/evidence/bayesian        Points3D, static: work points that received pixel mass, Bayesian labels
    world/evidence/unseen          Points3D, static: work points no pixel reached
    world/diffusion/labels         Points3D: positions static, class ids per recorded iteration
    world/diffusion/confidence     Points3D: positions static, class id = max_c Z / sum_c Z in 1/64 steps
                                   per iteration (its own AnnotationContext: viridis colours, labels)
    world/diffusion/wrong          Points3D per iteration: annotated points whose label is wrong
    metrics/residual|changed|miou|accuracy|confidence   Scalars per iteration

Every per-iteration entity is on the ``diffusion_step`` sequence timeline.
"""
from __future__ import annotations

import uuid
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from diffuser_lab.data.scene import IGNORE

from .steps import Step

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
CONFIDENCE_BINS = 64
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
    infos.append(rr.AnnotationInfo(id=UNLABELED_ID, label="unlabeled", color=(70, 70, 70)))
    return rr.AnnotationContext(infos)


def point_radius(points: np.ndarray) -> float:
    """Half the mean nearest-neighbour spacing (on a sample), metres: points that just touch."""
    from scipy.spatial import cKDTree

    if len(points) < 2:
        return 0.01
    sample = points[np.random.default_rng(0).choice(len(points), min(len(points), 2000), replace=False)]
    # an unbalanced tree builds in half the time and answers 2,000 queries as well
    d, _ = cKDTree(points, balanced_tree=False, compact_nodes=False).query(sample, k=2)
    return float(max(0.5 * np.mean(d[:, 1]), 1e-4))


def blueprint():
    """The default layout: the labelled points in 3D beside the time series; other 3D views
    (confidence, errors, ground truth, input + cameras, evidence) in tabs behind it."""
    import rerun.blueprint as rrb

    def view3d(name: str, contents: list[str]):
        return rrb.Spatial3DView(name=name, origin="/world", contents=contents)

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Tabs(
                view3d("diffusion: labels", ["/world/diffusion/labels"]),
                view3d("confidence", ["/world/diffusion/confidence"]),
                view3d("errors (red)", ["/world/diffusion/labels", "/world/diffusion/wrong"]),
                view3d("ground truth", ["/world/scene/ground_truth"]),
                view3d("input + cameras", ["/world/scene/points", "/world/cameras/**"]),
                view3d("evidence (Bayesian)", ["/world/evidence/**", "/world/cameras/*"]),
                active_tab="diffusion: labels",
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(name="mIoU so far [%]", origin="/metrics", contents=["/metrics/miou"]),
                rrb.TimeSeriesView(name="labels changed", origin="/metrics", contents=["/metrics/changed"]),
                rrb.TimeSeriesView(name="relative residual |Z_t - Z_t-1|", origin="/metrics",
                                   contents=["/metrics/residual"]),
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(state="expanded"),
        collapse_panels=True,
    )


class RerunRecorder:
    """Writes run.rrd. Methods take plain arrays so that a run can be re-logged from its MCAP."""

    file_key = "rrd"

    def __init__(self, path: Path, *, application_id: str = "diffuser_lab", recording_id: Optional[str] = None,
                 max_image_side: int = 320, max_depth_side: int = 160):
        import rerun as rr

        self.rr = rr
        self.path = Path(path)
        self.max_image_side = int(max_image_side)
        self.max_depth_side = int(max_depth_side)  # 0: no depth images
        batcher = rr.ChunkBatcherConfig(flush_tick=BATCH_SECONDS, flush_num_bytes=BATCH_BYTES)
        self.rec = rr.RecordingStream(application_id, recording_id=recording_id or str(uuid.uuid4()),
                                      batcher_config=batcher)
        self.rec.save(str(self.path), default_blueprint=blueprint())
        self.radius = 0.01
        self._work_radius = 0.01
        self._closed = False

    # -- static -----------------------------------------------------------------------------
    def log_taxonomy(self, names: Sequence[str], colors: np.ndarray) -> None:
        rr = self.rr
        self.rec.log("world", annotation_context(names, colors), rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rr_series = [("miou", "mIoU so far [%]", (31, 119, 180)), ("accuracy", "accuracy [%]", (44, 160, 44)),
                     ("changed", "labels changed", (214, 39, 40)), ("residual", "relative residual", (148, 103, 189)),
                     ("confidence", "mean confidence", (255, 127, 14))]
        for key, name, color in rr_series:
            self.rec.log(f"metrics/{key}", rr.SeriesLines(names=name, colors=color), static=True)

    def log_scene(self, points: np.ndarray, colors: Optional[np.ndarray], gt: Optional[np.ndarray]) -> None:
        """points (N, 3) world m; colors (N, 3) uint8 or None; gt (N,) int class ids or None."""
        rr = self.rr
        self.radius = point_radius(points)
        self._scene_points = points
        cols = colors if colors is not None else np.full((1, 3), 160, np.uint8)
        self.rec.log("world/scene/points", rr.Points3D(points, colors=cols, radii=self.radius), static=True)
        if gt is not None:
            self.rec.log("world/scene/ground_truth",
                         rr.Points3D(points, class_ids=class_ids(gt), radii=self.radius), static=True)

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
        ``max_image_side``)."""
        rr = self.rr
        path = f"world/cameras/{index:04d}"
        T_wc = np.linalg.inv(np.asarray(T_cw, np.float64))
        K_img = np.asarray(K, np.float64)
        res = (int(width), int(height))
        if labels is not None:
            lab, K_img = self._shrink(labels, np.asarray(K, np.float64))
            res = (lab.shape[1], lab.shape[0])
            self.rec.log(f"{path}/labels", rr.SegmentationImage(class_ids(lab)), static=True)
        if rgb is not None:
            im, _ = self._shrink(rgb, np.asarray(K, np.float64))
            self.rec.log(f"{path}/rgb", rr.Image(np.ascontiguousarray(im)), static=True)
        pose = rr.Transform3D(translation=T_wc[:3, 3], mat3x3=T_wc[:3, :3])
        self.rec.log(path, pose, rr.Pinhole(image_from_camera=K_img, resolution=res, image_plane_distance=0.25),
                     static=True)
        if depth is not None and self.max_depth_side:
            # coarser than the labels (depth compresses ~5x worse), so under a camera of its own:
            # world/depth/<i> has the pinhole of the strided image, which back-projects it
            d, K_d = self._shrink(np.asarray(depth, np.float32), np.asarray(K, np.float64), self.max_depth_side)
            dpath = f"world/depth/{index:04d}"
            self.rec.log(dpath, pose, rr.Pinhole(image_from_camera=K_d, resolution=(d.shape[1], d.shape[0]),
                                                 image_plane_distance=0.25), static=True)
            self.rec.log(f"{dpath}/depth", rr.DepthImage(depth_mm(d), meter=1000.0), static=True)

    def log_evidence(self, work_points: np.ndarray, seen: np.ndarray, bayesian: np.ndarray) -> None:
        """Work cloud (M, 3); seen (M,) bool; bayesian (M,) labels. Also logs the static
        positions of the per-iteration entities."""
        rr = self.rr
        same = work_points is getattr(self, "_scene_points", None)
        self._work_radius = self.radius if same else point_radius(work_points)
        r = self._work_radius
        seen = np.asarray(seen, bool)
        self.rec.log("world/evidence/bayesian",
                     rr.Points3D(work_points[seen], class_ids=class_ids(bayesian[seen]), radii=r), static=True)
        self.rec.log("world/evidence/unseen",
                     rr.Points3D(work_points[~seen], colors=(90, 90, 90), radii=r), static=True)
        self.rec.log("world/diffusion/labels", rr.Points3D(work_points, radii=r), static=True)
        self.rec.log("world/diffusion/confidence", confidence_context(), rr.Points3D(work_points, radii=r), static=True)

    # -- per iteration -------------------------------------------------------------------------
    def log_step(self, step: Step, points: Optional[np.ndarray] = None) -> None:
        """One recorded iteration; ``points`` (N, 3) are the original points (for ``wrong``)."""
        rr = self.rr
        rec = self.rec
        rec.set_time(TIMELINE, sequence=step.iteration)
        rec.log("world/diffusion/labels", rr.Points3D.from_fields(class_ids=class_ids(step.labels)))
        q = np.minimum(np.multiply(step.confidence, CONFIDENCE_BINS, dtype=np.float32), CONFIDENCE_BINS - 1)
        rec.log("world/diffusion/confidence", rr.Points3D.from_fields(class_ids=q.astype(np.uint16)))
        if step.wrong is not None and points is not None:
            rec.log("world/diffusion/wrong", rr.Points3D(points[step.wrong], colors=(230, 30, 30),
                                                         radii=1.2 * self.radius))
        rec.log("metrics/residual", rr.Scalars(step.residual))
        rec.log("metrics/changed", rr.Scalars(float(step.n_changed)))
        rec.log("metrics/confidence", rr.Scalars(step.mean_confidence))
        if step.miou is not None:
            rec.log("metrics/miou", rr.Scalars(step.miou))
            rec.log("metrics/accuracy", rr.Scalars(step.accuracy))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.rec.flush()
        self.rec.disconnect()


__all__ = ["RerunRecorder", "blueprint", "class_ids", "UNLABELED_ID", "TIMELINE", "CONFIDENCE_LUT"]
