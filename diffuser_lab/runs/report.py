"""What a run tells: summary.json (built here only, :class:`SummaryFile`), its figures as a
comparison reads them (:func:`figures`) and the table printed at the end."""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from diffuser_lab.backends import provenance
from diffuser_lab.config import Config
from diffuser_lab.data import inputs, sources
from diffuser_lab.data.scene import IGNORE

from .pipeline import RunResult
from .records import config_sha256, json_ready, output_hashes, write_json_atomic
from .results import calibration_key

STAGES = ("load", "predictions", "evidence", "graph", "diffusion", "labels", "scores", "metrics", "write", "total")


def summary(res: RunResult, cfg: Config) -> dict:
    """summary.json content (keys as in shared/DESIGN.md; mIoU, accuracy, coverage in percent)."""
    scene = res.scene
    out: dict = {
        "method": res.method,
        "scene": scene.name,
        "n_points": scene.n_points,
        "n_points_diffused": int(res.work_points.shape[0]),
        "n_frames": len(res.frames),
        "n_classes": scene.taxonomy.num_classes,
        "taxonomy": scene.taxonomy.name,
        "coverage_evidence": float(100.0 * res.evidence.seen.mean()),
        "n_unlabeled": int((res.labels == IGNORE).sum()),
        "metrics": res.metrics,
        "baseline": {"bayesian": res.baseline.get("bayesian"), **{k: v for k, v in res.baseline.items() if k != "bayesian"}},
        "predictions_2d": res.predictions_2d,
        "predictions_stats": res.predictions_stats,
        "timings_s": {k: round(v, 4) for k, v in res.timings_s.items()},
    }
    capture = _capture(scene)
    if capture:
        out["capture"] = capture
    kept = keyframes_kept(scene)
    if kept:
        out["keyframes"] = kept
    if res.diffusion is not None:
        out["diffusion"] = {"iterations": res.diffusion.iterations, "converged": res.diffusion.converged,
                            "residual": res.diffusion.residual,
                            "backend": res.diffusion.info.get("backend")}
    else:
        out["diffusion"] = {"iterations": 0, "converged": None, "residual": None}
    if res.graph is not None:
        out["graph"] = {"k": int(res.graph.neighbors.shape[1]), "rho_m": res.graph.rho,
                        "sigma_d_m": res.graph.sigma_d, "normals": cfg.graph.use_normals}
    out.update(res.space.summary(scene.taxonomy))  # a features run's class names and queries
    return out


CAPTURE_KEYS = ("cloud", "visibility", "gt_from_frames", "intrinsics")
"""What a capture format's loader reports (diffuser_lab/data/capture.py), in summary.json's ``capture``."""


def keyframes_kept(scene) -> Optional[dict]:
    """The keyframe rule's thresholds and the frames it kept (summary.json's ``keyframes``), None when off."""
    return (getattr(scene.frames, "info", None) or {}).get("keyframes")


def followed(scene) -> Optional[dict]:
    """How a capture followed as it was written went (summary.json's ``follow``:
    :attr:`diffuser_lab.data.frames.Follow.info`), None when it was not followed."""
    return (getattr(scene.frames, "info", None) or {}).get("follow")


def follow_line(scene) -> str:
    """The table's line of a followed capture ("" when it was not followed)."""
    f = followed(scene)
    if not f:
        return ""
    return (f"followed as written ({f['policy']}): {f['frames']} frames, {f['used']} used, {f['skipped_behind']} "
            f"skipped behind (newer taken; {f['keyframes_from_backlog']} keyframes kept), {f['skipped_bad']} bad; "
            f"ended: {f['ended']}, {f['wait_s']:.1f} s waiting")


def _capture(scene) -> dict:
    info = getattr(scene.frames, "info", None) or {}
    return {k: info[k] for k in CAPTURE_KEYS if k in info}


def _capture_line(scene) -> Optional[str]:
    c = _capture(scene)
    if not c:
        return None
    parts = [f"cloud {c['cloud']}" if "cloud" in c else "", f"visibility: {c['visibility']}" if "visibility" in c else ""]
    if "intrinsics" in c:
        parts.append(c["intrinsics"])
    g = c.get("gt_from_frames")
    if g:
        parts.append(f"ground truth carried from the frames' labels ({g['points_labelled']:,} points, "
                     f"{g['points_disagreeing']:,} with disagreeing views)")
    return "capture: " + "; ".join(p for p in parts if p)


def _fmt(x, spec=".1f") -> str:
    return "-" if x is None else format(x, spec)


def table(res: RunResult, run_dir: Path | None = None) -> str:
    """A short human-readable result table."""
    s = res.scene
    kf = keyframes_kept(s)
    of = f" (keyframes of {kf['of']})" if kf else ""
    lines = [f"diffuser-lab | scene {s.name} | {s.n_points:,} points ({res.work_points.shape[0]:,} diffused) | "
             f"{len(res.frames)} frames{of} | {s.taxonomy.num_classes} classes"]
    if res.metrics is None:  # e.g. a posed RGB-D folder without label images: nothing to score
        lab = res.labels[res.labels != IGNORE].astype(np.int64)
        counts = np.bincount(lab, minlength=s.taxonomy.num_classes)
        top = np.argsort(-counts, kind="stable")[:4]
        share = ", ".join(f"{s.taxonomy.names[c]} {100 * counts[c] / max(lab.size, 1):.0f}%" for c in top if counts[c])
        lines.append(f"no ground truth: no mIoU; {res.method} labelled {lab.size:,} of {s.n_points:,} points "
                     f"({100 * lab.size / max(s.n_points, 1):.1f}%){': ' + share if share else ''}")
    else:
        lines.append(f"{'':22s}{'mIoU':>7s}{'acc':>7s}{'cover':>7s}")
        rows = [(res.method, res.metrics)]
        if res.method != "bayesian":  # a features run's bayesian baseline is the features' average
            rows.append((res.space.baseline_title,
                         res.baseline.get("bayesian")))
        if "best_view" in res.baseline:
            rows.append(("best view (baseline)", res.baseline["best_view"]))
        for name, m in rows:
            m = m or {}
            lines.append(f"{name:22s}{_fmt(m.get('miou')):>7s}{_fmt(m.get('accuracy')):>7s}"
                         f"{_fmt(m.get('coverage')):>7s}")
    line = _capture_line(s)
    if line:
        lines.append(line)
    st = res.predictions_stats
    if "model_calls" in st:  # a network in the loop (diffuser_lab/data/networks.py)
        lines.append(f"2D predictions: {st['model']}, {st['model_calls']} frames run, {st['cached_frames']} from "
                     f"cache{'' if st.get('cache') else ' (cache off)'}")
    if res.predictions_2d is not None:
        p = res.predictions_2d
        lines.append(f"{'2D predictions':22s}{_fmt(p.get('miou')):>7s}{_fmt(p.get('accuracy')):>7s}")
    if res.diffusion is not None:
        d = res.diffusion
        lines.append(f"iterations {d.iterations} ({'converged' if d.converged else 'max reached'}, "
                     f"relative residual {d.residual:.1e})")
    lines.append("time [s]  " + "  ".join(f"{k} {res.timings_s[k]:.2f}" for k in STAGES if k in res.timings_s))
    if run_dir is not None:
        lines.append(f"run folder: {run_dir}")
    return "\n".join(lines)


def single_frame_summary(sf) -> dict:
    """summary.json content of a single-frame protocol run; ``metrics`` is the run's method's widest
    row (Diffuser's W-view row by default), ``baseline.bayesian`` the Bayesian W-view row, ``rows``
    all of Table II (and the method's rows); ``metrics.calibration`` has every row's calibration
    (:func:`calibration_key`)."""
    rows = sf.rows
    pick = {(r["method"], r["views"]): r for r in rows}
    method = getattr(sf, "method", "diffuser")
    main = max((r for r in rows if r["method"] == method), key=lambda r: r["views"], default=None) \
        or pick.get(("diffuser", sf.window))
    bayes = pick.get(("bayesian", sf.window))
    return {
        "protocol": "single_frame",
        "method": main["method"],
        "scene": sf.scene.name,
        "n_points": sf.mean_points,
        "n_frames": len(sf.scene.frames),
        "n_targets": len(sf.targets),
        "window": sf.window,
        "fill_missing_depth": sf.filled,
        "n_classes": sf.scene.taxonomy.num_classes,
        "taxonomy": sf.scene.taxonomy.name,
        "metrics": {"miou": main["miou"], "accuracy": main["accuracy"], "per_class_iou": main["per_class_iou"],
                    "calibration": {calibration_key(r["method"], r["views"]): r["calibration"]
                                    for r in rows if "calibration" in r}},
        "baseline": {"bayesian": {"miou": bayes["miou"], "accuracy": bayes["accuracy"]}},
        "rows": rows,
        "predictions_2d": sf.predictions_2d,
        "diffusion": {},
        "timings_s": {k: round(v, 4) for k, v in sf.timings_s.items()},
        "records": {},
        **({"keyframes": keyframes_kept(sf.scene)} if keyframes_kept(sf.scene) else {}),
    }


VOLATILE_KEYS = frozenset({"status", "error", "overrides", "started", "provenance", "timings_s", "memory", "records",
                           "files", "warnings", "inputs", "outputs", "verify", "kernels"})
"""summary.json's top-level keys that say how, where and when a run ran, not what it computed."""
VOLATILE_LEAVES = frozenset({"node", "pid", "host", "machine", "machines", "tiles_dir", "resumed_from", "cache",
                             "model_calls", "cached_frames", "ms", "s"})
"""Keys, at any depth, of the same kind: where a tile ran, a network's cache and what it held."""
VOLATILE_SUFFIXES = ("_s", "_ms", "_gb")
"""... and of times and memory (``time_s``, ``latency_ms``, ``peak_rss_gb``)."""


def _volatile(key: str) -> bool:
    return key in VOLATILE_LEAVES or key.endswith(VOLATILE_SUFFIXES)


def figures(summary: dict) -> dict:
    """What a run computed, as its summary.json says it: the summary without :data:`VOLATILE_KEYS`
    and, at any depth, the keys :data:`VOLATILE_LEAVES` or ending in :data:`VOLATILE_SUFFIXES`
    (JSON-ready: numpy scalars as numbers, NaN as None). Two runs that computed the same have equal
    figures; ``outputs.figures_sha256`` is the hash of their :func:`canonical_json`."""
    def walk(o: Any) -> Any:
        if isinstance(o, dict):
            return {k: walk(v) for k, v in o.items() if not _volatile(k)}
        if isinstance(o, list):
            return [walk(v) for v in o]
        return o

    return walk(json_ready({k: v for k, v in summary.items() if k not in VOLATILE_KEYS}))


def canonical_json(obj: Any) -> str:
    """Sorted keys, no spaces, floats as Python writes them (shortest exact): equal text, equal values."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"))


def generator(cfg: Config) -> Optional[dict]:
    """A procedural scene's generator and seed (summary.json ``inputs.generator``), None for a scene
    read from files (the scene sources' ``generated``)."""
    if not sources.get(cfg.scene.source).generated:
        return None
    return {"source": cfg.scene.source, "seed": getattr(cfg.scene.options, "seed", None)}


class SummaryFile:
    """A run folder's summary.json, the one place it is built. Written as soon as the run starts
    (``status: running``: a run that dies leaves it; with the ``provenance`` block of
    :func:`diffuser_lab.backends.provenance.collect`), rewritten atomically at every change, and
    finished ``ok`` with the result (:meth:`result`, :meth:`single_frame`) or ``failed`` with the
    error (:meth:`failed`). Never overwrites an earlier run's summary."""

    def __init__(self, run_dir: Path, overrides: Sequence[str]):
        self.path = Path(run_dir) / "summary.json"
        if self.path.exists():
            raise FileExistsError(f"{run_dir} already holds a run (summary.json); refusing to overwrite it")
        # provenance: the machine and versions, there from the start (a failed run's too); cached per process
        self.data: dict[str, Any] = {"status": "running", "overrides": list(overrides),
                                     "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                                     "provenance": provenance.collect()}
        self.write()

    def write(self) -> None:
        write_json_atomic(self.path, self.data)

    def update(self, **values: Any) -> None:
        self.data.update(values)
        self.write()

    def warn(self, message: str) -> None:
        """Keep a warning (the data only; the next write stores it)."""
        self.data.setdefault("warnings", []).append(message)

    def result(self, res: RunResult, cfg: Config, *, records: dict, files: dict) -> dict:
        self.data.update(summary(res, cfg))
        self.update(records=records, files=files, status="ok")
        return self.data

    def single_frame(self, sf) -> dict:
        self.data.update(single_frame_summary(sf))
        self.update(status="ok")
        return self.data

    def seal(self, cfg: Optional[Config], read: Optional[inputs.Collector]) -> dict:
        """summary.json's ``inputs`` (the files ``read`` recorded, :func:`diffuser_lab.data.inputs.block`,
        every one listed in the run folder's ``inputs.tsv``; ``config_sha256``; ``generator`` of a
        procedural scene) and ``outputs`` (``files``: the hashes of the files in ``files``, read back;
        ``figures_sha256``: of :func:`figures`), written. ``cfg``: the resolved config (None: the run
        failed before it was). Its own time: ``timings_s.hashes``."""
        t0 = time.perf_counter()
        run_dir = self.path.parent
        rows = read.rows() if read is not None else []
        block = inputs.block(rows, read)
        if rows:
            inputs.write_list(run_dir / inputs.LIST_NAME, rows)
            block["list"] = inputs.LIST_NAME
        if cfg is not None:
            block["config_sha256"] = config_sha256(cfg)
            gen = generator(cfg)
            if gen is not None:
                block["generator"] = gen
        self.data["inputs"] = block
        self.data["outputs"] = {"files": output_hashes(run_dir, self.data.get("files") or {}),
                                "figures_sha256": inputs.sha256_bytes(canonical_json(figures(self.data)).encode())}
        self.data.setdefault("timings_s", {})["hashes"] = round(time.perf_counter() - t0, 4)
        self.write()
        return {"inputs": block, "outputs": self.data["outputs"]}

    def failed(self, error: str) -> Optional[dict]:
        self.data.update(status="failed", error=error)
        try:
            self.write()
        except OSError:  # the folder went away: the error is reported on the terminal anyway
            pass
        return self.data

