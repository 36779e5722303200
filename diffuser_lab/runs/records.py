"""Files a run writes into its own folder: summary.json (atomically replaced), labels.npy, labels.ply;
the config as the records keep it (:func:`config_yaml`) and its hash (:func:`config_sha256`); the
hashes of what a run wrote (:func:`output_hashes`)."""
from __future__ import annotations

import dataclasses
import json
import math
import os
from enum import Enum
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np
import yaml
from omegaconf import OmegaConf

from diffuser_lab import progress
from diffuser_lab.data import inputs
from diffuser_lab.data.arrays import read_array
from diffuser_lab.data.clouds import write_las, write_pointcloud2_bag
from diffuser_lab.data.o3d import open3d
from diffuser_lab.backends.records import write_rows
from diffuser_lab.data.scene import IGNORE, Taxonomy
from diffuser_lab.method.calibration import point_rows


def config_yaml(conf: Any) -> str:
    """The config as YAML, the text ``OmegaConf.to_yaml`` writes (enums by name). A
    :class:`~diffuser_lab.config.Config` object is dumped from its plain fields: 5 ms instead of
    OmegaConf's 30 ms, which re-validates the whole tree first."""
    if dataclasses.is_dataclass(conf) and not isinstance(conf, type):
        def plain(o: Any) -> Any:
            if isinstance(o, dict):
                return {k: plain(v) for k, v in o.items()}
            if isinstance(o, (list, tuple)):
                return [plain(v) for v in o]
            return o.name if isinstance(o, Enum) else o

        return yaml.safe_dump(plain(dataclasses.asdict(conf)), default_flow_style=False, allow_unicode=True,
                              sort_keys=False)
    return OmegaConf.to_yaml(conf)


def config_sha256(conf: Any) -> str:
    """sha256 of the config as :func:`config_yaml` writes it (every key, enums by name): equal
    hashes, the same resolved config."""
    return inputs.sha256_bytes(config_yaml(conf).encode())


def output_hashes(run_dir: Path, files: dict) -> dict:
    """{file name relative to the run folder: {"size", "sha256"}} of the files a run wrote
    (summary.json ``files``' values: labels.npy, labels.ply, features, map.npy, ...); a folder
    (``labels_ros2/``) as the :func:`~diffuser_lab.data.inputs.manifest` of its files (and their
    count). Read back after writing: what is hashed is what is on disk."""
    out = {}
    for name in sorted({str(v) for v in (files or {}).values() if isinstance(v, str)}):  # a few files
        path = Path(run_dir) / name
        if path.is_file():
            size, sha = inputs.sha256_file(path)
            out[name] = {"size": size, "sha256": sha}
        elif path.is_dir():
            parts = [inputs.sha256_file(p) for p in sorted(path.rglob("*")) if p.is_file()]
            out[name] = {"size": sum(n for n, _ in parts), "count": len(parts),
                         "sha256": inputs.manifest(h for _, h in parts)}
    return out


def json_ready(obj: Any) -> Any:
    """JSON-safe copy: numpy scalars -> Python, NaN/inf -> None."""
    if isinstance(obj, dict):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def write_json_atomic(path: Path, data: dict) -> None:
    """Write ``data`` to ``path`` through a temporary file and os.replace, so a reader (or a
    run killed mid-write) never sees a half-written file."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as fh:
        json.dump(json_ready(data), fh, indent=2)
        fh.write("\n")
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


CONFIDENCE_FIELDS = ("confidence", "margin", "entropy")
"""The per-point confidence's vertex properties (labels.ply) and extra dimensions (LAS / LAZ), float32:
the top score, top - second score, entropy in nats (:func:`~diffuser_lab.method.calibration.confidence`)."""


def _fields(confidence: Optional[np.ndarray]) -> dict:
    """{property: (N,) float32} of an (N, 3) ``confidence`` (None: {})."""
    if confidence is None:
        return {}
    c = np.asarray(confidence, np.float32)
    return {name: np.ascontiguousarray(c[:, j]) for j, name in enumerate(CONFIDENCE_FIELDS)}


def _las(suffix: str) -> Callable[..., list[Path]]:
    def write(run_dir: Path, points: np.ndarray, labels: np.ndarray, taxonomy: Taxonomy,
              confidence: Optional[np.ndarray] = None) -> list[Path]:
        return write_las(run_dir / f"labels.{suffix}", points, labels, taxonomy.names, taxonomy.colorize(labels),
                         extra=_fields(confidence))

    return write


def _ros2(run_dir: Path, points: np.ndarray, labels: np.ndarray, taxonomy: Taxonomy,
          confidence: Optional[np.ndarray] = None) -> list[Path]:
    return [write_pointcloud2_bag(run_dir / "labels_ros2", points, labels, taxonomy)]  # its fields are fixed


TIMED_OUTPUTS = {"labels.las": "its header has the day it was written", "labels.laz": "its header has the day it was written",
                 "labels_ros2/": "its message is stamped with the time it was written"}
"""Output files (a name, or a folder's prefix) whose bytes hold when they were written: two runs' differ
there whatever their labels (``diffuser-lab-verify`` names them apart; their labels are labels.npy's)."""


def timed_output(name: str) -> Optional[str]:
    """Why an output file's bytes hold its write time (:data:`TIMED_OUTPUTS`), None for the others."""
    return next((why for k, why in TIMED_OUTPUTS.items() if name == k or k.endswith("/") and name.startswith(k)),
                None)


CLOUD_WRITERS: dict[str, Callable[..., list[Path]]] = {
    "las": _las("las"),
    "laz": _las("laz"),
    "ros2": _ros2,
}
"""``output.clouds`` formats: ``(run folder, points, labels, taxonomy, confidence=None) -> files written``
(the LAS formats carry ``confidence`` as extra dimensions, :data:`CONFIDENCE_FIELDS`)."""


def write_labels(run_dir: Path, points: np.ndarray, labels: np.ndarray, taxonomy: Taxonomy, ply: bool = True,
                 clouds: Sequence = (), confidence: Optional[np.ndarray] = None) -> dict:
    """labels.npy ((N,) int16, -1 = unlabeled), labels.ply (points coloured by class, with a
    per-vertex ``label`` property) and the ``clouds`` formats (:data:`CLOUD_WRITERS`, names or
    :class:`~diffuser_lab.config.CloudFormat`); ``confidence`` ((N, 3) float32, ``output.scores``)
    adds the :data:`CONFIDENCE_FIELDS` to labels.ply and the LAS files. Returns the file names written."""
    run_dir = Path(run_dir)
    names = [getattr(c, "value", c) for c in clouds]
    with progress.stage("writing " + " + ".join(["labels.npy"] + (["labels.ply"] if ply else []) + names)):
        out = _write_labels(run_dir, points, labels, taxonomy, ply, confidence)
        for name in names:  # loop over output formats
            written = CLOUD_WRITERS[name](run_dir, points, labels, taxonomy, confidence)
            out[f"labels_{name}"] = Path(written[0]).relative_to(run_dir).as_posix()
        return out


def _write_labels(run_dir: Path, points: np.ndarray, labels: np.ndarray, taxonomy: Taxonomy, ply: bool,
                  confidence: Optional[np.ndarray] = None) -> dict:
    np.save(run_dir / "labels.npy", labels.astype(np.int16))
    out = {"labels": "labels.npy"}
    if ply:
        o3d = open3d()

        pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.asarray(points, np.float32)))
        pcd.point.colors = o3d.core.Tensor(taxonomy.colorize(labels))
        pcd.point.label = o3d.core.Tensor(labels.astype(np.int32)[:, None])
        for name, values in _fields(confidence).items():
            setattr(pcd.point, name, o3d.core.Tensor(values[:, None]))
        if not o3d.t.io.write_point_cloud(str(run_dir / "labels.ply"), pcd, write_ascii=False):
            raise OSError(f"could not write {run_dir / 'labels.ply'}")
        out["labels_ply"] = "labels.ply"
    return out


GT_FILE = "gt_labels.npy"
"""The scene's ground truth on its points, (N,) int16 (IGNORE = unannotated), when it has one."""
BAYESIAN_FILE = "bayesian_labels.npy"
"""The Bayesian baseline's labels of the same run, (N,) int16 (-1 = unlabeled)."""
SCORES_FILE = "scores.npy"
"""``output.scores``: each point's class distribution, (N, C) float16 (:func:`write_scores`)."""


def write_scoring(run_dir: Path, scene, bayesian_labels: np.ndarray | None = None) -> dict:
    """What scores a run's labels again without its scene: :data:`GT_FILE` (when the scene has
    ground truth) and :data:`BAYESIAN_FILE` (the baseline's labels, when given), beside labels.npy:
    ``analysis.report`` scores every method on the points all of them label (2 bytes a point each:
    0.1 MB at 51k points, 6 MB at 3M). Returns the file names written."""
    out = {}
    if scene.gt_labels is not None:
        np.save(run_dir / GT_FILE, np.asarray(scene.gt_labels, np.int16))
        out["gt_labels"] = GT_FILE
    if bayesian_labels is not None:
        np.save(run_dir / BAYESIAN_FILE, np.asarray(bayesian_labels, np.int16))
        out["bayesian_labels"] = BAYESIAN_FILE
    return out


def load_npy(path: Path) -> np.ndarray:
    """A run folder's ``.npy`` file as a read-only memory map (:func:`diffuser_lab.data.arrays.read_array`:
    its header checked against the file's bytes); one line naming the file when it is not one."""
    if not Path(path).is_file():
        raise ValueError(f"{path}: unreadable (FileNotFoundError: no such file), expected a .npy array")
    return read_array(path, ".npy array", role=None, mmap=True)


def read_gt(run_dir: Path, n: int, num_classes: int) -> Optional[np.ndarray]:
    """:data:`GT_FILE` of ``run_dir`` ((n,) class ids in IGNORE..num_classes - 1), None when the run wrote
    none; one line naming the file when it does not fit."""
    path = Path(run_dir) / GT_FILE
    if not path.is_file():
        return None
    gt = np.asarray(load_npy(path))
    if gt.shape != (n,) or gt.dtype.kind not in "iu":
        raise ValueError(f"{path}: shape {gt.shape} dtype {gt.dtype}, expected ({n},) class ids")
    if gt.size and (gt.min() < IGNORE or gt.max() >= num_classes):
        raise ValueError(f"{path}: class ids {int(gt.min())}..{int(gt.max())}, expected "
                         f"{IGNORE}..{num_classes - 1} ({num_classes} classes in summary.json)")
    return gt


def write_scores(run_dir: Path, result) -> dict:
    """``output.scores``: :data:`SCORES_FILE`, (N, C) float16, row i the class distribution of original
    point i (labels.npy's order) as the run's calibration scores it
    (:func:`~diffuser_lab.method.calibration.point_rows`: Eq. 16's row of Z, or a per-point method's mass,
    divided by its sum; all zero where nothing reached the point), written CHUNK rows at a time; with
    :data:`GT_FILE` (:func:`write_scoring`) the run's calibration is computed from its folder
    (:func:`diffuser_lab.runs.scores.calibration_of_run`)."""
    n, c = len(result.labels), result.scene.taxonomy.num_classes
    write_rows(run_dir / SCORES_FILE, (n, c), (p for _, _, p in point_rows(result.scores, result.rows, n)))
    return {"scores": SCORES_FILE}
