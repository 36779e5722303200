"""Taxonomies: the shipped class sets, taxonomy files, and one inferred from the data's ids.

A taxonomy file is a CSV (``#`` starts a comment line) with the header ``id,name`` or
``id,name,r,g,b``, one row per class; ``id`` is the class's label id in the data (label
images, PLY ``label``), ``name`` its name (unique, case-insensitive), ``r,g,b`` its colour
(0..255; generated when absent). Comment lines ``# name: X`` (the taxonomy's name; default:
the file's stem) and ``# ignore: 0 255`` (label ids that mean "no label") are read as keys.
A YAML file says the same::

    name: my_classes            # optional
    ignore: [0]                 # optional
    classes:                    # a list of {id, name, color: [r, g, b] (optional)} ...
      - {id: 1, name: wall, color: [174, 199, 232]}
      - {id: 2, name: floor}
    # ... or a mapping id -> name:  classes: {1: wall, 2: floor}

Class ids inside diffuser-lab are always 0..C-1 (row order); :func:`~diffuser_lab.data.mapping.native_mapping`
turns the data's label ids into them where no mapping file is given.
"""
from __future__ import annotations

import colorsys
import csv
import warnings
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from diffuser_lab.config import SPECIAL_TAXONOMIES

from . import inputs, predictions, sources
from .scene import Taxonomy

__all__ = ["TAXONOMIES_DIR", "shipped_taxonomies", "taxonomy_names", "load_taxonomy", "resolve_taxonomy", "generated_colors", "ids_taxonomy",
           "taxonomy_from_rows"]

TAXONOMIES_DIR = Path(__file__).resolve().parent / "taxonomies"
_CACHE: dict[str, Taxonomy] = {}


def shipped_taxonomies() -> list[str]:
    """Names of the taxonomy CSVs shipped with the package (``taxonomy=<name>``)."""
    return sorted(p.stem for p in TAXONOMIES_DIR.glob("*.csv"))


def taxonomy_names() -> list[str]:
    """The names ``taxonomy.name`` takes: the shipped taxonomies, then ``file`` and ``ids``."""
    return shipped_taxonomies() + list(SPECIAL_TAXONOMIES)


def generated_colors(n: int) -> np.ndarray:
    """(n, 3) uint8 distinct colours, the same for the same n: golden-ratio hue steps over three
    lightness/saturation levels (neighbouring ids differ in hue and brightness)."""
    levels = [(0.5, 0.75), (0.38, 0.85), (0.65, 0.6)]
    out = [colorsys.hls_to_rgb((i * 0.6180339887498949) % 1.0, *levels[i % 3]) for i in range(n)]
    return np.round(np.asarray(out, np.float64).reshape(-1, 3) * 255).astype(np.uint8)


def taxonomy_from_rows(name: str, rows: Sequence[tuple[int, str, tuple | None]], ignore: Iterable[int] = (),
                       where: str = "<rows>") -> Taxonomy:
    """(id, name, colour or None) rows -> :class:`Taxonomy`; missing colours are generated.
    Raises ValueError naming ``where`` for duplicate ids or names, bad colours or an empty table."""
    if not rows:
        raise ValueError(f"{where}: no classes (expected one row per class: id,name[,r,g,b])")
    ids = [int(r[0]) for r in rows]
    names = [str(r[1]).strip() for r in rows]
    for what, vals in (("id", ids), ("name", [n.lower() for n in names])):
        seen: set = set()
        dup = [v for v in vals if v in seen or seen.add(v)]
        if dup:
            raise ValueError(f"{where}: duplicate class {what} {dup[0]!r}")
    if min(ids) < 0 or max(ids) > (1 << 20):
        raise ValueError(f"{where}: class ids in [{min(ids)}, {max(ids)}], expected 0..{1 << 20}")
    if any(not n for n in names):
        raise ValueError(f"{where}: empty class name for id {ids[names.index('')]}")
    ignore = tuple(sorted({int(i) for i in ignore}))
    clash = sorted(set(ignore) & set(ids))
    if clash:
        raise ValueError(f"{where}: ignore ids {clash} are also class ids")
    colors = generated_colors(len(rows))
    for i, r in enumerate(rows):
        c = r[2] if len(r) > 2 else None
        if c is None:
            continue
        c = np.asarray(c)
        if c.shape != (3,) or not np.issubdtype(c.dtype, np.number) or c.min() < 0 or c.max() > 255:
            raise ValueError(f"{where}: colour {r[2]!r} of class {names[i]!r}, expected three values in 0..255")
        colors[i] = c.astype(np.uint8)
    plain = ids == list(range(len(ids)))
    return Taxonomy(name=name, names=tuple(names), colors=colors, ids=None if plain else tuple(ids),
                    ignore_ids=ignore)


def _read_csv(path: Path) -> Taxonomy:
    keys: dict[str, str] = {}
    rows: list[tuple] = []
    header = None
    lines = inputs.read_bytes(path, "taxonomy").decode("utf-8").splitlines()
    for lineno, line in enumerate(lines, start=1):  # loop over table rows (tens to hundreds)
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            key, sep, val = s[1:].partition(":")
            if sep and key.strip().lower() in ("name", "ignore"):
                keys[key.strip().lower()] = val.strip()
            continue
        fields = [x.strip() for x in next(csv.reader([line]))]
        if header is None:
            header = [x.lower() for x in fields]
            if header not in (["id", "name"], ["id", "name", "r", "g", "b"]):
                raise ValueError(f"{path}:{lineno}: header {','.join(fields)!r}, expected 'id,name' or 'id,name,r,g,b'")
            continue
        if len(fields) != len(header):
            raise ValueError(f"{path}:{lineno}: row {line!r} has {len(fields)} fields, expected {len(header)} "
                             f"({','.join(header)})")
        try:
            cid = int(fields[0])
            color = tuple(int(x) for x in fields[2:5]) if len(fields) == 5 else None
        except ValueError:
            raise ValueError(f"{path}:{lineno}: row {line!r}: id and r,g,b must be integers") from None
        rows.append((cid, fields[1], color))
    try:
        ignore = [int(x) for x in keys.get("ignore", "").replace(",", " ").split()]
    except ValueError:
        raise ValueError(f"{path}: '# ignore: {keys['ignore']}' must list integer label ids") from None
    return taxonomy_from_rows(keys.get("name") or path.stem, rows, ignore, where=str(path))


def _read_yaml(path: Path) -> Taxonomy:
    import yaml

    try:
        doc = yaml.safe_load(inputs.read_bytes(path, "taxonomy").decode("utf-8"))
    except yaml.YAMLError as e:
        raise ValueError(f"{path}: not valid YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(doc, dict) or "classes" not in doc:
        raise ValueError(f"{path}: expected a mapping with a 'classes' key (a list of {{id, name, color}} "
                         f"or a mapping id -> name)")
    classes = doc["classes"]
    rows: list[tuple] = []
    try:
        if isinstance(classes, dict):
            rows = [(int(k), str(v), None) for k, v in classes.items()]
        elif isinstance(classes, list):
            rows = [(int(c["id"]), str(c["name"]), c.get("color")) for c in classes]
        else:
            raise TypeError
    except (TypeError, KeyError, ValueError):
        raise ValueError(f"{path}: 'classes' must be a list of {{id: int, name: str, color: [r, g, b]}} "
                         f"or a mapping id -> name") from None
    ignore = doc.get("ignore") or []
    if not isinstance(ignore, list) or not all(isinstance(i, int) for i in ignore):
        raise ValueError(f"{path}: 'ignore' must be a list of integer label ids, got {ignore!r}")
    return taxonomy_from_rows(str(doc.get("name") or path.stem), rows, ignore, where=str(path))


def load_taxonomy(name_or_path: str | Path) -> Taxonomy:
    """A shipped taxonomy by name (``nyu40``) or a CSV / YAML file (module docstring).

    Raises:
        FileNotFoundError: unknown name or missing file (naming the shipped ones).
        ValueError: malformed file (line number and what was expected).
    """
    s = str(name_or_path)
    p = Path(s)
    if isinstance(name_or_path, Path) or p.suffix.lower() in (".csv", ".yaml", ".yml") or "/" in s or "\\" in s:
        if not p.is_file():
            raise FileNotFoundError(f"taxonomy file {p} does not exist")
        return _read_yaml(p) if p.suffix.lower() in (".yaml", ".yml") else _read_csv(p)
    if s not in _CACHE:
        shipped = TAXONOMIES_DIR / f"{s}.csv"
        if not shipped.is_file():
            raise FileNotFoundError(f"no shipped taxonomy named {s!r}; shipped: {', '.join(shipped_taxonomies())} "
                                    f"(or taxonomy=file taxonomy.path=FILE.csv|.yaml)")
        _CACHE[s] = _read_csv(shipped)
    else:  # read by an earlier run of this process: this run read it too
        inputs.record(TAXONOMIES_DIR / f"{s}.csv", "taxonomy")
    return _CACHE[s]


def ids_taxonomy(ids: np.ndarray, where: str) -> Taxonomy:
    """The label ids found in the data (``where`` says where) as classes ``class_<id>``, with a
    warning that their names and colours are made up."""
    ids = np.unique(np.asarray(ids, np.int64))
    if ids.size == 0:
        raise ValueError(f"taxonomy=ids: no label ids found in {where}")
    if ids.size > 4096:
        raise ValueError(f"taxonomy=ids: {ids.size} distinct label ids in {where}; these look like instance "
                         f"ids or depth, not classes (give taxonomy=file taxonomy.path=...)")
    shown = ", ".join(map(str, ids[:8])) + (" ..." if ids.size > 8 else "")
    warnings.warn(f"taxonomy=ids: {ids.size} classes class_<id> for the label ids [{shown}] found in {where}; "
                  f"names and colours are made up (taxonomy=file taxonomy.path=... names them)", stacklevel=2)
    return taxonomy_from_rows("ids", [(int(i), f"class_{i}", None) for i in ids], where=where)


def _scan_ids(cfg) -> tuple[np.ndarray, str]:
    """The label ids in the label images a run with ``cfg`` (a :class:`~diffuser_lab.config.Config`) reads:
    those of its prediction source (predictions=files: the first ``taxonomy.scan_frames`` label images
    of predictions.folder, name order), then those of its scene source's ground truth (the first label
    images of rgbd_folder (label_suffix) / scannet (label-filt/), the PLY labels of scannet /
    mesh_views): each registry entry's ``label_ids``. Returns (unique ids, where they were found)."""
    n = cfg.taxonomy.scan_frames
    found: list[tuple[np.ndarray, str]] = []
    for entry, keys in ((predictions.get(cfg.predictions.source), cfg.predictions),
                        (sources.get(cfg.scene.source), cfg.scene)):
        if entry.label_ids is not None:
            found += entry.label_ids(keys, n)
    if not found:
        raise ValueError("taxonomy=ids: no label images to take the classes from (predictions=files with label "
                         "images in predictions.folder, or a scene source with ground-truth label images / "
                         "PLY labels); give taxonomy=<name> or taxonomy=file taxonomy.path=...")
    return np.unique(np.concatenate([ids for ids, _ in found])), " and ".join(where for _, where in found)


def resolve_taxonomy(cfg) -> Taxonomy:
    """The run's taxonomy from ``cfg.taxonomy`` (a shipped name, ``file`` or ``ids``)."""
    t = cfg.taxonomy
    if t.name == "file":
        return load_taxonomy(Path(t.path))
    if t.name == "ids":
        ids, where = _scan_ids(cfg)
        return ids_taxonomy(ids, where)
    return load_taxonomy(t.name)
