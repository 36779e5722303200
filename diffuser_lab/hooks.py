"""The narrow hook through which records observe a run. Hooks read; they never change anything.

:func:`diffuser_lab.runs.pipeline.run` calls, in order:
    on_scene(scene)                                  once, after loading
    on_frame(index, frame)                           for every frame, with its predictions attached
        (a features run: on_queries(names, embeddings, basis) once, before its first frame)
    on_evidence(points, grid, evidence, bayesian)    once, on the cloud the diffusion runs on
    wants(iteration) -> bool, observe(iteration, Z, stats)   during the diffusion
        (a features run: observe_features(iteration, F) first, then observe with class scores)
    on_result(result)                                once, at the end (also gets the final Z)
:func:`diffuser_lab.runs.online.online` (protocol=online) calls on_scene, then per frame taken
on_frame(index, frame) and on_online_frame(frame, update), then on_result(online result).
Arrays passed in are read-only views or must be treated as such.
"""
from __future__ import annotations

from typing import Any, Optional

import numpy as np


class RunHooks:
    """No-op base: subclass and override what you need."""

    reads_rgb = True
    """Whether :meth:`on_frame` reads ``frame.rgb`` (False: a run that needs no colour otherwise reads
    its frames without it, :meth:`~diffuser_lab.data.frames.LazyFrames.without`)."""

    def on_scene(self, scene: Any) -> None:
        """scene: :class:`~diffuser_lab.data.scene.Scene` (original points, gt labels, taxonomy)."""

    def on_frame(self, index: int, frame: Any) -> None:
        """frame: :class:`~diffuser_lab.data.scene.Frame` with ``labels``/``probs`` set (predictions)."""

    def on_queries(self, names: Any, embeddings: np.ndarray, basis: Optional[np.ndarray] = None) -> None:
        """A features run (predictions=features) only, once, before the first ``on_frame``: the
        queries' names (Q,) and (Q, D) float32 unit embeddings (read-only). With a reduced basis
        (``predictions.basis=auto``: ``basis`` (D, k) float32 orthonormal columns) every feature
        the hooks see, the embeddings included, is (.., k) coordinates in it (x @ basis.T: in R^D)."""

    def on_evidence(self, points: np.ndarray, grid: Optional[Any], evidence: Any, bayesian: np.ndarray) -> None:
        """points: (M, 3) work cloud (world m); grid: VoxelGrid mapping original -> work points or
        None; evidence: Evidence on the work points; bayesian: (M,) int16 baseline labels."""

    def wants(self, iteration: int) -> bool:
        """Whether :meth:`observe` should be called after this iteration (1-based)."""
        return False

    def observe(self, iteration: int, Z: np.ndarray, stats: dict) -> None:
        """Z: (M, C) float32 read-only scores after ``iteration``, valid during this call only (the
        solver reuses the memory for the next observed iteration); stats: ``residual``."""

    def observe_features(self, iteration: int, F: np.ndarray) -> None:
        """A features run (predictions=features) only, before :meth:`observe` of the same iteration:
        F (M, D) float32 (a reduced basis: (M, k) coordinates, :meth:`on_queries`) read-only
        per-point feature sums after ``iteration`` (valid during this call
        only); :meth:`observe` then gets the queries' class scores (M, C) of them
        (:meth:`~diffuser_lab.runs.pipeline.FeatureLift.scores`), and ``on_result``'s
        ``result.diffusion.Z`` is those of the final features (``result.lifted.method``)."""

    def on_online_frame(self, frame: Any, update: Any) -> None:
        """protocol=online, after each frame's update: ``update`` is a
        :class:`~diffuser_lab.runs.online.OnlineUpdate` (the map's points, labels, Bayesian labels,
        per-frame figures, metrics so far; ``update.scores()`` computes Z on demand)."""

    def on_result(self, result: Any) -> None:
        """result: :class:`~diffuser_lab.runs.pipeline.RunResult` (``result.diffusion.Z`` is the final Z)."""

    def close(self) -> None:
        """Flush and close files (called even when the run fails)."""
