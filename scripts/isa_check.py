"""The same seed's figures under forced instruction sets (issue 47): does a run give the same labels
and metrics on any x86-64 CPU?

What decides a run's numbers and can be forced on one machine is forced here, each in its own
process (the variables act when the libraries load):

- ``host``: nothing forced (numba compiles for this CPU, OpenBLAS and numpy pick their kernels);
- ``avx2``: numba for ``haswell``, OpenBLAS's ``Haswell`` kernels, numpy's AVX-512 loops off;
- ``generic``: numba for ``generic`` x86-64 (no AVX, no FMA), OpenBLAS's ``Prescott`` (SSE3)
  kernels, numpy at its baseline (every dispatched loop off).

What cannot be forced this way is the ray caster's kernels (Embree picks SSE/AVX2/AVX-512 itself);
the code no longer depends on them (docs/results/isa.md). ``--qemu CPU`` runs a setting under
``qemu-x86_64 -cpu CPU`` (e.g. ``Haswell``, ``EPYC-Rome``): an emulated CPU, Embree included
(slow: minutes; ``--runs data`` builds only the demo's data and hashes it).

    python scripts/isa_check.py run --setting generic --out DIR [--runs demo,scene0470,features]
    python scripts/isa_check.py compare DIR_A DIR_B          # labels' hashes and every score equal (FROM_Z: 1e-3)
    python scripts/isa_check.py both --out DIR               # host and generic, then compare

Each run writes DIR/<run>.npy (its labels) and DIR/report.json (its labels' sha256, every figure of its
metrics and baselines, the diffusion's iterations and residual, the forced settings as the libraries
report them).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared" / "data"
RUNS = {
    "demo": [],
    "scene0470": ["scene=scannet0470"],
    "features": ["predictions=features", "predictions.dim=64"],
}
"""The runs compared: the README's demo, the real ScanNet scene and a features run (64-D: the default
512 takes 39 s; the same code path)."""
DATA = "data"
"""A run of its own: the demo's points, frames and predictions hashed (no diffusion; for qemu)."""


def settings() -> dict[str, dict[str, str]]:
    """Environment of each setting. numpy's dispatch targets are read from numpy itself (their names
    change between versions): ``generic`` disables all, ``avx2`` those of AVX-512."""
    from numpy._core._multiarray_umath import __cpu_dispatch__ as dispatch

    avx512 = [t for t in dispatch if "512" in t or t.endswith("V4")]
    return {
        "host": {},
        "avx2": {"NUMBA_CPU_NAME": "haswell", "OPENBLAS_CORETYPE": "Haswell",
                 "NPY_DISABLE_CPU_FEATURES": " ".join(avx512)},
        "generic": {"NUMBA_CPU_NAME": "generic", "OPENBLAS_CORETYPE": "Prescott",
                    "NPY_DISABLE_CPU_FEATURES": " ".join(dispatch)},
    }


def _what_ran() -> dict:
    """The kernels this process uses, as the libraries report them."""
    import numba
    import numpy as np
    from numpy._core._multiarray_umath import __cpu_features__ as feats
    from threadpoolctl import threadpool_info

    import llvmlite.binding as ll

    blas = [{k: i.get(k) for k in ("internal_api", "architecture", "version")} for i in threadpool_info()
            if i.get("user_api") == "blas"]
    return {"numba_cpu": numba.config.CPU_NAME or ll.get_host_cpu_name(),
            "numpy_simd": sorted(k for k, v in feats.items() if v and ("AVX" in k or k.startswith("X86"))),
            "blas": blas, "numpy": np.__version__}


def _data_hashes() -> dict:
    """sha256 of the demo scene's points, poses, depth and label images and simulated predictions."""
    import numpy as np

    from diffuser_lab.config import default_config
    from diffuser_lab.data.predictions import with_predictions
    from diffuser_lab.data.sources.demo import make_demo_scene

    scene, _ = make_demo_scene()
    frames = with_predictions(scene.frames, default_config().predictions, scene.taxonomy)
    parts = {"points": scene.points, "poses": np.stack([f.T_cw for f in scene.frames]),
             "depth": np.stack([f.depth for f in scene.frames]),
             "label_images": np.stack([f.gt_labels for f in scene.frames]),
             "predictions": np.stack([frames[i].labels for i in range(len(frames))])}
    return {k: hashlib.sha256(np.ascontiguousarray(v).tobytes()).hexdigest()[:16] for k, v in parts.items()}


def figures(tree, prefix: str = "") -> dict[str, float]:
    """Every number of a nested dict (or list) by its dotted path: the figures a run prints and
    saves (mIoU, accuracy, coverage, per-class IoU, calibration, the baselines'), as float64."""
    out = {}
    items = tree.items() if isinstance(tree, dict) else enumerate(tree) if isinstance(tree, (list, tuple)) else ()
    for k, v in items:
        key = f"{prefix}{k}"
        if hasattr(v, "ndim") and v.ndim > 0:
            v = v.tolist()
        if isinstance(v, (dict, list, tuple)):
            out.update(figures(v, key + "."))
        elif isinstance(v, (int, float)) and not isinstance(v, bool) or hasattr(v, "dtype") and v.ndim == 0:
            out[key] = float(v)
    return out


def run(setting: str, out: Path, names: list[str]) -> dict:
    """The runs ``names`` in this process (the setting's variables already set by the caller)."""
    import numpy as np
    from hydra import compose, initialize_config_dir

    from diffuser_lab.cli.main import config_dir
    from diffuser_lab.config import register, to_object
    from diffuser_lab.runs.pipeline import run as pipeline_run

    out.mkdir(parents=True, exist_ok=True)
    report = {"setting": setting, "env": {k: os.environ.get(k) for k in settings()["generic"]},
              "kernels": _what_ran(), "runs": {}}
    register()
    for name in names:
        if name == DATA:
            report["runs"][name] = {"hashes": _data_hashes()}
            continue
        if name == "scene0470" and not SHARED.is_dir():
            report["runs"][name] = {"skipped": f"{SHARED} is absent"}
            continue
        with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
            cfg = to_object(compose("config", overrides=[*RUNS[name], "record=off"]))
        res = pipeline_run(cfg)
        np.save(out / f"{name}.npy", res.labels)
        d = res.diffusion
        report["runs"][name] = {
            "n": int(len(res.labels)),
            "figures": figures({"metrics": res.metrics or {}, "baselines": res.baseline,
                                "diffusion": {} if d is None else {"iterations": d.iterations, "residual": d.residual}}),
            "labels_sha": hashlib.sha256(np.ascontiguousarray(res.labels).tobytes()).hexdigest()}
    (out / "report.json").write_text(json.dumps(report, indent=1))
    return report


def spawn(setting: str, out: Path, names: list[str], qemu: str | None = None, timeout: float = 3000) -> dict:
    """Run ``names`` under ``setting`` in a fresh interpreter (under ``qemu-x86_64 -cpu qemu`` if given)."""
    env = {**os.environ, **settings()[setting], "DIFFUSER_LAB_NUMBA": "1", "PYTHONPATH": str(ROOT)}
    argv = [sys.executable, str(Path(__file__).resolve()), "run", "--setting", setting, "--out", str(out),
            "--runs", ",".join(names)]
    if qemu:
        argv = [shutil.which("qemu-x86_64") or "qemu-x86_64", "-cpu", qemu, *argv]
    p = subprocess.run(argv, env=env, cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    if p.returncode:
        raise RuntimeError(f"isa_check {setting}{' under qemu ' + qemu if qemu else ''} failed "
                           f"(exit {p.returncode}):\n{p.stderr[-3000:]}")
    return json.loads((out / "report.json").read_text())


FROM_Z = ("metrics.calibration.", "diffusion.residual")
"""Figures computed from the diffusion's float32 state Z rather than from its labels: the calibration
(ECE, NLL, Brier, the reliability bins) and the relative change of the last step. The compiled kernels
round Z's last bits by the instruction set (numba's AVX-512 / AVX2 / generic code: FMA, the order of
a row's sums), so these agree to :data:`Z_REL` only; every other figure, and the labels, bit for bit."""
Z_REL = 1e-3
"""Relative tolerance of the figures of :data:`FROM_Z` (measured 2026-12-07, AMD EPYC Zen 4 host
against generic: 8.1e-5 for the residual, 2.5e-4 for the features run's bins: one point of 4,067 in
the next confidence bin; 1e-8 for scene0470's)."""


def compare(a: Path, b: Path) -> list[str]:
    """Differences between two report folders (empty = the same bits: the labels' sha256 and every
    figure equal, nan to nan; the figures of :data:`FROM_Z` within :data:`Z_REL`), and a table of what
    was compared printed to stdout."""
    import numpy as np

    ra, rb = (json.loads((d / "report.json").read_text()) for d in (a, b))
    bad = []
    print(f"{'run':<11} {'labels':>9} {'equal':>8} {'max rel. diff':>15}   {ra['setting']} vs {rb['setting']}")
    for name in sorted(set(ra["runs"]) & set(rb["runs"])):
        x, y = ra["runs"][name], rb["runs"][name]
        if "skipped" in x or "skipped" in y:
            print(f"{name:<11} skipped ({x.get('skipped') or y.get('skipped')})")
            continue
        if "hashes" in x:
            diff = [k for k in x["hashes"] if x["hashes"][k] != y["hashes"].get(k)]
            print(f"{name:<11} {'identical' if not diff else 'differ: ' + ', '.join(diff)}")
            bad += [f"{name}: {k} differ" for k in diff]
            continue
        la, lb = np.load(a / f"{name}.npy"), np.load(b / f"{name}.npy")
        same = x["labels_sha"] == y["labels_sha"]
        fx, fy = x["figures"], y["figures"]
        differ = sorted(k for k in set(fx) | set(fy) if not (fx.get(k) == fy.get(k) or
                                                                 _nan(fx.get(k)) and _nan(fy.get(k))))
        worst = max((abs(fx[k] - fy[k]) / max(abs(fx[k]), 1e-300) for k in differ if k in fx and k in fy),
                    default=0.0)
        print(f"{name:<11} {'same' if same else 'differ':>9} {len(fx) - len(differ):>4}/{len(fx):<3} {worst:15.3g}")
        differ = [k for k in differ if not (k.startswith(FROM_Z) and k in fx and k in fy
                                            and abs(fx[k] - fy[k]) <= Z_REL * max(abs(fx[k]), abs(fy[k])))]
        if not same:
            equal = float((la == lb).mean()) if la.shape == lb.shape else 0.0
            bad.append(f"{name}: labels differ (sha256 {x['labels_sha'][:16]} vs {y['labels_sha'][:16]}; "
                       f"{100 * equal:.4f} % equal)")
        bad += [f"{name}: {k} = {fx.get(k)!r} vs {fy.get(k)!r}" for k in differ]
        if not fx:
            bad.append(f"{name}: no figures recorded")
    return bad


def _nan(v) -> bool:
    return isinstance(v, float) and v != v


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="run in this process (set the variables yourself, or use 'both')")
    r.add_argument("--setting", default="host")
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--runs", default=",".join(RUNS))
    c = sub.add_parser("compare")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    bo = sub.add_parser("both", help="host and another setting, each in its own process, then compare")
    bo.add_argument("--out", type=Path, required=True)
    bo.add_argument("--runs", default=",".join(RUNS))
    bo.add_argument("--against", default="generic", choices=["avx2", "generic"])
    bo.add_argument("--qemu", default=None, help="run the other setting under qemu-x86_64 -cpu QEMU")
    args = ap.parse_args(argv)
    if args.cmd == "run":
        run(args.setting, args.out, args.runs.split(","))
        return 0
    if args.cmd == "compare":
        bad = compare(args.a, args.b)
    else:
        names = args.runs.split(",")
        spawn("host", args.out / "host", names)
        other = f"host-qemu-{args.qemu}" if args.qemu else args.against
        spawn(args.against if not args.qemu else "host", args.out / other, names, qemu=args.qemu)
        bad = compare(args.out / "host", args.out / other)
    for b in bad:
        print(f"isa_check: {b}", file=sys.stderr)
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
