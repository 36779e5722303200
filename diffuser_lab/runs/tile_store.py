"""A tiled run's store (``protocol=tiled``, docs/tiling.md): ``tiles/<ix>_<iy>.npz``, each tile's labels,
a checksum of its points, its record and (a features run) its features, written atomically
(:func:`write_tile`) and read back only when complete (:func:`read_tile`); the config's fingerprint
that lets a run resume another's tiles (``tiling.resume``: :func:`tiles_dir`, :func:`check_fingerprint`,
:func:`finished`); the tiles' files put together into the scene's labels (:func:`assemble`: a features
run's ``features.npy`` too, a point its tile left unlabelled from a neighbour's halo, :func:`fill_from_halos`)."""
from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import os
import zlib
from pathlib import Path
from typing import Optional

import numpy as np

from diffuser_lab.config import Config
from diffuser_lab.data.scene import IGNORE
from diffuser_lab.method.space import TILE_FEATURES, TileFeatures

from .records import config_yaml, write_json_atomic
from .tile_geometry import TileSpec

__all__ = ["TILES", "INPUTS", "write_tile", "read_tile", "fill_from_halos", "fingerprint", "tiles_dir",
           "check_fingerprint", "finished", "assemble"]

TILES = "tiles"
"""The run folder's sub-folder of tile files."""
INPUTS = "inputs"
"""``tiles/inputs/<id>.npz``: a Ray tile's points (:class:`~diffuser_lab.runs.tile_geometry.TileInput`), removed once the tile is done."""


def _crc(own: np.ndarray) -> int:
    return zlib.crc32(np.ascontiguousarray(own, np.int64).tobytes())


def write_tile(tiles_dir: Path, spec: TileSpec, own: np.ndarray, labels: np.ndarray, bayes: np.ndarray,
               rec: dict, features: Optional[dict] = None,
               halo: Optional[tuple[np.ndarray, np.ndarray]] = None) -> Path:
    """``tiles/<id>.npz`` through a temporary file and os.replace (never half-written under its name);
    a features run's tile also keeps its points' features (``features``:
    :meth:`~diffuser_lab.method.space.Features.tile_features`), every tile its halo's labelled points."""
    path = Path(tiles_dir) / f"{spec.id}.npz"
    buf = io.BytesIO()
    extra = dict(features or {})
    if halo is not None:
        extra.update(halo_index=halo[0], halo_labels=halo[1])
    np.savez(buf, labels=labels.astype(np.int16), bayesian=bayes.astype(np.int16), crc=np.int64(_crc(own)),
             record=np.array(json.dumps(rec)), **extra)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as fh:
        fh.write(buf.getvalue())
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    return path


def read_tile(tiles_dir: Path, spec: TileSpec, own: np.ndarray, features: bool = False, halo: bool = False
              ) -> Optional[tuple[np.ndarray, np.ndarray, dict, Optional[dict], Optional[tuple]]]:
    """A tile's finished file (labels, Bayesian labels, record, with ``features`` a features
    run's features (:func:`write_tile`'s dict) or None, and with ``halo`` its halo's labelled points
    (indices, labels) or None in a file without them), or None when it is missing or not complete
    (unreadable, another shape, another set of points)."""
    path = Path(tiles_dir) / f"{spec.id}.npz"
    if not path.is_file():
        return None
    try:
        with np.load(path) as z:
            labels, bayes, crc, rec = z["labels"], z["bayesian"], int(z["crc"]), json.loads(str(z["record"]))
            stored = ({k: z[k] for k in TILE_FEATURES if k in z.files} or None) if features else None
            halo = (z["halo_index"], z["halo_labels"]) if halo and "halo_index" in z.files else None
    except Exception:  # noqa: BLE001 - a truncated or foreign file: the tile is computed again
        return None
    if labels.shape != (own.size,) or bayes.shape != (own.size,) or crc != _crc(own):
        return None
    if stored is not None and TileFeatures.rows_of(stored) != own.size:
        return None
    if halo is not None and halo[0].shape != halo[1].shape:
        halo = None
    return labels, bayes, rec, stored, halo


def fill_from_halos(labels: np.ndarray, halos: list[tuple[np.ndarray, np.ndarray]],
                    done: Optional[np.ndarray] = None) -> int:
    """Give a point its tile left unlabelled (nothing reached it there: unseen surface whose
    evidence lies across the border) the label a neighbouring tile gave it in its halo, the first
    such tile in grid order; labelled points keep theirs, and so do the points of a failed tile
    (``done``: (N,) bool, False there; None = every tile finished). ``labels``: (N,) int16, changed
    in place; ``halos``: per tile (scene indices, labels) of its labelled halo points. Returns how many
    points were filled. The untiled graph reaches these points through the border; a tile only
    through its halo, so the neighbour that holds them in its halo is the one that saw the way."""
    filled = 0
    for idx, lab in halos:  # loop over tiles
        take = labels[idx] == IGNORE
        if done is not None:
            take &= done[idx]
        labels[idx[take]] = lab[take]
        filled += int(take.sum())
    return filled


def fingerprint(cfg: Config) -> str:
    """What makes tiles of two runs interchangeable: the config without where and how they ran."""
    t = dataclasses.replace(cfg.tiling, workers=0, address=None, max_retries=0, resume=None)
    c = dataclasses.replace(cfg, tiling=t, record=type(cfg.record)(), output=type(cfg.output)())
    return hashlib.sha1(config_yaml(c).encode()).hexdigest()


def tiles_dir(cfg: Config, run_dir: Optional[Path]) -> Path:
    if cfg.tiling.resume:
        d = Path(cfg.tiling.resume) / TILES
        if not d.is_dir():
            raise FileNotFoundError(f"tiling.resume={cfg.tiling.resume}: no {TILES}/ folder of a tiled run there")
        return d
    if run_dir is None:
        raise ValueError("a tiled run needs a run folder for its tiles (run_dir=..., or tiling.resume=<folder>)")
    d = Path(run_dir) / TILES
    d.mkdir(parents=True, exist_ok=True)
    return d


def check_fingerprint(tiles_dir: Path, cfg: Config) -> None:
    path = tiles_dir / "tiling.json"
    fp = fingerprint(cfg)
    if path.is_file():
        old = json.loads(path.read_text()).get("config_sha1")
        if old != fp:
            raise ValueError(f"tiling.resume: the tiles in {tiles_dir} were made with another config (scene, "
                             f"predictions, method, tiling.size/halo, ...); resume with the same keys")
    else:
        write_json_atomic(path, {"config_sha1": fp})


def finished(tiles_dir: Path, specs: list[TileSpec], owns: dict, resume: Optional[str]) -> tuple[dict, list[TileSpec]]:
    """The records of the tiles whose files are complete in ``tiles_dir`` (kept: ``resumed`` when the run
    resumes another's), and the tiles still to run."""
    records: dict[str, dict] = {}
    todo = []
    for spec in specs:  # loop over tiles: the finished ones are kept
        got = read_tile(tiles_dir, spec, owns[spec.id])
        if got is None:
            todo.append(spec)
        else:
            records[spec.id] = dict(got[2], status="resumed" if resume else got[2]["status"])
    return records, todo


def assemble(tiles_dir: Path, specs: list[TileSpec], owns: dict, records: dict, n: int,
             run_dir: Optional[Path]) -> tuple[np.ndarray, np.ndarray, dict, int]:
    """The scene's (N,) labels and Bayesian labels from the tiles' files (a tile whose file is missing or
    damaged turns ``error`` in ``records``; a failed tile's points stay unlabeled), a features run's
    ``features.npy`` in ``run_dir`` (:class:`~diffuser_lab.method.space.TileFeatures`), the files written and
    how many points their tile left unlabelled took a neighbour's halo label (:func:`fill_from_halos`)."""
    labels = np.full(n, IGNORE, np.int16)
    bayes = labels.copy()
    features = TileFeatures(Path(run_dir or ".") / "features.npy", n)
    halos, done = [], np.zeros(n, bool)  # done: the points whose own tile finished
    for spec in specs:  # loop over tiles: their files -> the scene's labels (and features)
        own = owns[spec.id]
        got = (read_tile(tiles_dir, spec, own, features=run_dir is not None, halo=True)
               if records[spec.id]["status"] != "error" else None)
        if got is None and records[spec.id]["status"] != "error":
            records[spec.id] = dict(records[spec.id], status="error", error="its tile file is missing or damaged")
        if got is None:
            continue
        labels[own], bayes[own] = got[0], got[1]
        done[own] = True
        if got[4] is not None and got[4][0].size and got[4][0].max() < n:
            halos.append(got[4])
        features.add(own, got[3])
    from_halo = fill_from_halos(labels, features.halos(halos), done)
    return labels, bayes, features.files, from_halo
