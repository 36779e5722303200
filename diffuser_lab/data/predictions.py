"""The frames' 2D labels: the registry :data:`SOURCES` of prediction sources, named by
``predictions.source``: ground truth, simulated 2D-network mistakes on it, a network's output
files, or a network run in the loop (:mod:`diffuser_lab.data.networks`).

Predictions are attached lazily, frame by frame (:class:`~diffuser_lab.data.frames.LazyFrames`),
so a long sequence is never held in memory twice; each frame's simulation is seeded by
(predictions.seed, frame index), so it does not depend on the order in which frames are visited.

Adding a prediction source is one function ``attach(frames, cfg, taxonomy, scene_name) -> frames``
(usually ``LazyFrames.mapped(frames, fn)``), one ``conf/predictions/<name>.yaml`` with
``source: <name>`` and one registry line (an entry in :data:`SOURCES`, or :func:`register`).
"""
from __future__ import annotations

import dataclasses
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from diffuser_lab import seeding
from diffuser_lab.config import MistakeCorrelation, PredictionsConfig
from diffuser_lab.registry import Registry

from .embeddings import prototypes, query_dim, simulate_features
from .frames import LazyFrames
from .mapping import load_mapping, native_mapping
from .networks import model_predictions, onnx_predictions
from .images import label_ids_in
from .prediction_files import (find_prediction, load_feature_prediction, load_label_prediction,
                               load_probability_prediction)
from .scene import Frame, Taxonomy
from .simulate import simulate_predictions, surface_regions

__all__ = ["PredictionSource", "SOURCES", "register", "get", "with_predictions", "describe", "reads_rgb"]


@dataclass(frozen=True)
class PredictionSource:
    """One prediction source.

    Attributes:
        name: the ``predictions.source`` value that selects it.
        description: a few words (docs/config.md's choices).
        attach: ``(frames, predictions config, taxonomy, scene name) -> frames`` whose ``labels``
            (or ``probs``) are the predictions; lazily, frame by frame. ``stats`` on the result
            (a dict) is reported in summary.json.
        describe: ``predictions config -> str``: what the labels are, for progress lines.
        label_ids: for ``taxonomy=ids``: ``(predictions config, n) -> [(unique label ids, where found)]``
            from the first ``n`` label images it reads; None = none.
        reads_rgb: ``predictions config -> bool``: whether it reads the frames' colour (a network on
            RGB); when nothing else does, a run's frames are read without it (:func:`reads_rgb`).
    """

    name: str
    description: str
    attach: Callable[[Sequence[Frame], PredictionsConfig, Taxonomy, str], Sequence[Frame]]
    describe: Callable[[PredictionsConfig], str]
    label_ids: Optional[Callable[[PredictionsConfig, int], list[tuple[np.ndarray, str]]]] = None
    reads_rgb: Callable[[PredictionsConfig], bool] = lambda cfg: False


def describe(cfg: PredictionsConfig) -> str:
    """What the frames' 2D labels are, in a few words (progress lines name the frame stage with it)."""
    return get(cfg.source).describe(cfg)


def reads_rgb(cfg: PredictionsConfig) -> bool:
    """Whether the configured predictions read the frames' colour (a network run on RGB)."""
    return get(cfg.source).reads_rgb(cfg)


def with_predictions(frames: Sequence[Frame], cfg: PredictionsConfig, taxonomy: Taxonomy,
                     scene_name: str = "") -> Sequence[Frame]:
    """Frames whose ``labels`` (or ``probs``) are the configured predictions; ``scene_name`` is
    part of a network's cache entries (:mod:`diffuser_lab.data.networks`)."""
    return get(cfg.source).attach(frames, cfg, taxonomy, scene_name)


def gt_predictions(frames: Sequence[Frame], cfg: PredictionsConfig, taxonomy: Taxonomy,
                   scene_name: str = "") -> LazyFrames:
    """The ground-truth label images as the predictions (perfect 2D labels)."""
    def fn(i: int, f: Frame) -> Frame:
        _need_gt(f)
        return dataclasses.replace(f, labels=f.gt_labels, probs=None)

    return LazyFrames.mapped(frames, fn)


def simulated_predictions(frames: Sequence[Frame], cfg: PredictionsConfig, taxonomy: Taxonomy,
                          scene_name: str = "") -> LazyFrames:
    """Simulated 2D-network mistakes on the ground-truth label images (:mod:`diffuser_lab.data.simulate`)."""
    return LazyFrames.mapped(frames, _simulated(cfg, taxonomy))


def _simulated(cfg: PredictionsConfig, taxonomy: Taxonomy) -> Callable[[int, Frame], Frame]:
    """``fn(i, frame)``: the frame with the simulated network's labels (frame ``i`` of the sequence)."""
    correlated = cfg.correlation == MistakeCorrelation.regions

    def fn(i: int, f: Frame) -> Frame:
        _need_gt(f)
        regions = (surface_regions(f.gt_labels, f.depth, f.K, f.T_cw, region_size=cfg.region_size,
                                   view_range_m=cfg.view_range_m, seed=cfg.seed) if correlated else None)
        pred = simulate_predictions(
            f.gt_labels, taxonomy.num_classes, (cfg.seed, i), strength=cfg.strength, jitter_px=cfg.jitter_px,
            jitter_scale_px=cfg.jitter_scale_px, confuse_prob=cfg.confuse_prob,
            confuse_max_frac=cfg.confuse_max_frac, blob_count=cfg.blob_count, blob_radius=cfg.blob_radius,
            blob_roughness=cfg.blob_roughness, class_names=taxonomy.names, regions=regions,
            region_seed=cfg.seed, persistence=cfg.persistence, confuse_region_frac=cfg.confuse_region_frac,
            view_gain=cfg.view_gain, output_stride=cfg.output_stride)
        return dataclasses.replace(f, labels=pred, probs=None)

    return fn


def file_predictions(frames: Sequence[Frame], cfg: PredictionsConfig, taxonomy: Taxonomy,
                     scene_name: str = "") -> LazyFrames:
    """A 2D network's outputs, one file per frame named after it: label images (mapped to the
    taxonomy; unmapped ids become IGNORE and are counted) or class probabilities (soft evidence)."""
    if not cfg.folder:
        raise ValueError("predictions.folder is required for predictions.source=files")
    folder = Path(cfg.folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"predictions.folder={folder}: no such folder")
    mapping = load_mapping(cfg.mapping, taxonomy) if cfg.mapping else native_mapping(taxonomy)
    stats = {"unmapped_pixels": 0, "label_files": 0, "probability_files": 0}
    seen: set[int] = set()
    counting = threading.Lock()  # frames are read on several threads (FrameLoop's read-ahead)

    def fn(i: int, f: Frame) -> Frame:
        path = find_prediction(folder, f.name, cfg.pattern)
        if path.suffix in (".npy", ".npz"):
            probs = load_probability_prediction(path, taxonomy.num_classes, f.shape)
            with counting:
                if i not in seen:
                    stats["probability_files"] += 1
                    seen.add(i)
            return dataclasses.replace(f, labels=None, probs=probs)
        labels, n_unmapped = load_label_prediction(path, mapping, f.shape)
        with counting:
            if i not in seen:  # count each frame once, however often it is read
                stats["label_files"] += 1
                stats["unmapped_pixels"] += int(n_unmapped)
                seen.add(i)
        return dataclasses.replace(f, labels=labels, probs=None)

    return LazyFrames.mapped(frames, fn, stats=stats)


def feature_predictions(frames: Sequence[Frame], cfg: PredictionsConfig, taxonomy: Taxonomy,
                        scene_name: str = "") -> LazyFrames:
    """Per-pixel embeddings (``Frame.features``, (h, w, D) at the network's resolution) instead of
    labels: the simulated embedding network (:mod:`diffuser_lab.data.embeddings`) on the configured
    simulated mistakes (predictions=features starts from predictions=realistic's), a network's
    ``.npy`` / ``.npz`` files in ``predictions.folder`` (``predictions.npz_key``, ``predictions.layout``),
    or a network run on each frame's RGB (``predictions.model`` / ``predictions.onnx``; cached per
    model and frame as float16, :mod:`diffuser_lab.data.networks`)."""
    if cfg.embeddings == "files":
        if not cfg.folder:
            raise ValueError("predictions.folder is required for predictions.embeddings=files")
        folder = Path(cfg.folder)
        if not folder.is_dir():
            raise FileNotFoundError(f"predictions.folder={folder}: no such folder")
        # D: the run's queries' (a query file, an encoder's output on the taxonomy's names), else the
        # first frame's map by the auto rule; every frame must have it (read on any thread, any order)
        dim = query_dim(cfg.queries, cfg.encoder, taxonomy.names)
        if dim is None:
            first = frames.names[0] if getattr(frames, "names", None) else frames[0].name
            dim = load_feature_prediction(find_prediction(folder, first, cfg.pattern), key=cfg.npz_key,
                                          layout=cfg.layout).shape[2]

        def from_file(i: int, f: Frame) -> Frame:
            fmap = load_feature_prediction(find_prediction(folder, f.name, cfg.pattern), key=cfg.npz_key,
                                           layout=cfg.layout, dim=dim)
            return dataclasses.replace(f, labels=None, probs=None, features=fmap)

        return LazyFrames.mapped(frames, from_file)
    if cfg.embeddings == "model":
        return model_predictions(frames, cfg, taxonomy, scene_name, features=True)
    if cfg.embeddings == "onnx":
        return onnx_predictions(frames, cfg, taxonomy, scene_name, features=True)
    protos = prototypes(taxonomy.names, dim=cfg.dim, seed=cfg.embedding_seed)
    labelled = _simulated(cfg, taxonomy)

    def simulated(i: int, f: Frame) -> Frame:
        g = labelled(i, f)
        fmap = simulate_features(g.labels, protos, seeding.rng(cfg.seed, "predictions.features", i), stride=cfg.stride,
                                 boundary_mix=cfg.boundary_mix, rotation_deg=cfg.rotation_deg,
                                 rotation_dims=min(cfg.rotation_dims, cfg.dim), noise=cfg.noise)
        return dataclasses.replace(f, labels=None, probs=None, features=fmap)

    return LazyFrames.mapped(frames, simulated)


def _describe_features(cfg: PredictionsConfig) -> str:
    if cfg.embeddings == "files":
        return f"2D features from {cfg.folder}"
    if cfg.embeddings == "model":
        return f"2D features of {(cfg.model or {}).get('_target_')}"
    if cfg.embeddings == "onnx":
        return f"2D features of {Path(cfg.onnx.path).name} (onnx)"
    return f"simulated {cfg.dim}-D features"


def file_label_ids(cfg: PredictionsConfig, n: int) -> list[tuple[np.ndarray, str]]:
    """``taxonomy=ids``: the first ``n`` label images of ``predictions.folder`` (predictions.pattern's images)."""
    if not cfg.folder:
        return []
    folder = Path(cfg.folder)
    pngs = [p for p in cfg.pattern if p.lower().endswith(".png")]
    files = {f for p in pngs for f in folder.glob(p.replace("{name}", "*")) if f.is_file()}
    return label_ids_in(list(files), n, f"prediction ({folder})", role="predictions")


def _need_gt(f: Frame) -> None:
    if f.gt_labels is None:
        raise ValueError(f"frame {f.name}: predictions need ground-truth label images, which this scene lacks")


SOURCES: Registry = Registry("predictions.source", "prediction source", [
    PredictionSource("simulated", "simulated 2D-network mistakes on ground-truth label images",
                     simulated_predictions, lambda cfg: "simulated 2D predictions"),
    PredictionSource("gt", "ground-truth label images (perfect 2D labels)", gt_predictions,
                     lambda cfg: "ground-truth 2D labels"),
    PredictionSource("files", "a 2D network's label images (mapped) or class probabilities (.npy/.npz)",
                     file_predictions, lambda cfg: f"2D predictions from {cfg.folder}", label_ids=file_label_ids),
    PredictionSource("model", "a Python callable (Hydra _target_) run on each frame's RGB", model_predictions,
                     lambda cfg: f"2D predictions of {(cfg.model or {}).get('_target_')}",
                     reads_rgb=lambda cfg: True),
    PredictionSource("onnx", "an exported ONNX segmentation network run with onnxruntime on the CPU",
                     onnx_predictions, lambda cfg: f"2D predictions of {Path(cfg.onnx.path).name} (onnx)",
                     reads_rgb=lambda cfg: True),
    PredictionSource("features", "per-pixel embeddings (simulated, a network's .npy/.npz maps, a callable or ONNX "
                     "network), queried with words",
                     feature_predictions, _describe_features,
                     reads_rgb=lambda cfg: cfg.embeddings in ("model", "onnx")),
])
"""The prediction sources by name (``predictions.source``)."""


def register(entry: PredictionSource) -> PredictionSource:
    """Add a prediction source (a run started after this may name it)."""
    return SOURCES.register(entry)


def get(name: str) -> PredictionSource:
    """The entry a name names, or one line naming predictions.source and the names."""
    return SOURCES.named(name)
