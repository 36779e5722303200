"""Open-vocabulary queries over per-point features: cosine scores, argmax labels, a threshold.

A query set (:class:`Queries`) is names plus unit embeddings (Q, D) in the features' space, from a
file (:func:`diffuser_lab.data.embeddings.load_queries`) or a text encoder ``module.fn``. A point's
label is its most similar query's class (:func:`query_classes`: by name, or a ``query,class``
mapping file); a point no evidence reached (an all-zero feature row) stays unlabeled, and one whose
best cosine is under a threshold gets a background class (or stays unlabeled).

Features can be large (3M x 512 float16 = 3 GB, a memory map): :func:`similarity` and
:func:`query_labels` read them in row chunks (:data:`CHUNK_ELEMENTS`), never as a whole float32 copy.
"""
from __future__ import annotations

import csv
import importlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from diffuser_lab.data.embeddings import check_queries, load_queries
from diffuser_lab.data.frames import first_line
from diffuser_lab.data.scene import IGNORE

__all__ = ["Queries", "similarity", "query_labels", "labels_of_cosines", "query_classes", "load_encoder", "CHUNK_ELEMENTS"]

CHUNK_ELEMENTS = 1 << 22
"""Feature values converted to float32 at once (16 MB): 8192 rows at D = 512."""

_IGNORE_WORDS = {"", "ignore"}


@dataclass(frozen=True, eq=False)
class Queries:
    """A query set: ``names[q]`` and ``embeddings[q]`` ((Q, D) float32, unit rows, read-only;
    normalised on creation). ``source`` says where it came from, for messages and records."""

    names: tuple[str, ...]
    embeddings: np.ndarray
    source: str = field(default="<in-memory queries>", compare=False)

    def __post_init__(self):
        names, e = check_queries(self.names, self.embeddings, self.source)
        e = e / np.linalg.norm(e.astype(np.float64), axis=1, keepdims=True)
        e = np.ascontiguousarray(e, np.float32)
        e.flags.writeable = False
        object.__setattr__(self, "names", tuple(names))
        object.__setattr__(self, "embeddings", e)

    def __len__(self) -> int:
        return len(self.names)

    @property
    def dim(self) -> int:
        """D, the embedding dimension."""
        return int(self.embeddings.shape[1])

    @classmethod
    def from_file(cls, path: str | Path, dim: int | None = None) -> "Queries":
        """The query set of a ``.npz`` file (names, embeddings); ``dim``: the D it must have.
        Raises ValueError (one line naming the file) on a bad file."""
        names, e = load_queries(path, dim)
        return cls(tuple(names), e, source=str(path))

    @classmethod
    def from_encoder(cls, names: Sequence[str], target: str) -> "Queries":
        """The embeddings of ``names`` from a text encoder: ``target`` = ``module.fn`` importable,
        called as ``fn(list[str]) -> (Q, D)`` (numpy, or anything with ``.detach().cpu().numpy()``
        or ``__array__``).

        Raises:
            ValueError: one line naming ``target``: not ``module.fn``, the module does not import,
                no such function, not callable, it raised, or its output is not (Q, D).
        """
        fn = load_encoder(target)
        names = [str(n) for n in names]
        if not names:
            raise ValueError(f"encoder {target}: no names to encode, expected at least one")
        try:
            out = fn(list(names))
            if hasattr(out, "detach"):  # a torch tensor, possibly on a GPU
                out = out.detach().float().cpu().numpy()
            out = np.asarray(out, dtype=np.float32)
        except Exception as exc:  # noqa: BLE001 - the user's code: one line naming it
            raise ValueError(f"encoder {target} failed on {len(names)} names ({type(exc).__name__}: "
                             f"{first_line(exc)})") from None
        if out.ndim != 2 or out.shape[0] != len(names):
            raise ValueError(f"encoder {target} returned shape {out.shape}, expected ({len(names)}, D) for "
                             f"{len(names)} names")
        return cls(tuple(names), out, source=f"encoder {target}")


def load_encoder(target: str):
    """``module.fn`` -> the function, imported; ValueError (one line naming ``target``) when it is not
    ``module.fn``, the module does not import, has no such name, or it is not callable."""
    module, _, name = str(target).rpartition(".")
    if not module or not name:
        raise ValueError(f"encoder {target!r}: expected module.fn, e.g. diffuser_lab.data.embeddings.text_encoder")
    try:
        mod = importlib.import_module(module)
    except Exception as exc:  # noqa: BLE001 - ImportError or the module's own error
        raise ValueError(f"encoder {target}: module {module} does not import ({type(exc).__name__}: "
                         f"{first_line(exc)})") from None
    fn = getattr(mod, name, None)
    if fn is None:
        raise ValueError(f"encoder {target}: module {module} has no {name!r}")
    if not callable(fn):
        raise ValueError(f"encoder {target}: {type(fn).__name__}, expected a function fn(list[str]) -> (Q, D)")
    return fn


def _embeddings(queries: Queries | np.ndarray) -> np.ndarray:
    if isinstance(queries, Queries):
        return queries.embeddings
    return Queries(tuple(f"q{i}" for i in range(len(queries))), np.asarray(queries)).embeddings


def _chunks(features: np.ndarray, E: np.ndarray) -> Iterator[tuple[slice, np.ndarray, np.ndarray]]:
    """(rows, (n, Q) float32 cosines, (n,) bool: the row has a finite non-zero feature) per chunk of
    rows; the cosines of the other rows are undefined."""
    if features.ndim != 2 or features.shape[1] != E.shape[1]:
        raise ValueError(f"features of shape {features.shape}, expected (N, {E.shape[1]}) (the queries' D)")
    step = max(1, CHUNK_ELEMENTS // max(features.shape[1], 1))
    Et = np.ascontiguousarray(E.T, np.float32)
    for start in range(0, features.shape[0], step):
        rows = slice(start, min(start + step, features.shape[0]))
        x = np.asarray(features[rows], dtype=np.float32)
        norm = np.sqrt(np.einsum("ij,ij->i", x, x))
        ok = np.isfinite(norm) & (norm > 0)
        if not ok.all():  # never write into the caller's array (a float32 input is not copied)
            x = np.where(ok[:, None], x, np.float32(0))
        sim = x @ Et
        sim *= np.divide(1.0, norm, out=np.zeros_like(norm), where=ok)[:, None]
        yield rows, sim, ok


def similarity(features: np.ndarray, queries: Queries | np.ndarray) -> np.ndarray:
    """Cosine similarity of every point's feature with every query.

    Args:
        features: (N, D) float16/float32 (a memory map works: read in chunks of rows, never
            converted whole).
        queries: a :class:`Queries` or (Q, D) embeddings.
    Returns:
        (N, Q) float32 cosines; NaN rows where a feature row is all zero (nothing reached the point)
        or not finite.
    Raises:
        ValueError: features not (N, D) with the queries' D.
    """
    E = _embeddings(queries)
    out = np.empty((features.shape[0], E.shape[0]), np.float32)
    for rows, sim, ok in _chunks(features, E):
        sim[~ok] = np.nan
        out[rows] = sim
    return out


def query_labels(features: np.ndarray, queries: Queries | np.ndarray, to_class, *, threshold: float | None = None,
                 background: int = IGNORE) -> np.ndarray:
    """Per point, the class of its most similar query.

    Args:
        features: (N, D) float16/float32 per-point features (read in chunks).
        queries: a :class:`Queries` or (Q, D) embeddings.
        to_class: (Q,) int, the class id of each query (:func:`query_classes`); IGNORE for a query
            that stands for no class (a point matching it best stays unlabeled).
        threshold: when given, a point whose best cosine is under it gets ``background``.
        background: a class id, or IGNORE (unlabeled).
    Returns:
        (N,) int16: the best query's class; IGNORE where the feature row is all zero (nothing
        reached the point) or not finite.
    """
    E = _embeddings(queries)
    lut = _class_lut(to_class, E.shape[0], background)
    out = np.full(features.shape[0], IGNORE, np.int16)
    for rows, sim, ok in _chunks(features, E):
        out[rows] = _labels(sim, ok, lut, threshold, background)
    return out


def labels_of_cosines(cos: np.ndarray, to_class, threshold: float | None = None, background: int = IGNORE) -> np.ndarray:
    """:func:`query_labels` from (N, Q) cosines already computed (NaN rows: no feature; e.g. a
    reduced basis' :meth:`~diffuser_lab.method.basis.BasisFeatures.cosines`) -> (N,) int16."""
    lut = _class_lut(to_class, cos.shape[1], background)
    ok = np.isfinite(cos).all(1)
    return _labels(np.where(ok[:, None], cos, np.float32(0)), ok, lut, threshold, background)


def _class_lut(to_class, n_queries: int, background: int) -> np.ndarray:
    lut = np.asarray(to_class)
    if lut.shape != (n_queries,) or lut.dtype.kind not in "iu" or (lut.size and lut.min() < IGNORE):
        raise ValueError(f"to_class of shape {lut.shape} dtype {lut.dtype}, expected ({n_queries},) class ids "
                         f">= {IGNORE}, one per query")
    if int(background) < IGNORE:
        raise ValueError(f"background {background}: expected a class id or {IGNORE} (unlabeled)")
    return lut.astype(np.int16)


def _labels(sim: np.ndarray, ok: np.ndarray, lut: np.ndarray, threshold, background) -> np.ndarray:
    """(n, Q) cosines, (n,) rows with a feature -> (n,) int16 the best query's class (the rule of
    :func:`query_labels`)."""
    best = sim.argmax(1)
    lab = lut[best]
    if threshold is not None:
        lab[sim[np.arange(len(best)), best] < threshold] = background
    lab[~ok] = IGNORE
    return lab


def query_classes(query_names: Sequence[str], class_names: Sequence[str],
                  mapping: str | Path | None = None) -> np.ndarray:
    """The class id of each query: the class of equal name (case-insensitive, spaces at the ends
    ignored), or the one a mapping file names.

    Args:
        query_names: (Q,) query names.
        class_names: (C,) the taxonomy's class names in id order.
        mapping: a CSV file of ``query,class`` lines (an optional header ``query,class``, ``#``
            comment lines); ``class`` empty or ``ignore`` = no class (IGNORE). Queries it does not
            list are matched by name.
    Returns:
        (Q,) int64 class ids (IGNORE for a query mapped to no class).
    Raises:
        ValueError: one line: a query that is no class name and not mapped, a mapping line naming an
        unknown query or class, a malformed line.
    """
    index = {n.strip().lower(): i for i, n in enumerate(class_names)}
    queries: dict[str, list[int]] = {}
    for q, n in enumerate(query_names):
        queries.setdefault(n.strip().lower(), []).append(q)
    out = np.full(len(query_names), -2, np.int64)
    if mapping is not None:
        for line, query, cls in _mapping_rows(Path(mapping)):
            where = f"{mapping} line {line}"
            qs = queries.get(query.strip().lower())
            if qs is None:
                raise ValueError(f"{where}: query {query!r} is not in the query set ({_some(query_names)})")
            if (out[qs] != -2).any():
                raise ValueError(f"{where}: query {query!r} mapped twice, expected one line a query")
            c = cls.strip().lower()
            if c not in _IGNORE_WORDS and c not in index:
                raise ValueError(f"{where}: class {cls!r} is not in the taxonomy ({_some(class_names)}), expected a "
                                 f"class name or 'ignore'")
            out[qs] = IGNORE if c in _IGNORE_WORDS else index[c]
    for q, name in enumerate(query_names):
        if out[q] != -2:
            continue
        c = index.get(name.strip().lower())
        if c is None:
            hint = f"and {mapping} does not map it" if mapping is not None else "and no mapping file is given"
            raise ValueError(f"query {name!r} is not a class of the taxonomy ({_some(class_names)}) {hint}: "
                             f"expected a mapping line '{name},CLASS'")
        out[q] = c
    return out


def _some(names: Sequence[str], n: int = 8) -> str:
    names = list(names)
    return ", ".join(names[:n]) + (f", ... {len(names)} in all" if len(names) > n else "")


def _mapping_rows(path: Path) -> Iterator[tuple[int, str, str]]:
    """(line number, query, class) of a ``query,class`` mapping file."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: unreadable ({type(exc).__name__}: {first_line(exc)}), expected a CSV file of "
                         f"'query,class' lines") from None
    first = True
    for i, row in enumerate(csv.reader(text.splitlines()), start=1):
        if not row or not "".join(row).strip() or row[0].lstrip().startswith("#"):
            continue
        if first and [c.strip().lower() for c in row] == ["query", "class"]:
            first = False
            continue
        first = False
        if len(row) != 2:
            raise ValueError(f"{path} line {i}: {len(row)} fields ({','.join(row)!r}), expected 'query,class'")
        yield i, row[0], row[1]
