"""The label spaces a run labels in: one interface, two implementations.

- :class:`Classes`: the frames carry a network's labels or class distributions; a point's evidence
  and scores are C class columns, its label their argmax (Eq. 16).
- :class:`Features`: the frames carry a network's per-pixel embeddings
  (:mod:`diffuser_lab.method.features`); a point's evidence is D feature columns (or their
  coordinates in the run's reduced basis, :mod:`diffuser_lab.method.basis`), its label the class of
  its best query (:mod:`diffuser_lab.method.queries`); the run adds the best-view baseline and
  writes its features (``features.npy``, ``features_basis.npz``: writer and reader here).

A run makes its space from its first frame (:func:`of_frame`) and asks it, never which it is:

=================================  ===========================================================
the run's evidence                 :meth:`~Classes.admit` (a frame's evidence can be added now;
                                   a features run holds the frames its basis is fitted on first:
                                   :func:`frame_order`), :meth:`~Classes.run_evidence`, ``rule``
labels and scores of values        :meth:`~Classes.labels`, :meth:`~Classes.scores`
a method's values                  :meth:`~Classes.values` (a mass as it is), :meth:`~Classes.diffuse`
                                   (Eqs. 14-15, 10: classes normalised and solved; features
                                   encoded, diffused and decoded), :meth:`~Classes.keep`
what the diffusion needs           :meth:`~Classes.solver` (features: no per-point class set),
                                   :meth:`~Classes.observer` (the hooks' adapter)
baselines                          :meth:`~Classes.add_baselines`, :meth:`~Classes.baseline_scores`
                                   (calibration), :meth:`~Classes.baseline_metrics` (best view)
what it tells and writes           :meth:`~Classes.summary`, :meth:`~Classes.write`,
                                   :meth:`~Classes.tile_features`
=================================  ===========================================================
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from diffuser_lab import progress
from diffuser_lab.backends.records import WRITE_ROWS, write_rows
from diffuser_lab.backends.threads import blas_one_thread
from diffuser_lab.config import SparseClasses
from diffuser_lab.data.arrays import open_npz
from diffuser_lab.data.embeddings import prototypes, write_queries
from diffuser_lab.data.scene import IGNORE, Frame, Taxonomy
from diffuser_lab.method.metrics import score

from . import features as features_mod
from .basis import BasisFeatures, FeatureBasis, fit_basis, query_span, unit_rows_float16
from .diffusion import Observer, labels_from_scores, normalise
from .evidence import BestView, Evidence, RunEvidence, accumulate
from .queries import Queries, labels_of_cosines, query_classes, query_labels, similarity
from .solvers import solve

__all__ = ["Classes", "Features", "Observe", "FeatureObserve", "of_frame", "frame_order", "basis_frames",
           "feature_basis", "basis_kept", "FEATURE_FILES", "BASIS_FILE", "read_basis", "TileFeatures"]


class Observe:
    """Adapts :class:`~diffuser_lab.hooks.RunHooks` (and a plain observer callable ``fn``) to the
    diffusion's observer: both see (M, C) class scores."""

    def __init__(self, hooks, fn: Optional[Observer] = None):
        self.hooks, self.fn = hooks, fn

    def wants(self, it: int) -> bool:
        return self.fn is not None or self.hooks.wants(it)

    def statistics(self):
        """The hooks' request of every step's statistics."""
        return self.hooks.statistics()

    def on_statistics(self, table) -> None:
        self.hooks.on_statistics(table)

    def __call__(self, it: int, Z: np.ndarray, stats: dict) -> None:
        if self.fn is not None:
            self.fn(it, Z, stats)
        if self.hooks.wants(it):
            self.hooks.observe(it, Z, stats)


class FeatureObserve(Observe):
    """:class:`Observe` of a features run's diffusion: the hooks see the decoded features
    (``observe_features``), then both see the queries' class scores of them (:meth:`Features.scores`)."""

    def __init__(self, hooks, fn: Optional[Observer], space: "Features"):
        super().__init__(hooks, fn)
        self.space = space

    def statistics(self):
        """None: the columns of a features run are no classes."""
        return None

    def __call__(self, it: int, Z: np.ndarray, stats: dict) -> None:
        F = features_mod.decode(Z)
        F.flags.writeable = False
        if self.hooks.wants(it):
            self.hooks.observe_features(it, self.space.observed(F))
        Z = self.space.scores(F)
        Z.flags.writeable = False
        super().__call__(it, Z, stats)


def of_frame(frame: Frame, cfg, taxonomy: Taxonomy, method, n_frames: int = 0):
    """The label space of a run whose first frame is ``frame``: :class:`Features` when it carries a
    feature map, else :class:`Classes`. ``method`` (the run's :class:`~diffuser_lab.method.fusion.FusionMethod`)
    and ``n_frames``: what a global run's evidence needs (:meth:`Features.admit`)."""
    if frame.features is not None:
        return Features.of(cfg, taxonomy, frame.features.shape[2], method, n_frames)
    return Classes(taxonomy.num_classes)


def _basis_sample(cfg, method, n_frames: int) -> list[int]:
    """The frames a features run fits its basis on (``predictions.basis=auto`` and a method that
    diffuses features in it), read first; [] otherwise."""
    auto = cfg.predictions.basis == "auto" and method.in_basis
    return basis_frames(n_frames, cfg.predictions.basis_frames) \
        if cfg.predictions.source == "features" and auto and n_frames else []


def frame_order(cfg, method, n_frames: int) -> Optional[list[int]]:
    """The order a global run reads its frames in: a features run with ``predictions.basis=auto``
    first the (evenly spaced) frames its basis is fitted on, then the others; None: in order."""
    sample = _basis_sample(cfg, method, n_frames)
    first = set(sample)
    return sample + [j for j in range(n_frames) if j not in first] if sample else None


class _Space:
    """What both spaces share: the run's evidence and lifting rule, once made (:meth:`admit`)."""

    baseline_title = "bayesian (baseline)"
    average = None  # a features run's averaged features (graph.affinity=features reads them)

    def __init__(self, num_classes: int):
        self.num_classes = int(num_classes)
        self.evidence: Optional[RunEvidence] = None
        self.rule = None  # the method's lifting rule (method/lifters.py), fed by the evidence's links
        self.timings: dict = {}

    def _start(self, cfg, method, n: int, columns: int) -> RunEvidence:
        self.evidence = RunEvidence.of(cfg, n, columns)
        self.rule = self.evidence.hook = method.lifting_rule(self, cfg, n)
        return self.evidence

    def admit(self, i: int, f: Frame, cfg, method, n: int, hooks) -> list[tuple[int, Frame]]:
        """The frames whose evidence a global run adds now, given frame ``i``: itself (the run's
        evidence made at the first frame, for ``n`` points, with ``method``'s lifting rule)."""
        if self.evidence is None:
            self._start(cfg, method, n, self.dim)
        return [(i, f)]

    def run_evidence(self, cfg, method, n: int) -> RunEvidence:
        """The run's evidence (made now when no frame came)."""
        return self.evidence if self.evidence is not None else self._start(cfg, method, n, self.dim)


class Classes(_Space):
    """Class labels: evidence, scores and values are (M, C) class columns."""

    kind = "classes"

    def __init__(self, num_classes: int):
        super().__init__(num_classes)
        self.dim = self.num_classes

    @property
    def classes(self) -> "Classes":
        return self

    # --- frames
    def check_frame(self, f: Frame) -> None:
        if f.features is not None:
            raise ValueError(f"frame {f.name}: feature map, unlike the first frame")

    def label_image(self, f: Frame) -> np.ndarray:
        """The frame's 2D prediction as labels (scored against its ground truth)."""
        return f.labels if f.labels is not None else np.argmax(f.probs, axis=2)

    def rule_inputs(self) -> dict:
        """What a lifting rule is made with (:meth:`~diffuser_lab.method.lifters.Rule.of`)."""
        return {"dim": self.num_classes, "features": False, "num_classes": self.num_classes}

    def observed_evidence(self, ev: Evidence) -> Evidence:
        """The evidence the hooks see (``on_evidence``)."""
        return ev

    # --- labels
    def labels(self, x: np.ndarray) -> np.ndarray:
        return labels_from_scores(x)

    def scores(self, x: np.ndarray) -> np.ndarray:
        return x

    def values(self, mass: np.ndarray) -> np.ndarray:
        """A method's per-point values of a mass it labels as it is (no graph)."""
        return mass

    def diffuse(self, graph, ev: Evidence, lam: float, solver, observer=None):
        """(Z, DiffusionResult): Eqs. 14-15 of ``graph`` and the evidence's mass, solved by ``solver``."""
        diff = solve(normalise(graph, ev.mass, lam), solver, observer=observer)
        return diff.Z, diff

    def keep(self, values) -> None:
        """A method's result on the work points, kept for the run's result (classes: its scores are)."""

    def solver(self, solver):
        return solver

    def observer(self, hooks, fn: Optional[Observer] = None) -> Observe:
        return Observe(hooks, fn)

    # --- baselines, what a run tells and writes
    def add_baselines(self, evidence: RunEvidence) -> None:
        """The baselines the space adds from the run's evidence (classes: the Bayesian one is the evidence's)."""

    def finish(self, evidence: RunEvidence) -> None:
        """After the method's labelling (features: what the basis kept)."""

    def baseline_scores(self, base_mass: np.ndarray) -> dict[str, Callable[[], np.ndarray]]:
        """The baselines' (M, C) class scores for calibration, by name (computed when called)."""
        return {"bayesian": lambda: base_mass}

    def baseline_metrics(self, rows: np.ndarray, gt: np.ndarray, names) -> dict:
        """The scores of the baselines the space adds (features: the best view)."""
        return {}

    def summary(self, taxonomy: Taxonomy) -> dict:
        """summary.json's keys of the space."""
        return {}

    def write(self, run_dir: Path, rows: Optional[np.ndarray]) -> dict:
        """The space's own files in the run folder (classes: none); their names."""
        return {}

    def tile_record(self) -> dict:
        return {}

    def tile_features(self, rows: np.ndarray) -> Optional[dict]:
        """What a tile file keeps of its own points' ``rows`` besides their labels (classes: nothing)."""
        return None

    # --- the single-frame protocol
    def extra_rows(self, window: int) -> list[tuple[str, int]]:
        """Rows the space adds to Table II (features: the best view of the window)."""
        return []

    def window_baselines(self, points: np.ndarray, frames: Sequence[Frame], window: int, depth_tol: float) -> dict:
        """{(row, views): (labels, scores)} of :meth:`extra_rows` on a target's work points."""
        return {}

    def averaged(self, mass: np.ndarray) -> Optional[np.ndarray]:
        """A window's averaged features (``graph.affinity=features``; classes: None, the mass is read)."""
        return None

    def watched(self, row):
        """The single-frame row whose diffusion the hooks observe (features: none, its columns are no classes)."""
        return row


@dataclasses.dataclass(eq=False)
class Features(_Space):
    """Features (frames with feature maps: :mod:`diffuser_lab.method.features`): per-point features
    turned into labels by the query set, each query's class and the background rule.

    Features are (M, D) arrays (``basis`` None: ``predictions.basis=full``, the single-frame
    protocol, a lifting rule) or, with a reduced ``basis`` (:mod:`diffuser_lab.method.basis`),
    :class:`BasisFeatures` (or the (M, k + s) sums they split from): cosines with the queries exact in
    f.q, divided by the estimated |f|.

    Attributes:
        queries: :class:`~diffuser_lab.method.queries.Queries` (Q names, (Q, D) unit embeddings).
        to_class: (Q,) int64 the taxonomy class of each query (-1: none).
        threshold, background: a point whose best cosine is below ``threshold`` gets ``background``.
        basis: the run's :class:`~diffuser_lab.method.basis.FeatureBasis`, or None (full).
        basis_info: summary.json's ``features.basis`` (what the basis is and what it kept).
        method: the method's per-point feature sums (Diffuser: diffused), set by the run: (M, D)
            float32, or :class:`BasisFeatures`; None for a rule of class votes (``vote``).
        average: the averaging baseline's (the mean of the depth-checked pixels' features): (M, D)
            float16 unit rows, or :class:`BasisFeatures` of the sums.
        best_view: the most confident view's unit feature (:class:`~diffuser_lab.method.evidence.BestView`):
            (M, D) float16, or :class:`BasisFeatures` (its residual exact: 1 - |coords|^2).
        sample: the frames a global run fits its basis on (:func:`frame_order`), held until it is.
    """

    queries: Queries
    to_class: np.ndarray
    num_classes: int
    threshold: Optional[float] = None
    background: int = IGNORE
    basis: Optional[FeatureBasis] = None
    basis_info: dict = dataclasses.field(default_factory=lambda: {"kind": "full"})
    method: Optional[np.ndarray | BasisFeatures] = None
    average: Optional[np.ndarray | BasisFeatures] = None
    best_view: Optional[np.ndarray | BasisFeatures] = None
    sample: list = dataclasses.field(default_factory=list)

    kind = "features"
    baseline_title = "average (baseline)"

    def __post_init__(self):
        self.num_classes = int(self.num_classes)
        self.evidence, self.rule, self.timings = None, None, {}
        self.pending: list = []

    @classmethod
    def of(cls, cfg, taxonomy: Taxonomy, dim: int, method, n_frames: int = 0) -> "Features":
        """The run's queries (``predictions.queries``: a file; ``predictions.encoder``: a text encoder
        on the taxonomy's names; neither: the simulated network's prototypes of them) and their classes,
        for frames of ``dim``-D features."""
        pc = cfg.predictions
        if pc.queries:
            q = Queries.from_file(pc.queries)
        elif pc.encoder:
            q = Queries.from_encoder(list(taxonomy.names), pc.encoder)
        else:
            q = Queries(tuple(taxonomy.names), prototypes(taxonomy.names, dim=dim, seed=pc.embedding_seed))
        if q.embeddings.shape[1] != dim:
            raise ValueError(f"the queries have D = {q.embeddings.shape[1]}, the frames' features D = {dim}")
        to_class = np.asarray(query_classes(q.names, taxonomy.names, pc.query_mapping), np.int64)
        background = IGNORE if pc.background is None else taxonomy.names.index(pc.background)
        return cls(q, to_class, taxonomy.num_classes, pc.threshold, background,
                   sample=_basis_sample(cfg, method, n_frames))

    @property
    def dim(self) -> int:
        """D: the columns of a window's evidence and of a lifting rule's vectors (in R^D)."""
        return self.queries.dim

    @property
    def classes(self) -> Classes:
        """The class space of the same taxonomy (a rule's class votes: ``vote``)."""
        return Classes(self.num_classes)

    # --- frames and the run's evidence
    def check_frame(self, f: Frame) -> None:
        if f.features is None:
            raise ValueError(f"frame {f.name}: no feature map, unlike the first frame")

    def label_image(self, f: Frame) -> None:
        """None: a feature map is no labels."""
        return None

    def admit(self, i: int, f: Frame, cfg, method, n: int, hooks) -> list[tuple[int, Frame]]:
        """Frame ``i`` once the run's evidence is made; the frames the basis is fitted on
        (:attr:`sample`) are held until the last of them comes, then the basis is fitted on their
        feature maps, the evidence made (:meth:`start`) and all of them returned."""
        if self.evidence is not None:
            return [(i, f)]
        self.pending.append((i, f))
        if len(self.pending) < len(self.sample):
            return []
        t0 = time.perf_counter()
        self.start(cfg, method, n, [g.features for _, g in self.pending], hooks)
        self.timings["basis"] = time.perf_counter() - t0
        ready, self.pending = self.pending, []
        return ready

    def start(self, cfg, method, n: int, maps: Sequence[np.ndarray], hooks) -> RunEvidence:
        """The run's evidence for ``n`` points: in the basis fitted on ``maps`` (``predictions.basis=auto``
        and a method that diffuses in it, :func:`feature_basis`) or in all D columns; with the most
        confident view tracked, the hooks told the queries (in the basis' coordinates when there is
        one) and ``method``'s lifting rule on its links."""
        D = self.queries.dim
        auto = cfg.predictions.basis == "auto" and method.in_basis
        basis = feature_basis(cfg, self.queries, maps) if auto else None
        if basis is not None:
            self.basis, self.basis_info = basis, basis.record()
        evidence = self._start(cfg, method, n, basis.width if basis else D)
        evidence.basis = basis
        hooks.on_queries(self.queries.names, self.queries.embeddings if basis is None else basis.queries,
                         basis=None if basis is None else basis.vectors)
        evidence.best = BestView(n, basis.k if basis else D, self.unit_confidence)
        return evidence

    def rule_inputs(self) -> dict:
        """A rule sees each link's unit feature in R^D: topk its confidence, vote its query label."""
        return {"dim": self.queries.dim, "features": True, "num_classes": self.num_classes,
                "confidence": self.confidence, "classify": self.labels}

    def observed_evidence(self, ev: Evidence) -> Evidence:
        """The evidence the hooks see: in the basis, its k coordinates (not the probes)."""
        return ev if self.basis is None else dataclasses.replace(ev, mass=ev.mass[:, :self.basis.k])

    # --- labels and scores of features
    def _in_basis(self, features) -> Optional[BasisFeatures]:
        if self.basis is None:
            return None
        if isinstance(features, BasisFeatures):
            return features
        if features.shape[1] != self.basis.width:
            raise ValueError(f"features of shape {features.shape}, expected (M, {self.basis.width}): the basis' "
                             f"{self.basis.k} + {self.basis.s} columns")
        return self.basis.split(features)

    def cosines(self, features) -> np.ndarray:
        """(M, Q) float32 cosines with the queries (NaN rows: no feature)."""
        b = self._in_basis(features)
        return similarity(features, self.queries) if b is None else b.cosines(self.basis.queries)

    def unit_confidence(self, features: np.ndarray) -> np.ndarray:
        """(M, D) unit features, or with a basis their (M, k) coordinates -> (M,) float32 the top
        class's probability (softmax over the classes' best cosines at
        :data:`~diffuser_lab.method.features.CLIP_TEMPERATURE`): what picks a point's most confident view."""
        if self.basis is None:
            return self.confidence(features)
        cos = np.asarray(features, np.float32) @ np.ascontiguousarray(self.basis.queries.T)  # |f| = 1 exactly
        return features_mod.top_probability(cos, self.to_class, self.num_classes)

    def confidence(self, features) -> np.ndarray:
        """Features -> (M,) float32 the top class's probability (as :meth:`unit_confidence`)."""
        return features_mod.top_probability(self.cosines(features), self.to_class, self.num_classes)

    def labels(self, features) -> np.ndarray:
        """Features -> (M,) int16 class ids (IGNORE where nothing reached a point)."""
        b = self._in_basis(features)
        if b is None:
            return query_labels(features, self.queries, self.to_class, threshold=self.threshold,
                                background=self.background)
        return labels_of_cosines(b.cosines(self.basis.queries), self.to_class, self.threshold, self.background)

    def scores(self, features) -> np.ndarray:
        """Features -> (M, C) class scores (:func:`~diffuser_lab.method.features.class_scores`)."""
        return features_mod.class_scores(self.cosines(features), self.to_class, self.num_classes)

    def observed(self, features) -> np.ndarray:
        """What the records' feature views see of features: the (M, D) array, or the (M, k) coordinates."""
        b = self._in_basis(features)
        return features if b is None else b.coords

    def unit_rows(self, features, rows: Optional[np.ndarray] = None, out: Optional[np.ndarray] = None) -> np.ndarray:
        """(M', D) float16 unit rows in R^D of ``rows`` (default all) of features (a basis':
        the projections; :meth:`BasisFeatures.unit_float16`), into ``out`` when given."""
        b = self._in_basis(features)
        if b is not None:
            return b.unit_float16(self.basis, rows, out)
        part = features if rows is None else features[rows]
        unit = part if part.dtype == np.float16 else features_mod.unit_float16(part)
        if out is None:
            return unit
        out[...] = unit
        return out

    def values(self, mass: np.ndarray):
        """A method's per-point features of feature sums it labels as they are (in the basis: split)."""
        return mass if self.basis is None else self.basis.split(mass)

    def diffuse(self, graph, ev: Evidence, lam: float, solver, observer=None):
        """The feature sums through the unchanged core, encoded (:func:`~diffuser_lab.method.features.diffuse_features`,
        in blocks when large: ``ev.mass`` may be overwritten); (features, DiffusionResult whose ``Z`` is
        their class scores, the scores its observers saw)."""
        F, diff = features_mod.diffuse_features(graph, ev.mass, ev.links, lam, solver, observer=observer)
        values = self.values(F)
        return values, dataclasses.replace(diff, Z=self.scores(values))

    def keep(self, values) -> None:
        self.method = values

    def solver(self, solver):
        """Every column is a feature's: no per-point class set."""
        return dataclasses.replace(solver, sparse_classes=SparseClasses.off)

    def observer(self, hooks, fn: Optional[Observer] = None) -> FeatureObserve:
        return FeatureObserve(hooks, fn, self)

    # --- baselines, what a run tells and writes
    def add_baselines(self, evidence: RunEvidence) -> None:
        """The averaging baseline (before the method's sums may be diffused in place) and the best view."""
        if self.basis is None:
            self.average = features_mod.unit_float16(evidence.baseline.mass)
            self.best_view = evidence.best.features
        else:  # the sums' coordinates (copied: F may be diffused in place); a unit view's residual is exact
            self.average = self.basis.split(evidence.baseline.mass.copy())
            c = evidence.best.features
            kept = np.einsum("ij,ij->i", c, c, dtype=np.float32)
            self.best_view = BasisFeatures(c, np.where(evidence.best.score > -np.inf, np.maximum(1 - kept, 0), 0))

    def finish(self, evidence: RunEvidence) -> None:
        """What a reduced basis kept (:func:`basis_kept`), into :attr:`basis_info`."""
        if self.basis is not None:
            self.basis_info.update(basis_kept(self, evidence.energy))

    def baseline_scores(self, base_mass: np.ndarray) -> dict[str, Callable[[], np.ndarray]]:
        return {"bayesian": lambda: self.scores(self.average), "best_view": lambda: self.scores(self.best_view)}

    def baseline_metrics(self, rows: np.ndarray, gt: np.ndarray, names) -> dict:
        return {"best_view": score(self.labels(self.best_view)[rows], gt, names)}

    def summary(self, taxonomy: Taxonomy) -> dict:
        """``class_names`` and ``features`` (its bayesian baseline is the averaging of features)."""
        return {"class_names": list(taxonomy.names),
                "features": {"dim": int(self.queries.dim), "queries": list(self.queries.names),
                             "threshold": self.threshold, "baseline": "average", "basis": self.basis_info}}

    def write(self, run_dir: Path, rows: Optional[np.ndarray]) -> dict:
        """The per-point features on the scene's original points (``rows``: each one's work point;
        None: the work points are they), (N, D) float16 unit rows (an all-zero row: nothing reached the
        point): ``features.npy`` (the method's), ``features_average.npy`` (the averaging baseline's),
        ``features_best_view.npy`` (the most confident view's); ``queries.npz`` (the run's query set),
        so that ``diffuser-lab-query`` relabels the run (with its ``gt_labels.npy``) without it.

        With a reduced basis (``predictions.basis=auto``) ``features.npy`` holds the projections, and
        :data:`BASIS_FILE` the three methods' features in the basis (:func:`write_basis`) instead of the
        baselines' (N, D) files: 3 x N x D x 2 bytes (950 MB at 317k x 512) are as long to write as the run."""
        if rows is not None and np.array_equal(rows, np.arange(rows.size)):
            rows = None
        with blas_one_thread():  # many small products: OpenBLAS's spinning workers would cost more than they give
            return self._write(Path(run_dir), rows)

    def _write(self, run_dir: Path, rows: Optional[np.ndarray]) -> dict:
        out = {}
        methods = dict(zip((key for key, _, _ in FEATURE_FILES), (self.method, self.average, self.best_view)))
        files = [(file, methods[key]) for key, file, _ in FEATURE_FILES]
        if self.basis is not None:  # the baselines in the basis only: (N, k) each, not (N, D)
            files = files[:1]
            write_basis(run_dir / BASIS_FILE, self.basis, {k: X if rows is None else X.take(rows)
                                                           for k, X in methods.items()})
            out["features_basis"] = BASIS_FILE
        for file, work in files:
            if work is None:  # a rule without features of its own (vote: class votes)
                continue
            n = len(work) if rows is None else len(rows)
            buf = np.empty((min(n, WRITE_ROWS), self.queries.dim), np.float16)  # a basis' rows made in R^D

            def chunks(work=work, buf=buf, n=n):
                for lo in range(0, n, WRITE_ROWS):  # chunks of rows: 4 MB at D = 512
                    sel = np.arange(lo, min(lo + WRITE_ROWS, n)) if rows is None else rows[lo:lo + WRITE_ROWS]
                    yield self.unit_rows(work, sel, out=buf[: len(sel)])

            write_rows(run_dir / file, (n, self.queries.dim), chunks())
            out[file[: -len(".npy")]] = file
        write_queries(run_dir / "queries.npz", list(self.queries.names), self.queries.embeddings)
        out["queries"] = "queries.npz"
        return out

    def tile_record(self) -> dict:
        """A tile's own basis (``predictions.basis=auto``) and what it kept."""
        return {"basis": self.basis_info}

    def tile_features(self, rows: np.ndarray) -> dict:
        """The method's features of a tile's own points (``rows``: their work points), for its tile file:
        ``{"features": (own, D) float16 unit rows}``, or in the tile's reduced basis ``{"feature_coords":
        (own, k) float32, "feature_vectors": (D, k) float32}`` (made (own, D) when features.npy is
        written: :class:`TileFeatures`)."""
        if self.basis is None:
            return {"features": self.unit_rows(self.method, rows)}
        return {"feature_coords": np.asarray(self.method.coords[rows], np.float32), "feature_vectors": self.basis.vectors}

    # --- the single-frame protocol
    def extra_rows(self, window: int) -> list[tuple[str, int]]:
        """A features run's other baseline: each point's most confident view of the window."""
        return [("best_view", window)] if window > 1 else []

    def window_baselines(self, points: np.ndarray, frames: Sequence[Frame], window: int, depth_tol: float) -> dict:
        if window <= 1:
            return {}
        best = BestView(points.shape[0], self.queries.dim, self.confidence)
        accumulate(points, frames, self.queries.dim, best=best, depth_tol=depth_tol)
        return {("best_view", window): (self.labels(best.features), self.scores(best.features))}

    def averaged(self, mass: np.ndarray) -> np.ndarray:
        return features_mod.normalised(mass)[0]

    def watched(self, row):
        return None


def basis_frames(n_frames: int, wanted: int) -> list[int]:
    """The frames a run's basis is fitted on: ``wanted`` evenly spaced indices of ``n_frames``
    (all of them when fewer), the first and the last included."""
    m = max(1, min(int(wanted), n_frames))
    return sorted({int(round(x)) for x in np.linspace(0, n_frames - 1, m)})


def feature_basis(cfg, queries: Queries, maps: Sequence[np.ndarray]) -> Optional[FeatureBasis]:
    """``predictions.basis=auto``: the run's :class:`~diffuser_lab.method.basis.FeatureBasis`, fitted on
    the valid cells (unit rows) of ``maps`` ((h, w, D) feature maps of the frames :func:`basis_frames`
    picks) and the queries; None (the full path, exact) when it would not halve the D columns (the
    queries' rank + ``basis_dim`` + ``basis_probes`` > D / 2)."""
    pc = cfg.predictions
    D = queries.dim
    rank = query_span(queries.embeddings).shape[1]
    if 2 * (rank + pc.basis_dim + pc.basis_probes) > D:
        return None
    cells = []
    with progress.stage(f"feature basis: {len(maps)} frames' cells, {rank} queries + {pc.basis_dim} "
                        f"directions + {pc.basis_probes} probes of {D}"):
        for fmap in maps:  # a few frames
            if fmap is None or fmap.ndim != 3 or fmap.shape[2] != D:
                continue  # the evidence reports it
            cells.append(features_mod.normalised(fmap.reshape(-1, D))[0][np.isfinite(fmap).all(2).reshape(-1)])
        sample = np.concatenate(cells) if cells else np.zeros((0, D), np.float32)
        sample = sample[np.einsum("ij,ij->i", sample, sample) > 0]
        return fit_basis(sample, queries.embeddings, pc.basis_dim, pc.basis_probes, cfg.seed)


def basis_kept(space: Features, energy: np.ndarray) -> dict:
    """What a reduced basis kept, for summary.json's ``features.basis``: the share of the linked
    pixels' energy (exact: each pixel's projection, over all links); per point with a feature, the
    share of the method's features' and of the averaging baseline's energy, |P f|^2 / |f|^2
    (``median``, ``p5``), and the relative error of the projection's norm, 1 - |P f| / |f|
    (``median``, ``p95``), |f| estimated with the probes (random: right on average over their draw,
    not for one draw: a few times too large or too small where the residual has few directions)."""
    out = {"energy_pixels": round(float(energy[0] / energy[1]), 6) if energy[1] else None}
    for name, X in (("features", space.method), ("average", space.average)):
        share = X.energy_kept()
        share = share[np.isfinite(share)]
        out[f"energy_{name}"] = {"median": round(float(np.median(share)), 6),
                                 "p5": round(float(np.percentile(share, 5)), 6)} if share.size else None
        if name == "features":
            err = 1 - np.sqrt(share)
            out["norm_error"] = {"median": round(float(np.median(err)), 6),
                                 "p95": round(float(np.percentile(err, 95)), 6)} if share.size else None
    return out


# --- a features run's files: the (N, D) features, the basis file (writer and reader), a tile's features

FEATURE_FILES = (("diffuser", "features.npy", "diffuser"),
                 ("average", "features_average.npy", "average (baseline)"),
                 ("best_view", "features_best_view.npy", "best view (baseline)"))
"""A features run's per-point features: (key in features_basis.npz and query.json, file in the run
folder, row of a table), the method's first."""
BASIS_FILE = "features_basis.npz"
"""A reduced-basis features run's per-point features in the basis (:func:`write_basis`, :func:`read_basis`)."""


def write_basis(path: Path, basis: FeatureBasis, methods: dict) -> None:
    """:data:`BASIS_FILE`: ``vectors`` (D, k) float32, the ``queries`` (Q, k) coordinates and per
    method key of :data:`FEATURE_FILES` (``methods``: {key: :class:`BasisFeatures`}, None: none)
    ``<key>_coords`` (N, k) float32 sums and ``<key>_residual`` (N,) float32 the estimated energy
    outside the basis."""
    parts = {"vectors": basis.vectors, "queries": basis.queries}
    for key, X in methods.items():
        parts[f"{key}_coords"] = np.asarray(X.coords, np.float32)
        parts[f"{key}_residual"] = np.asarray(X.residual, np.float32)
    np.savez(path, **parts)


def read_basis(path: Path, shape: tuple[int, int]) -> tuple[np.ndarray, dict]:
    """(D, k) vectors and {method key: BasisFeatures} of a run's :data:`BASIS_FILE`; ``shape``:
    features.npy's (N, D). ValueError (one line naming the file) when it does not fit."""
    with open_npz(path, "a features run's basis (vectors, <method>_coords, <method>_residual)", role=None) as z:
        V = np.asarray(z.read("vectors", ndim=2, kinds="f"), np.float32)
        out = {key: BasisFeatures(np.asarray(z.read(f"{key}_coords", ndim=2, kinds="f"), np.float32),
                                  np.asarray(z.read(f"{key}_residual", ndim=1, kinds="f"), np.float32))
               for key, _, _ in FEATURE_FILES if f"{key}_coords" in z}
    N, D = shape
    if V.ndim != 2 or V.shape[0] != D or FEATURE_FILES[0][0] not in out or any(
            f.coords.shape != (N, V.shape[1]) or f.residual.shape != (N,) for f in out.values()):
        raise ValueError(f"{path}: vectors {V.shape} and coordinates {[f.coords.shape for f in out.values()]}, expected "
                         f"({D}, k) and ({N}, k) as features.npy's ({N}, {D})")
    return V, out


TILE_FEATURES = ("features", "feature_coords", "feature_vectors")
"""A features run's tile file's feature arrays (:meth:`Features.tile_features`)."""


class TileFeatures:
    """``features.npy`` of a tiled run, assembled from its tiles' files (:meth:`Features.tile_features`'s
    arrays): made at the first tile that holds features (zero rows), each tile's rows written through a
    memory map of its own; a labels run's tiles hold none, and nothing is written."""

    def __init__(self, path: Path, n: int):
        self.path, self.n, self.made = Path(path), int(n), False

    def add(self, own: np.ndarray, stored: Optional[dict]) -> None:
        """A tile's ``stored`` features (None: none) into the rows ``own`` (a failed tile's points keep
        zero rows: unlabeled), a chunk of rows at a time."""
        if not stored:
            return
        if not self.made:
            dim = stored["features"].shape[1] if "features" in stored else stored["feature_vectors"].shape[0]
            np.lib.format.open_memmap(self.path, mode="w+", dtype=np.float16, shape=(self.n, dim)).flush()
            self.made = True
        mm = np.load(self.path, mmap_mode="r+")  # this tile's pages leave the process when it is closed
        if "features" in stored:
            mm[own] = stored["features"]
        else:
            with blas_one_thread():
                for lo in range(0, own.size, WRITE_ROWS):  # chunks of rows: (4096, D) temporaries
                    mm[own[lo:lo + WRITE_ROWS]] = unit_rows_float16(stored["feature_coords"][lo:lo + WRITE_ROWS],
                                                                    stored["feature_vectors"])
        mm.flush()
        del mm

    @property
    def files(self) -> dict:
        """The files written ({"features": "features.npy"} once made)."""
        return {"features": self.path.name} if self.made else {}

    def halos(self, halos: list) -> list:
        """The tiles' labelled halo points a point its tile left unlabelled may take its label from:
        none in a features run (a point's features come from its own tile only, and its label with them)."""
        return [] if self.made else halos

    @staticmethod
    def rows_of(stored: dict) -> int:
        """The points a tile file's features cover (its check against the tile's own points)."""
        return next(v for k, v in stored.items() if k != "feature_vectors").shape[0]
