"""Visibility without depth images, measured: a scene's run with its frames' own depth beside the same
run with the depth check's depth rendered from the cloud (diffuser_lab.data.visibility.CloudDepth) for
several splat radii, and (for scenes built from a mesh) rendered from the mesh. Prints labels equal to
the depth run's and mIoU, Diffuser and Bayesian.

    python -m analysis.no_depth                      # the demo and scene0470 (../shared), splats 0.2 0.4 0.7
    python -m analysis.no_depth demo --splat 0.4
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from diffuser_lab.data.frames import LazyFrames
from diffuser_lab.data.visibility import CloudDepth
from diffuser_lab.runs.pipeline import load_scene, run
from diffuser_lab.runs.resolve import resolve
from diffuser_lab.data.taxonomy import resolve_taxonomy



def compose(*overrides: str):
    """The validated, resolved config of ``diffuser-lab OVERRIDES`` (composed from conf/)."""
    from hydra import compose as hcompose
    from hydra import initialize_config_dir

    from diffuser_lab.cli.main import config_dir
    from diffuser_lab.config import register, to_object

    register()
    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        return resolve(to_object(hcompose("config", overrides=list(overrides))))


def rendered(scene, splat: float):
    """The scene with its frames' depth replaced by the cloud's z-buffer."""
    r = CloudDepth(scene.points, splat=splat)
    frames = LazyFrames.mapped(scene.frames, lambda i, f: dataclasses.replace(f, depth=r(f.K, f.T_cw, f.depth.shape)))
    return dataclasses.replace(scene, frames=frames)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="*", default=["demo", "scannet0470"], help="scene YAML names (conf/scene)")
    ap.add_argument("--splat", type=float, nargs="+", default=[0.2, 0.4, 0.7])
    a = ap.parse_args(argv)
    print(f"{'scene':12s} {'depth':22s} {'equal %':>8s} {'mIoU':>6s} {'bayes':>6s} {'cover %':>8s} {'s':>5s}")
    for name in a.scenes:  # loop over scenes
        cfg = compose(f"scene={name}", "record=off")
        scene = load_scene(cfg.scene, resolve_taxonomy(cfg), cfg.depth)
        rows = [("frames' depth", scene)] + [(f"cloud, splat {s:g}", rendered(scene, s)) for s in a.splat]
        base = None
        for label, sc in rows:  # loop over variants
            t = time.perf_counter()
            res = run(cfg, scene=sc)
            base = res.labels if base is None else base
            b = res.baseline.get("bayesian") or {}
            print(f"{name:12s} {label:22s} {100 * np.mean(res.labels == base):8.2f} {res.metrics['miou']:6.1f} "
                  f"{b.get('miou', float('nan')):6.1f} {100 * res.evidence.seen.mean():8.1f} {time.perf_counter() - t:5.1f}")


if __name__ == "__main__":
    main()
