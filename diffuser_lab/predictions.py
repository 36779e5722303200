"""The frames' 2D labels: ground truth, or simulated 2D-network mistakes on it.

Predictions are attached lazily, frame by frame, so a long sequence is never held in memory
twice; each frame's simulation is seeded by (predictions.seed, frame index), so it does not
depend on the order in which frames are visited.
"""
from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import numpy as np

from .config import PredictionSource, PredictionsConfig
from .scene import Frame, Taxonomy


class MappedFrames(Sequence[Frame]):
    """A read-only sequence whose item i is ``fn(i, frames[i])``, computed on access."""

    def __init__(self, frames: Sequence[Frame], fn: Callable[[int, Frame], Frame]):
        self._frames, self._fn = frames, fn

    def __len__(self) -> int:
        return len(self._frames)

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        if i < 0:
            i += len(self)
        return self._fn(i, self._frames[i])


def with_predictions(frames: Sequence[Frame], cfg: PredictionsConfig, taxonomy: Taxonomy) -> Sequence[Frame]:
    """Frames whose ``labels`` are the configured predictions."""
    if cfg.source == PredictionSource.gt:
        def fn(i: int, f: Frame) -> Frame:
            _need_gt(f)
            return dataclasses.replace(f, labels=f.gt_labels, probs=None)
    elif cfg.source == PredictionSource.simulated:
        from .simulate import simulate_predictions

        def fn(i: int, f: Frame) -> Frame:
            _need_gt(f)
            rng = np.random.default_rng([cfg.seed, i])
            pred = simulate_predictions(
                f.gt_labels, taxonomy.num_classes, rng, strength=cfg.strength, jitter_px=cfg.jitter_px,
                jitter_scale_px=cfg.jitter_scale_px, confuse_prob=cfg.confuse_prob,
                confuse_max_frac=cfg.confuse_max_frac, blob_count=cfg.blob_count, blob_radius=cfg.blob_radius,
                blob_roughness=cfg.blob_roughness, class_names=taxonomy.names)
            return dataclasses.replace(f, labels=pred, probs=None)
    else:  # pragma: no cover - the config enum forbids it
        raise ValueError(f"predictions.source={cfg.source}: unknown")
    return MappedFrames(frames, fn)


def _need_gt(f: Frame) -> None:
    if f.gt_labels is None:
        raise ValueError(f"frame {f.name}: predictions need ground-truth label images, which this scene lacks")
