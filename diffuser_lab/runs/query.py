"""Relabel a finished features run from its saved per-point features with a query set: no
diffusion, no scene loading (seconds). The command: ``diffuser-lab-query`` (cli/query.py).

A features run's folder holds (written by the pipeline, ``predictions=features``):

- ``features.npy`` (N, D) float16, Diffuser's per-point features (an all-zero row: nothing reached
  the point), and the baselines' ``features_average.npy`` (feature averaging, OpenScene's 2D fusion)
  and ``features_best_view.npy`` (the most confident view's feature), each optional;
- with a reduced basis (``predictions.basis=auto``) ``features_basis.npz`` (the three methods'
  features in the basis: :meth:`diffuser_lab.method.space.Features.write`, read by
  :func:`diffuser_lab.method.space.read_basis`), read instead of the
  (N, D) files: a query's cosines are then f.q from the basis' coordinates over the run's estimated |f|;
- ``gt_labels.npy`` (N,) int16 ground truth (IGNORE = unannotated), when the scene has it;
- ``summary.json`` with ``class_names`` (the taxonomy's names in id order) and ``taxonomy``.

:func:`query_run` labels every method's features with the queries
(:func:`diffuser_lab.method.queries.query_labels`), scores them against the ground truth as a run
does (:func:`diffuser_lab.method.metrics.score`), and writes ``query_labels.npy`` (Diffuser's
labels, (N,) int16) and ``query.json`` beside them, never over an earlier query's files (``_1``,
``_2``... or a name of the caller's).
"""
from __future__ import annotations

import json
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from diffuser_lab.backends import provenance
from diffuser_lab.data.frames import first_line
from diffuser_lab.data.scene import IGNORE
from diffuser_lab.method.metrics import score
from diffuser_lab.method.queries import Queries, labels_of_cosines, query_classes, query_labels
from diffuser_lab.method.space import BASIS_FILE, FEATURE_FILES, read_basis

from .records import load_npy, read_gt, write_json_atomic

__all__ = ["METHODS", "FEATURES", "RunFeatures", "QueryResult", "read_run", "query_run", "output_names", "table", "basis_line"]

METHODS = FEATURE_FILES
"""(key in query.json, file in the run folder, row of the table), in the table's order (the run's
label space writes them: :meth:`diffuser_lab.method.space.Features.write`)."""
FEATURES = METHODS[0][1]
"""The file that makes a folder a features run."""
_OUT_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")


@dataclass
class RunFeatures:
    """What a features run saved: ``features[key]`` (N, D) float16/32 memory maps (keys of
    :data:`METHODS` whose file exists), ``gt`` (N,) int or None, the taxonomy's ``class_names``."""

    run_dir: Path
    features: dict[str, np.ndarray]
    gt: Optional[np.ndarray]
    class_names: tuple[str, ...]
    taxonomy: str
    basis: dict = field(default_factory=lambda: {"kind": "full"})  # summary.json's features.basis
    run_queries: tuple[str, ...] = ()  # the run's own query set's names (summary.json's features.queries)
    vectors: Optional[np.ndarray] = None  # (D, k) a reduced basis' vectors: ``features`` are then BasisFeatures

    @property
    def n_points(self) -> int:
        return int(self.features["diffuser"].shape[0])

    @property
    def dim(self) -> int:
        return int(self.features["diffuser"].shape[1] if self.vectors is None else self.vectors.shape[0])

    def labels(self, key: str, queries: Queries, to_class, threshold: Optional[float], background: int) -> np.ndarray:
        """(N,) int16 the labels of method ``key``'s features (:func:`query_labels`; in a reduced basis:
        f.q from the coordinates, |f| estimated as the run did)."""
        f = self.features[key]
        if self.vectors is None:
            return query_labels(f, queries, to_class, threshold=threshold, background=background)
        q = queries.embeddings @ self.vectors  # (Q, k): a query's part in the basis
        return labels_of_cosines(f.cosines(q), to_class, threshold, background)


@dataclass
class QueryResult:
    """A query over a run: per method key, the (N,) int16 ``labels`` and the ``metrics`` (None
    without ground truth); ``to_class`` (Q,) the queries' class ids; ``files`` written."""

    run: RunFeatures
    queries: Queries
    to_class: np.ndarray
    threshold: Optional[float]
    background: int
    mapping: Optional[str]
    labels: dict[str, np.ndarray]
    metrics: dict[str, Optional[dict]]
    timings_s: dict[str, float] = field(default_factory=dict)
    files: dict[str, str] = field(default_factory=dict)

    def record(self) -> dict:
        """query.json's content."""
        names = self.run.class_names
        return {
            "queries": list(self.queries.names),
            "query_classes": [names[c] if c != IGNORE else None for c in self.to_class.tolist()],
            "source": self.queries.source,
            "dim": self.queries.dim,
            "threshold": self.threshold,
            "background": names[self.background] if self.background != IGNORE else None,
            "mapping": self.mapping,
            "taxonomy": self.run.taxonomy,
            "n_points": self.run.n_points,
            "n_unlabeled": {k: int((v == IGNORE).sum()) for k, v in self.labels.items()},
            "basis": self.run.basis,
            "outside_run_queries": [q for q in self.queries.names if q not in set(self.run.run_queries)],
            "metrics": self.metrics,
            "files": self.files,
            "timings_s": {k: round(v, 4) for k, v in self.timings_s.items()},
            "provenance": provenance.collect(),  # the relabelling's machine, maybe not the run's
        }


def read_run(run_dir: str | Path) -> RunFeatures:
    """The features, ground truth and class names a features run saved (features as memory maps).

    Raises:
        FileNotFoundError: no ``features.npy`` (not a features run) or no ``summary.json``.
        ValueError: one line naming the file: unreadable, ``summary.json`` without ``class_names``,
        features not (N, D) floats or of different shapes, ground truth not (N,) ids in IGNORE..C-1.
    """
    run_dir = Path(run_dir)
    for name in (FEATURES, "summary.json"):
        if not (run_dir / name).is_file():
            raise FileNotFoundError(f"{run_dir}: no {name}, expected the folder of a features run "
                                    f"(predictions=features)")
    path = run_dir / "summary.json"
    try:
        summary = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ValueError(f"{path}: unreadable ({type(exc).__name__}: {first_line(exc)})") from None
    names = summary.get("class_names") if isinstance(summary, dict) else None
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise ValueError(f"{path}: no 'class_names', expected the taxonomy's class names of a features run")
    features = {}
    for key, fname, _ in METHODS:
        if (run_dir / fname).is_file():
            f = load_npy(run_dir / fname)
            ref = features.get("diffuser")
            if f.ndim != 2 or f.dtype.kind != "f" or (ref is not None and f.shape != ref.shape):
                want = f"{ref.shape} as {FEATURES}" if ref is not None else "(N, D)"
                raise ValueError(f"{run_dir / fname}: shape {f.shape} dtype {f.dtype}, expected {want} floats")
            features[key] = f
    gt = read_gt(run_dir, features["diffuser"].shape[0], len(names))
    feats = summary.get("features") if isinstance(summary.get("features"), dict) else {}
    basis = feats.get("basis") if isinstance(feats.get("basis"), dict) else {"kind": "full"}
    vectors = None
    if (run_dir / BASIS_FILE).is_file():  # a reduced basis: every method's features from it
        vectors, features = read_basis(run_dir / BASIS_FILE, features["diffuser"].shape)
    return RunFeatures(run_dir, features, gt, tuple(names), str(summary.get("taxonomy", "")), basis,
                       tuple(str(q) for q in feats.get("queries") or ()), vectors)


def output_names(run_dir: str | Path, out: Optional[str] = None) -> tuple[Path, Path]:
    """(labels .npy, .json) paths of a new query in ``run_dir``: ``query_labels.npy`` and
    ``query.json``, else ``query_labels_1.npy`` / ``query_1.json``... the first pair not taken;
    with ``out``: ``query_labels_OUT.npy`` / ``query_OUT.json``.

    Raises:
        ValueError: ``out`` not a plain name, or its files exist.
    """
    run_dir = Path(run_dir)

    def pair(suffix: str) -> tuple[Path, Path]:
        return run_dir / f"query_labels{suffix}.npy", run_dir / f"query{suffix}.json"

    if out is not None:
        if not _OUT_NAME.fullmatch(out):
            raise ValueError(f"--out {out!r}: expected a plain name (letters, digits, _ . -)")
        p = pair(f"_{out}")
        if any(x.exists() for x in p):
            raise ValueError(f"--out {out}: {p[1].name} or {p[0].name} already in {run_dir}, expected a new name")
        return p
    i = 0
    while any(x.exists() for x in pair(f"_{i}" if i else "")):
        i += 1
    return pair(f"_{i}" if i else "")


def query_run(run_dir: str | Path | RunFeatures, queries: Queries, *, threshold: Optional[float] = None,
              background: int = IGNORE, mapping: Optional[str | Path] = None, out: Optional[str] = None,
              write: bool = True) -> QueryResult:
    """Label a features run's points with ``queries``, score them and (``write``) keep the labels.

    Args:
        run_dir: the run folder (or its :func:`read_run`).
        queries: the query set, of the features' D.
        threshold: a point whose best cosine is under it gets ``background``.
        background: a class id or IGNORE.
        mapping: a ``query,class`` CSV (:func:`diffuser_lab.method.queries.query_classes`).
        out: a name for the files (:func:`output_names`).
    Returns:
        the :class:`QueryResult`; ``query_labels*.npy`` (Diffuser's labels) and ``query*.json``
        written into the run folder.
    Raises:
        FileNotFoundError, ValueError: one line (:func:`read_run`, the queries' D against the
        features', :func:`query_classes`, :func:`output_names`).
    """
    t0 = time.perf_counter()
    run = run_dir if isinstance(run_dir, RunFeatures) else read_run(run_dir)
    if queries.dim != run.dim:
        raise ValueError(f"{queries.source}: embeddings of dimension {queries.dim}, expected {run.dim} "
                         f"(the features of {run.run_dir})")
    if not IGNORE <= int(background) < len(run.class_names):
        raise ValueError(f"background {background}: expected a class id 0..{len(run.class_names) - 1} or {IGNORE}")
    to_class = query_classes(queries.names, run.class_names, mapping)
    paths = output_names(run.run_dir, out) if write else None
    t1 = time.perf_counter()
    labels = {key: run.labels(key, queries, to_class, threshold, background) for key in run.features}
    t2 = time.perf_counter()
    metrics = {key: score(lab, run.gt, run.class_names) if run.gt is not None else None
               for key, lab in labels.items()}
    t3 = time.perf_counter()
    res = QueryResult(run, queries, to_class, threshold, int(background), None if mapping is None else str(mapping),
                      labels, metrics)
    res.timings_s = {"load": t1 - t0, "labels": t2 - t1, "metrics": t3 - t2}
    if paths is not None:
        np.save(paths[0], labels["diffuser"])
        res.files = {"labels": paths[0].name, "record": paths[1].name}
        res.timings_s["write"] = time.perf_counter() - t3
        res.timings_s["total"] = time.perf_counter() - t0
        write_json_atomic(paths[1], res.record())
    else:
        res.timings_s["total"] = time.perf_counter() - t0
    return res


def basis_line(basis: dict, outside: list[str]) -> Optional[str]:
    """One line on the run's reduced basis (summary.json's ``features.basis``; None for a full run):
    its dimension, the share of the evidence's energy it kept, and what that means for ``outside``
    (the queries not in the run's query set)."""
    if not basis or basis.get("kind") != "auto":
        return None
    pct = lambda x: "-" if x is None else f"{100 * x:.1f} %"  # noqa: E731
    err = basis.get("norm_error") or {}
    kept = basis.get("energy_features") or {}
    line = (f"features from a basis of {basis.get('dim')} of {basis.get('of')} dimensions (the run's "
            f"{basis.get('queries_span')} queries + {basis.get('principal')} principal directions): it kept "
            f"{pct(basis.get('energy_pixels'))} of the pixels' energy and ~{pct(kept.get('median'))} of a point's "
            f"diffused feature (median; |f| within {pct(err.get('median'))}, 95 % within {pct(err.get('p95'))})")
    if outside:
        line += (f"; {len(outside)} of these queries are not the run's: their cosines are those of the "
                 f"projection (what the basis did not keep is lost)")
    return line


def _fmt(x) -> str:
    return "-" if x is None else f"{x:.1f}"


def table(res: QueryResult) -> str:
    """The usual result table: a header line, mIoU / acc / cover per method (or a line saying there
    is no ground truth), the times and the files written."""
    run = res.run
    n_classes = len({c for c in res.to_class.tolist() if c != IGNORE})
    thr = "none" if res.threshold is None else f"{res.threshold:g}"
    lines = [f"diffuser-lab-query | run {run.run_dir.name} | {run.n_points:,} points x {run.dim} | "
             f"{len(res.queries)} queries -> {n_classes} classes | threshold {thr}"]
    rows = [(title, key) for key, _, title in METHODS if key in res.labels]
    if run.gt is None:
        for title, key in rows:
            lab = res.labels[key]
            lines.append(f"no ground truth: no mIoU; {title} labelled {int((lab != IGNORE).sum()):,} of "
                         f"{run.n_points:,} points")
    else:
        lines.append(f"{'':22s}{'mIoU':>7s}{'acc':>7s}{'cover':>7s}")
        for title, key in rows:
            m = res.metrics[key] or {}
            lines.append(f"{title:22s}{_fmt(m.get('miou')):>7s}{_fmt(m.get('accuracy')):>7s}"
                         f"{_fmt(m.get('coverage')):>7s}")
    line = basis_line(run.basis, [q for q in res.queries.names if q not in set(run.run_queries)])
    if line:
        lines.append(line)
    lines.append("time [s]  " + "  ".join(f"{k} {v:.2f}" for k, v in res.timings_s.items()))
    if res.files:
        lines.append(f"wrote {res.files['labels']}, {res.files['record']} in {run.run_dir}")
    return "\n".join(lines)
