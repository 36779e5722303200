"""The fusion methods, one registry entry each: what it is, what it reads and how it labels.

A method turns the frames' pixel evidence into point labels. Each entry says in code

- which evidence it reads (:meth:`FusionMethod.reads`, :meth:`FusionMethod.window_evidence`): the
  frames' evidence as configured, the Bayesian baseline's, one view's, or a streaming lifting rule's
  per-point result (its :attr:`~FusionMethod.rule`, a class of :mod:`diffuser_lab.method.lifters`),
- whether it diffuses over the kNN graph (Eqs. 3-4, 10-16) or labels from its evidence alone, and
  how its scores become labels (:meth:`FusionMethod.label`, in the run's label space:
  :mod:`diffuser_lab.method.space`),
- which part of the graph and evidence it fixes (LDLS: no normal term, K = 10, a 5x5 pixel window),
- the rows it has in the single-frame protocol (1 view, W views; paper Table II; the lifting rules
  of 2024-2026 add theirs when they are the run's method), the protocols it runs in, how far a
  tile's halo must reach for it.

The runs (``runs/pipeline.py``, ``runs/single_frame.py``, ``runs/tiled.py``) ask the entry and never
which kind it is; the resolve step (:mod:`diffuser_lab.runs.resolve`) accepts exactly its names and
applies what the chosen method fixes. Adding a method is one entry here plus
``conf/method/<name>.yaml``; a lifting rule is a :class:`~diffuser_lab.method.lifters.Rule` subclass
and an entry that names it (``rule=``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np

from diffuser_lab.registry import Registry

from . import affinity, lifters
from .diffusion import DiffusionResult
from .evidence import Evidence, RunEvidence, accumulate
from .exact import tikhonov_scale

EVIDENCE = "evidence"  # the frames' evidence with the method's pixel window (Eqs. 11-13)
BASELINE = "baseline"  # the Bayesian baseline's: single pixel, likelihoods or votes (method.bayesian_mode)
ONE_VIEW = "one_view"  # the evidence of one frame (method.view)
RULE = "rule"  # a lifting rule's per-point values, kept as the frames stream in (method/lifters.py)

LIFTING_PROTOCOLS = ("global_3d", "single_frame")
"""The protocols that run the lifting rules (and ``graph.affinity``, ``solver.tikhonov``: runs/resolve.py)."""

GraphOf = Callable[[Evidence], tuple]
"""A run's graph for an evidence: ``ev -> (graph, ev')``, the kNN graph (built when first asked) and
the evidence as ``graph.affinity`` / ``solver.tikhonov`` change it (:func:`graph_variant`)."""


@dataclass(frozen=True)
class Labelled:
    """What a method made of its evidence: ``values`` in ``space`` (class scores, or a features
    run's per-point features), the :class:`~diffuser_lab.method.diffusion.DiffusionResult` (None
    without a graph; a features run's ``Z``: the class scores of its features)."""

    space: object
    values: object
    diffusion: Optional[DiffusionResult]

    @property
    def labels(self) -> np.ndarray:
        """(M,) int16 labels (IGNORE where nothing reached a point)."""
        return self.space.labels(self.values)

    @property
    def scores(self) -> np.ndarray:
        """(M, C) the class scores calibration reads (Z, a pixel mass, a features run's query scores)."""
        return self.diffusion.Z if self.diffusion is not None else self.space.scores(self.values)

    def keep(self) -> None:
        """The values as the run's result (a features run's per-point features: ``space.method``)."""
        self.space.keep(self.values)


@dataclass(frozen=True)
class FusionMethod:
    """One fusion method. ``normals`` / ``k`` / ``pixel_radius``: None = as ``graph.use_normals`` /
    ``graph.k`` / ``evidence.pixel_radius`` say; a value = fixed by the method's definition.
    ``rule``: a lifting rule's class (its evidence is then :data:`RULE`)."""

    name: str
    description: str
    graph: bool  # it diffuses over the kNN graph; else it labels from its evidence alone
    evidence: str = EVIDENCE
    normals: Optional[bool] = None
    k: Optional[int] = None  # neighbours of the kNN graph (Eq. 3)
    pixel_radius: Optional[int] = None
    multi_view_row: bool = True  # a W-view row in the single-frame protocol besides the 1-view one
    rule: Optional[type] = None  # a streaming lifting rule (lifters.Rule subclass): evidence=RULE
    table_ii: bool = True  # a row of every single-frame run (else only when it is the run's method.name)
    protocols: Optional[tuple] = None  # the protocols it runs in (None: all)
    observed: bool = False  # its widest single-frame row's diffusion is the one the hooks observe (Diffuser)

    def __post_init__(self):
        if self.rule is not None:
            object.__setattr__(self, "evidence", RULE)
            object.__setattr__(self, "protocols", self.protocols or LIFTING_PROTOCOLS)

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

    @property
    def in_basis(self) -> bool:
        """Whether a features run may hold its evidence in a reduced basis (``predictions.basis=auto``):
        not for a lifting rule, which sees each link's unit feature in R^D."""
        return self.rule is None

    def runs_in(self, protocol: str) -> bool:
        """Whether the protocol ``protocol.name`` runs this method."""
        return self.protocols is None or protocol in self.protocols

    def check(self, cfg, n_points: int) -> None:
        """One line when the run's ``n_points`` work points cannot carry the method (a graph's K)."""
        if self.graph and cfg.graph.k >= n_points:
            raise ValueError(f"graph.k={cfg.graph.k} must be smaller than the number of points ({n_points})")

    # --- the evidence it reads

    def lifting_rule(self, space, cfg, n: int) -> Optional[lifters.Rule]:
        """This method's streaming rule for ``n`` points in the run's label ``space`` (its
        :meth:`rule_inputs`: the columns, and a features run's confidence and per-view labels), fed
        by the frame loop's links; None for a method without one."""
        if self.rule is None:
            return None
        return self.rule.of(n, depth_tol=cfg.evidence.depth_tol, top_k=cfg.method.top_k, **space.rule_inputs())

    def reads(self, run: RunEvidence, rule: Optional[lifters.Rule], frames: Sequence, cfg,
              points: np.ndarray) -> Evidence:
        """The evidence this method reads in a global run, of the run's evidence ``run`` (the method's
        and the baseline's), its lifting ``rule`` (:meth:`lifting_rule`, fed by the same frame loop)
        and its ``frames`` (``method.view``'s) on the work ``points``."""
        ev = run.method
        if self.evidence == BASELINE:
            return run.baseline
        if self.evidence == RULE:
            return Evidence(mass=rule.values(), links=ev.links)
        if self.evidence == ONE_VIEW:
            n_frames = len(frames)
            if not -n_frames <= cfg.method.view < n_frames:
                raise ValueError(f"method.view={cfg.method.view}: the scene has {n_frames} frames")
            return accumulate(points, [frames[cfg.method.view]], ev.mass.shape[1], depth_tol=cfg.evidence.depth_tol,
                              pixel_radius=cfg.evidence.pixel_radius)
        return ev

    def evidence_radius(self, cfg) -> int:
        """The pixel window of the evidence it reads (the Bayesian baseline's: the projected pixel)."""
        return 0 if self.evidence == BASELINE else cfg.evidence.pixel_radius

    def window_evidence(self, space, cfg, points: np.ndarray, frames: Sequence,
                        shared: Callable[[int], Evidence]) -> tuple[Evidence, Optional[lifters.Rule]]:
        """The evidence this method reads in the single-frame protocol, on a target's ``points`` from
        ``frames`` (its window, or the target alone): ``shared(radius)`` (the frames' evidence with its
        pixel window, shared between the rows that read the same) or a lifting rule's own pass over the
        same links; and the rule (None without)."""
        radius = self.evidence_radius(cfg)
        rule = self.lifting_rule(space, cfg, points.shape[0])
        if rule is None:
            return shared(radius), None
        ev = accumulate(points, frames, space.dim, depth_tol=cfg.evidence.depth_tol, pixel_radius=radius, hook=rule)
        return Evidence(mass=rule.values(), links=ev.links), rule

    # --- how it labels

    def label(self, space, ev: Evidence, *, rule: Optional[lifters.Rule] = None, graph: Optional[GraphOf] = None,
              solver=None, lam: float = 1.0, observer=None) -> Labelled:
        """Label ``ev`` (the evidence it reads) in the run's label ``space``: a graph method diffuses it
        over ``graph(ev)`` (Eqs. 14-15, 10, 16: ``space.diffuse``, lambda ``lam``, the ``solver`` config,
        ``observer`` sees the iterations), the others take its per-point values as they are (the
        Bayesian baseline, one view, a rule). A rule's class votes (``rule.classes``: ``vote``) are
        labelled as classes whatever the run's space."""
        space = space.classes if rule is not None and rule.classes else space
        if not self.graph:
            return Labelled(space, space.values(ev.mass), None)
        g, ev = graph(ev)
        values, diff = space.diffuse(g, ev, lam, solver, observer)
        return Labelled(space, values, diff)

    # --- what the protocols ask

    def single_frame_rows(self, window: int) -> list[int]:
        """Views of this method's rows in the single-frame protocol."""
        return [1, window] if self.multi_view_row and window > 1 else [1]

    def table_rows(self, window: int, run_method: str) -> list[int]:
        """Views of its rows in a single-frame run whose ``method.name`` is ``run_method`` (none when
        it is not in Table II and not the run's method)."""
        return self.single_frame_rows(window) if self.table_ii or self.name == run_method else []

    def spacing(self, cfg, measure: Callable[[], float]) -> Optional[float]:
        """rho for a tiled run's graphs (sigma_d = sigma_d_factor * rho of the whole cloud: ``measure()``),
        None where the method has no graph or ``graph.sigma_d`` is given."""
        return measure() if self.graph and cfg.graph.sigma_d is None else None

    def halo(self, cfg) -> float:
        """How far (metres) a point's label depends on other points, for a tile's halo:
        ``tiling.halo_factor`` * sigma_d (the graph's reach per Jacobi step, docs/tiling.md); 0 for a
        method without a graph (a point's label depends on its own evidence only)."""
        if not self.graph:
            return 0.0
        if cfg.graph.sigma_d is None:
            raise ValueError("tiling.halo=null needs the graph's sigma_d (resolved from rho first)")
        return float(cfg.tiling.halo_factor * cfg.graph.sigma_d)


def graph_variant(graph, ev: Evidence, cfg, *, colors: Optional[np.ndarray] = None,
                  average: Optional[np.ndarray] = None) -> Evidence:
    """What ``graph.affinity`` and ``solver.tikhonov`` change of a graph method's inputs: the graph's
    weights (in place: LUDVIG's Eq. 4 x the points' similarity, :mod:`~diffuser_lab.method.affinity`;
    ``colors`` / ``average``: the work points' colours, a features run's averaged features) and the
    evidence the system reads (Splat Feature Solver's Tikhonov term, :func:`~diffuser_lab.method.exact.tikhonov_scale`:
    a new Evidence; ``ev`` is not changed). Both off (the defaults): ``ev`` and the graph as they are."""
    attrs, known = affinity.attributes(cfg.graph.affinity, colors=colors, mass=ev.mass, links=ev.links, average=average)
    if attrs is not None:
        affinity.apply_affinity(graph, attrs, known, cfg.graph.sigma_c)
    if cfg.solver.tikhonov > 0:
        alpha = tikhonov_scale(graph, ev.links, cfg.evidence.pixel_weight, cfg.solver.tikhonov)
        ev = Evidence(mass=ev.mass * alpha[:, None], links=ev.links * alpha)
    return ev


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
    FusionMethod("diffuser", "the paper's method: the evidence diffused over the kNN graph", graph=True,
                 observed=True),
    # the training-free lifting rules of 2024-2026 on the same evidence (method/lifters.py, docs/lifters.md)
    FusionMethod("weighted", "Occam's LGS / Dr. Splat: the average weighted by each view's share of the point "
                 "(incidence, distance, depth margin)", graph=False, rule=lifters.Weighted, table_ii=False),
    FusionMethod("median", "VALA: streaming weighted geometric median (Weiszfeld steps; features in cosine space)",
                 graph=False, rule=lifters.Median, table_ii=False),
    FusionMethod("topk", "The Bare Necessities: the average of each point's method.top_k most confident views",
                 graph=False, rule=lifters.TopK, table_ii=False),
    FusionMethod("vote", "LabelMaker: hard votes of the depth-checked views (features: of their query labels)",
                 graph=False, rule=lifters.Vote, table_ii=False),
], sort_names=True)
"""The fusion methods by name (``method.name``)."""


def get(name: str) -> FusionMethod:
    """The entry a name names, or one line naming method.name and the names (sorted)."""
    return METHODS.named(name)
