"""The fusion methods, one registry entry each: what it needs and how it labels.

A method turns the frames' pixel evidence into point labels. Each entry says in code

- whether it diffuses over the kNN graph (Eqs. 3-4, 10-16) or labels from the evidence alone,
- which part of the graph and evidence it fixes (LDLS: no normal term, K = 10, a 5x5 pixel window),
- which evidence it reads (the frames' evidence as configured, the Bayesian baseline's, one view's,
  or a streaming lifting rule's per-point result: :mod:`diffuser_lab.method.lifters`),
- the rows it has in the single-frame protocol (1 view, W views; paper Table II; the lifting rules
  of 2024-2026 add theirs when they are the run's method),

and :meth:`FusionMethod.label` does the labelling. ``runs/pipeline.py`` and
``runs/single_frame.py`` both ask :data:`METHODS`; the resolve step (:mod:`diffuser_lab.runs.resolve`)
accepts exactly its names and applies what the chosen method fixes. Adding a method is one entry
here plus ``conf/method/<name>.yaml``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from diffuser_lab.registry import Registry

from .diffusion import labels_from_scores
from .solvers import solve

EVIDENCE = "evidence"  # the frames' evidence with the method's pixel window (Eqs. 11-13)
BASELINE = "baseline"  # the Bayesian baseline's: single pixel, likelihoods or votes (method.bayesian_mode)
ONE_VIEW = "one_view"  # the evidence of one frame (method.view)
RULE = "rule"  # a lifting rule's per-point values, kept as the frames stream in (method/lifters.py)


@dataclass(frozen=True)
class FusionMethod:
    """One fusion method. ``normals`` / ``k`` / ``pixel_radius``: None = as ``graph.use_normals`` /
    ``graph.k`` / ``evidence.pixel_radius`` say; a value = fixed by the method's definition."""

    name: str
    description: str
    graph: bool
    evidence: str = EVIDENCE
    normals: Optional[bool] = None
    k: Optional[int] = None  # neighbours of the kNN graph (Eq. 3)
    pixel_radius: Optional[int] = None
    multi_view_row: bool = True  # a W-view row in the single-frame protocol besides the 1-view one
    rule: Optional[str] = None  # evidence=RULE: the rule's name in lifters.RULES
    table_ii: bool = True  # a row of every single-frame run (else only when it is the run's method.name)

    def apply(self, cfg) -> None:
        """Set what the method fixes in ``cfg`` (a :class:`~diffuser_lab.config.Config`), so the
        config a run records is the one that ran; the resolve step calls it
        (:func:`diffuser_lab.runs.resolve.with_method`)."""
        if self.normals is not None:
            cfg.graph.use_normals = self.normals
        if self.k is not None:
            cfg.graph.k = self.k
        if self.pixel_radius is not None:
            cfg.evidence.pixel_radius = self.pixel_radius

    def label(self, mass: np.ndarray, *, system=None, solver=None, observer=None):
        """(M,) int16 labels (IGNORE where no evidence reaches a point) and the DiffusionResult
        (None for methods without a graph). ``mass``: (M, C) the evidence the method reads;
        ``system``: the normalised graph system of Eqs. 14-15 for graph methods."""
        if not self.graph:
            return labels_from_scores(mass), None
        diff = solve(system, solver, observer=observer)
        return labels_from_scores(diff.Z), diff

    def single_frame_rows(self, window: int) -> list[int]:
        """Views of this method's rows in the single-frame protocol."""
        return [1, window] if self.multi_view_row and window > 1 else [1]


METHODS: Registry = Registry("method.name", "fusion method", [  # the order of the paper's Table II
    FusionMethod("direct", "labels projected from a single view (method.view)", graph=False, evidence=ONE_VIEW,
                 multi_view_row=False),
    # LDLS as its authors' implementation runs it (github.com/brian-h-wang/LDLS,
    # lidar_segmentation/segmentation.py: LidarSegmentation(num_neighbors=10,
    # pixel_to_lidar_kernel_size=5), 200 iterations): a distance-only kNN graph of 10 neighbours and
    # every point linked to the 5x5 pixels around its projection; the distance kernel (sigma_d),
    # lambda and the iterations are the run's, as for Diffuser
    FusionMethod("ldls", "LDLS (Wang et al. 2019): distance-only kNN graph of K = 10, 5x5 pixel window", graph=True,
                 normals=False, k=10, pixel_radius=2, multi_view_row=False),
    FusionMethod("bayesian", "per-point sum of pixel likelihoods (or votes), argmax", graph=False,
                 evidence=BASELINE),
    FusionMethod("diffuser", "the paper's method: the evidence diffused over the kNN graph", graph=True),
    # the training-free lifting rules of 2024-2026 on the same evidence (method/lifters.py, docs/lifters.md)
    FusionMethod("weighted", "Occam's LGS / Dr. Splat: the average weighted by each view's share of the point "
                 "(incidence, distance, depth margin)", graph=False, evidence=RULE, rule="weighted", table_ii=False),
    FusionMethod("median", "VALA: streaming weighted geometric median (Weiszfeld steps; features in cosine space)",
                 graph=False, evidence=RULE, rule="median", table_ii=False),
    FusionMethod("topk", "The Bare Necessities: the average of each point's method.top_k most confident views",
                 graph=False, evidence=RULE, rule="topk", table_ii=False),
    FusionMethod("vote", "LabelMaker: hard votes of the depth-checked views (features: of their query labels)",
                 graph=False, evidence=RULE, rule="vote", table_ii=False),
], sort_names=True)
"""The fusion methods by name (``method.name``)."""


def get(name: str) -> FusionMethod:
    """The entry a name names, or one line naming method.name and the names (sorted)."""
    return METHODS.named(name)
