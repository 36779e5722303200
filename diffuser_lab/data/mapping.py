"""Class mappings: a network's / dataset's integer class ids -> an evaluation Taxonomy.

A mapping is a CSV file (``#`` starts a comment line) with the header
``source_id,source_name,target``: one row per source id, ``target`` is the NAME of a
class of the target :class:`~diffuser_lab.data.scene.Taxonomy` (case-insensitive), or empty /
``ignore`` for source classes that the evaluation does not use. Comment lines
``# source: <taxonomy>`` and ``# target: <taxonomy>`` state the two label spaces (optional;
when ``target`` is given, :func:`load_mapping` refuses a run taxonomy of another name). Any
taxonomy can be the target (:mod:`diffuser_lab.data.taxonomy`); the shipped mappings live in
``diffuser_lab/data/mappings/`` and are loaded by bare name, e.g.
``load_mapping("nyu40_to_scannet20", SCANNET20)``.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import inputs
from .scene import IGNORE, Taxonomy

__all__ = ["ClassMapping", "load_mapping", "identity_mapping", "native_mapping", "mapping_header",
           "shipped_mappings", "MAPPINGS_DIR"]

MAPPINGS_DIR = Path(__file__).resolve().parent / "mappings"
_HEADER = ["source_id", "source_name", "target"]
_IGNORE_WORDS = {"", "ignore"}


_OUTSIDE = np.int16(-32768)  # apply()'s fast table: an id the table does not list


@dataclass
class ClassMapping:
    """Lookup table from source class ids to target class ids.

    Attributes:
        lut: (S,) int16, ``lut[s]`` = target class id (0..C-1) of source id s, IGNORE
            when s is unmapped or not listed in the table.
        source_names: (S,) tuple, name of source id s, or None where s is not listed
            (ids not listed are "outside the table": :meth:`apply` refuses them).
        target: the evaluation taxonomy the ids in ``lut`` refer to.
        source: where the table came from (file path or a description), for messages.
        source_taxonomy: name of the source label space, when the file states it.
    """

    lut: np.ndarray
    source_names: tuple
    target: Taxonomy
    source: str = "<in-memory mapping>"
    source_taxonomy: str | None = None  # the file's "# source:" key, if any
    known: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        self.lut = np.asarray(self.lut, np.int16)
        if self.lut.ndim != 1 or len(self.source_names) != len(self.lut):
            raise ValueError(f"{self.source}: lut of shape {self.lut.shape} and {len(self.source_names)} "
                             f"source names, expected one name per lut entry")
        bad = (self.lut != IGNORE) & ((self.lut < 0) | (self.lut >= self.target.num_classes))
        if bad.any():
            raise ValueError(f"{self.source}: target ids {np.unique(self.lut[bad]).tolist()} outside "
                             f"0..{self.target.num_classes - 1} of taxonomy {self.target.name}")
        self.known = np.array([n is not None for n in self.source_names], bool)

    def _table(self, dtype) -> np.ndarray:
        """The lookup over every value of a small unsigned ``dtype``: target id, IGNORE, or
        ``_OUTSIDE`` for an id the table does not list (built once per dtype)."""
        key = np.dtype(dtype).str
        cache = self.__dict__.setdefault("_tables", {})
        if key not in cache:
            t = np.full(np.iinfo(dtype).max + 1, _OUTSIDE, np.int16)
            n = min(self.num_source, t.size)
            t[:n] = np.where(self.known[:n], self.lut[:n], _OUTSIDE)
            cache[key] = t
        return cache[key]

    @property
    def num_source(self) -> int:
        """Size S of the table (largest listed source id + 1)."""
        return int(self.lut.shape[0])

    def apply(self, ids: np.ndarray) -> tuple[np.ndarray, int]:
        """Map source ids (any shape, integer dtype) to target class ids.

        Returns:
            mapped: int16 array of the same shape (IGNORE for unmapped source classes);
            n_unmapped: number of elements whose source class is listed but unmapped.
        Raises:
            ValueError: ids not in the table (negative, >= S, or not listed), naming them.
        """
        ids = np.asarray(ids)
        if ids.dtype.kind not in "iub":
            raise ValueError(f"{self.source}: class ids must be integers, got dtype {ids.dtype}")
        if ids.dtype in (np.uint8, np.uint16) and ids.size:  # label images as stored: one gather per pixel
            table = self._table(ids.dtype)
            mapped = table[ids]
            if not (mapped == _OUTSIDE).any():
                return mapped, int(np.count_nonzero(mapped == IGNORE))
        flat = ids.reshape(-1).astype(np.int64)
        inside = (flat >= 0) & (flat < self.num_source)
        safe = np.where(inside, flat, 0)
        listed = inside & self.known[safe]
        if not listed.all():
            bad = np.unique(flat[~listed])
            shown = ", ".join(str(b) for b in bad[:10]) + (" ..." if bad.size > 10 else "")
            raise ValueError(f"class ids [{shown}] ({int((~listed).sum())} elements) are not in mapping "
                             f"{self.source} (it lists ids {self._listed_range()})")
        mapped = self.lut[safe]
        n_unmapped = int(np.count_nonzero(mapped == IGNORE))
        return mapped.reshape(ids.shape), n_unmapped

    def _listed_range(self) -> str:
        listed = np.flatnonzero(self.known)
        if listed.size == listed[-1] - listed[0] + 1:
            return f"{listed[0]}..{listed[-1]}"
        return f"{listed.size} ids in {listed[0]}..{listed[-1]} with gaps"


def shipped_mappings() -> list[str]:
    """Names of the mapping CSVs shipped with the package (usable by bare name)."""
    return sorted(p.stem for p in MAPPINGS_DIR.glob("*.csv"))


def _resolve(name_or_path: str | Path) -> Path:
    """A bare name -> the shipped CSV; anything path-like (separator, suffix, existing file) -> itself."""
    s = str(name_or_path)
    p = Path(s)
    if p.is_file() or "/" in s or "\\" in s or p.suffix:
        if not p.is_file():
            raise FileNotFoundError(f"class mapping file {p} does not exist")
        return p
    shipped = MAPPINGS_DIR / f"{s}.csv"
    if not shipped.is_file():
        raise FileNotFoundError(f"no shipped class mapping named {s!r}; shipped: {', '.join(shipped_mappings())} "
                                f"(or give a path to a CSV)")
    return shipped


def load_mapping(name_or_path: str | Path, target: Taxonomy) -> ClassMapping:
    """Read a mapping CSV (see module docstring) for the ``target`` taxonomy.

    Args:
        name_or_path: a shipped mapping's bare name (``nyu40_to_scannet20``) or a CSV path.
        target: evaluation taxonomy whose class names the ``target`` column uses.
    Raises:
        FileNotFoundError: unknown name / missing file.
        ValueError: bad header, malformed row (line number given), duplicate source id,
            unknown target class name.
    """
    path = _resolve(name_or_path)
    keys = mapping_header(path)
    declared = keys.get("target")
    if declared and declared.lower() != target.name.lower():
        raise ValueError(f"class mapping {path} targets taxonomy {declared} (its '# target:' line), but the run's "
                         f"taxonomy is {target.name}: give a mapping to {target.name}, none (mapping=null: the ids are its own), or taxonomy={declared}")
    by_name = {n.lower(): i for i, n in enumerate(target.names)}
    rows: dict[int, tuple[str, int]] = {}
    header_seen = False
    lines = inputs.read_bytes(path, "mapping").decode("utf-8").splitlines()
    for lineno, line in enumerate(lines, start=1):  # loop over table rows (tens to hundreds)
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = [x.strip() for x in next(csv.reader([line]))]
        if not header_seen:
            if [x.lower() for x in fields] != _HEADER:
                raise ValueError(f"{path}:{lineno}: header {','.join(fields)!r}, expected {','.join(_HEADER)!r}")
            header_seen = True
            continue
        if len(fields) != 3:
            raise ValueError(f"{path}:{lineno}: malformed row {line!r}, expected 3 fields source_id,source_name,target")
        sid_txt, sname, tname = fields
        try:
            sid = int(sid_txt)
        except ValueError:
            sid = -1
        if sid < 0 or sid > np.iinfo(np.int32).max:
            raise ValueError(f"{path}:{lineno}: source_id {sid_txt!r} is not a non-negative integer")
        if sid in rows:
            raise ValueError(f"{path}:{lineno}: duplicate source_id {sid} (first given for {rows[sid][0]!r})")
        if tname.lower() in _IGNORE_WORDS:
            tid = IGNORE
        elif tname.lower() in by_name:
            tid = by_name[tname.lower()]
        else:
            raise ValueError(f"{path}:{lineno}: unknown target class {tname!r} for taxonomy {target.name} "
                             f"(valid: {', '.join(target.names[:6])}, ... or ignore)")
        rows[sid] = (sname, tid)
    if not rows:
        raise ValueError(f"{path}: no mapping rows (expected header {','.join(_HEADER)} and one row per source id)")
    size = max(rows) + 1
    if size > 1 << 20:
        raise ValueError(f"{path}: largest source_id {size - 1} is too large for a lookup table (max {1 << 20})")
    lut = np.full(size, IGNORE, np.int16)
    names: list[str | None] = [None] * size
    ids = np.fromiter(rows.keys(), np.int64, len(rows))
    lut[ids] = np.fromiter((t for _, t in rows.values()), np.int16, len(rows))
    for sid, (sname, _) in rows.items():
        names[sid] = sname
    return ClassMapping(lut=lut, source_names=tuple(names), target=target, source=str(path),
                        source_taxonomy=keys.get("source"))


def mapping_header(name_or_path: str | Path) -> dict[str, str]:
    """The ``# source: X`` / ``# target: Y`` comment keys of a mapping file (lower-case keys)."""
    keys: dict[str, str] = {}
    with open(_resolve(name_or_path), encoding="utf-8") as f:
        for line in f:  # the comment lines before the header row
            s = line.strip()
            if s and not s.startswith("#"):
                break
            key, sep, val = s[1:].partition(":")
            if sep and key.strip().lower() in ("source", "target") and val.strip():
                keys[key.strip().lower()] = val.strip()
    return keys


def identity_mapping(taxonomy: Taxonomy) -> ClassMapping:
    """Source ids already are ``taxonomy`` class ids 0..C-1 (others are refused by apply)."""
    n = taxonomy.num_classes
    return ClassMapping(lut=np.arange(n, dtype=np.int16), source_names=tuple(taxonomy.names),
                        target=taxonomy, source=f"identity({taxonomy.name})")


def native_mapping(taxonomy: Taxonomy) -> ClassMapping | None:
    """The data's own label ids of ``taxonomy`` (``taxonomy.ids``, ``taxonomy.ignore_ids`` -> IGNORE)
    -> class ids 0..C-1; None when the ids already are 0..C-1 with no ignore ids (used as they are)."""
    if taxonomy.ids is None and not taxonomy.ignore_ids:
        return None
    ids = np.arange(taxonomy.num_classes) if taxonomy.ids is None else np.asarray(taxonomy.ids, np.int64)
    size = int(max(ids.max(), max(taxonomy.ignore_ids, default=0))) + 1
    lut = np.full(size, IGNORE, np.int16)
    lut[ids] = np.arange(taxonomy.num_classes, dtype=np.int16)
    names: list[str | None] = [None] * size
    for i, n in zip(ids.tolist(), taxonomy.names):
        names[i] = n
    for i in taxonomy.ignore_ids:
        names[i] = "ignore"
    return ClassMapping(lut=lut, source_names=tuple(names), target=taxonomy,
                        source=f"{taxonomy.name} label ids", source_taxonomy=taxonomy.name)


def relabel_scene(scene, taxonomy: Taxonomy):
    """``scene`` (a :class:`~diffuser_lab.data.scene.Scene` with in-memory frames, e.g. the demo room)
    with its ground truth moved to ``taxonomy`` by the shipped mapping ``<scene taxonomy>_to_<taxonomy>``.
    Raises ValueError when no such mapping is shipped."""
    import dataclasses

    name = f"{scene.taxonomy.name}_to_{taxonomy.name}"
    if name not in shipped_mappings():
        raise ValueError(f"scene {scene.name} is labelled in {scene.taxonomy.name} and no shipped mapping {name} "
                         f"moves it to taxonomy={taxonomy.name} (shipped: {', '.join(shipped_mappings())})")
    table = load_mapping(name, taxonomy)

    def move(ids):
        if ids is None:
            return None
        return np.where(ids == IGNORE, IGNORE, table.lut[np.maximum(ids, 0)]).astype(np.int16)

    frames = [dataclasses.replace(f, gt_labels=move(f.gt_labels)) for f in scene.frames]
    return dataclasses.replace(scene, taxonomy=taxonomy, frames=frames, gt_labels=move(scene.gt_labels))
