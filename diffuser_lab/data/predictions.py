"""The frames' 2D labels: ground truth, simulated 2D-network mistakes on it, a network's output
files, or a network run in the loop (:mod:`diffuser_lab.data.networks`).

Predictions are attached lazily, frame by frame, so a long sequence is never held in memory
twice; each frame's simulation is seeded by (predictions.seed, frame index), so it does not
depend on the order in which frames are visited.
"""
from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from diffuser_lab.config import MistakeCorrelation, PredictionsConfig, PredictionSource

from .frames import LazyFrames
from .networks import network_predictions
from .scene import Frame, Taxonomy


def describe(cfg: PredictionsConfig) -> str:
    """What the frames' 2D labels are, in a few words (progress lines name the frame stage with it)."""
    if cfg.source == PredictionSource.gt:
        return "ground-truth 2D labels"
    if cfg.source == PredictionSource.simulated:
        return "simulated 2D predictions"
    if cfg.source == PredictionSource.model:
        return f"2D predictions of {(cfg.model or {}).get('_target_')}"
    if cfg.source == PredictionSource.onnx:
        from pathlib import Path

        return f"2D predictions of {Path(cfg.onnx.path).name} (onnx)"
    return f"2D predictions from {cfg.folder}"


def with_predictions(frames: Sequence[Frame], cfg: PredictionsConfig, taxonomy: Taxonomy,
                     scene_name: str = "") -> Sequence[Frame]:
    """Frames whose ``labels`` (or ``probs``) are the configured predictions; ``scene_name`` is
    part of a network's cache entries (:mod:`diffuser_lab.data.networks`)."""
    if cfg.source == PredictionSource.gt:
        def fn(i: int, f: Frame) -> Frame:
            _need_gt(f)
            return dataclasses.replace(f, labels=f.gt_labels, probs=None)
    elif cfg.source == PredictionSource.simulated:
        from .simulate import simulate_predictions, surface_regions

        correlated = cfg.correlation == MistakeCorrelation.regions

        def fn(i: int, f: Frame) -> Frame:
            _need_gt(f)
            rng = np.random.default_rng([cfg.seed, i])
            regions = (surface_regions(f.gt_labels, f.depth, f.K, f.T_cw, region_size=cfg.region_size,
                                       view_range_m=cfg.view_range_m, seed=cfg.seed) if correlated else None)
            pred = simulate_predictions(
                f.gt_labels, taxonomy.num_classes, rng, strength=cfg.strength, jitter_px=cfg.jitter_px,
                jitter_scale_px=cfg.jitter_scale_px, confuse_prob=cfg.confuse_prob,
                confuse_max_frac=cfg.confuse_max_frac, blob_count=cfg.blob_count, blob_radius=cfg.blob_radius,
                blob_roughness=cfg.blob_roughness, class_names=taxonomy.names, regions=regions,
                region_seed=cfg.seed, persistence=cfg.persistence, confuse_region_frac=cfg.confuse_region_frac,
                view_gain=cfg.view_gain, output_stride=cfg.output_stride)
            return dataclasses.replace(f, labels=pred, probs=None)
    elif cfg.source == PredictionSource.files:
        return _file_predictions(frames, cfg, taxonomy)
    elif cfg.source in (PredictionSource.model, PredictionSource.onnx):
        return network_predictions(frames, cfg, taxonomy, scene_name)
    else:  # pragma: no cover - the config enum forbids it
        raise ValueError(f"predictions.source={cfg.source}: unknown")
    return LazyFrames.mapped(frames, fn)


def _file_predictions(frames: Sequence[Frame], cfg: PredictionsConfig, taxonomy: Taxonomy) -> LazyFrames:
    """A 2D network's outputs, one file per frame named after it: label images (mapped to the
    taxonomy; unmapped ids become IGNORE and are counted) or class probabilities (soft evidence)."""
    from pathlib import Path

    from .mapping import load_mapping, native_mapping
    from .prediction_files import find_prediction, load_label_prediction, load_probability_prediction

    if not cfg.folder:
        raise ValueError("predictions.folder is required for predictions.source=files")
    folder = Path(cfg.folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"predictions.folder={folder}: no such folder")
    mapping = load_mapping(cfg.mapping, taxonomy) if cfg.mapping else native_mapping(taxonomy)
    stats = {"unmapped_pixels": 0, "label_files": 0, "probability_files": 0}
    seen: set[int] = set()

    def fn(i: int, f: Frame) -> Frame:
        path = find_prediction(folder, f.name, cfg.pattern)
        if path.suffix in (".npy", ".npz"):
            probs = load_probability_prediction(path, taxonomy.num_classes, f.shape)
            if i not in seen:
                stats["probability_files"] += 1
                seen.add(i)
            return dataclasses.replace(f, labels=None, probs=probs)
        labels, n_unmapped = load_label_prediction(path, mapping, f.shape)
        if i not in seen:  # count each frame once, however often it is read
            stats["label_files"] += 1
            stats["unmapped_pixels"] += int(n_unmapped)
            seen.add(i)
        return dataclasses.replace(f, labels=labels, probs=None)

    return LazyFrames.mapped(frames, fn, stats=stats)


def _need_gt(f: Frame) -> None:
    if f.gt_labels is None:
        raise ValueError(f"frame {f.name}: predictions need ground-truth label images, which this scene lacks")
