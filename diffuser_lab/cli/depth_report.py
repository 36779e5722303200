"""``diffuser-lab-depth-report``: what the depth sensor model does to a scene's depth.

    diffuser-lab-depth-report [--json FILE] [HYDRA OVERRIDES ...]
    python -m diffuser_lab.cli.depth_report scene=scannet0470 depth.quantization=disparity

The scene is composed from the same config as ``diffuser-lab`` (``depth=sensor`` unless the
overrides pick another ``depth`` option). Rendered sources (demo, mesh_views) are loaded twice,
with perfect and with sensor depth (the same seeded camera path); real sources once, their depth
taken as "perfect" and the model applied on top. Prints the frames, the pixels and a markdown
table of :func:`diffuser_lab.data.sensor.depth_error_report` (RMSE, holes by range bin); ``--json``
also writes the report as JSON.
"""
from __future__ import annotations

import json
import sys
from dataclasses import replace

from diffuser_lab import progress
from diffuser_lab.cli.main import config_dir, one_line
from diffuser_lab.config import DepthModel, register, to_object
from diffuser_lab.data import sources
from diffuser_lab.data.sensor import depth_error_report, format_depth_report, noisy_frames, sensor_model
from diffuser_lab.data.taxonomy import resolve_taxonomy
from diffuser_lab.runs.pipeline import load_scene
from diffuser_lab.runs.resolve import resolve

PROG = "diffuser-lab-depth-report"


def report_for(cfg) -> tuple[dict, int]:
    """(depth_error_report over every frame, number of frames) for a composed :class:`Config`."""
    tax = resolve_taxonomy(cfg)
    depth_cfg = cfg.depth if cfg.depth.model != DepthModel.perfect else replace(cfg.depth, model=DepthModel.sensor)
    rendered = sources.get(cfg.scene.source).rendered
    with progress.quiet():
        perfect = load_scene(cfg.scene, tax)
        if rendered:
            noisy = load_scene(cfg.scene, tax, depth_cfg).frames
        else:
            noisy = noisy_frames(perfect.frames, sensor_model(depth_cfg))
        p = [f.depth for f in perfect.frames]
        q = [f.depth for f in noisy]
    return depth_error_report(p, q), len(p)


def main(argv: list[str] | None = None) -> None:
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    args = list(sys.argv[1:] if argv is None else argv)
    json_path = None
    if "--json" in args:
        i = args.index("--json")
        if i + 1 >= len(args):
            print(f"{PROG}: error: --json needs a file name", file=sys.stderr)
            sys.exit(2)
        json_path = args[i + 1]
        del args[i : i + 2]
    if any(a in ("-h", "--help") for a in args):
        print(__doc__)
        return
    overrides = args if any(a.split("=")[0] in ("depth", "+depth") for a in args) else ["depth=sensor", *args]
    register()
    try:
        with initialize_config_dir(config_dir=config_dir(), version_base="1.3", job_name="depth_report"):
            cfg = resolve(to_object(compose(config_name="config", overrides=overrides)))
        rep, n_frames = report_for(cfg)
    except Exception as exc:  # noqa: BLE001 - one line, as diffuser-lab prints it
        print(f"{PROG}: error: {one_line(exc)}", file=sys.stderr)
        sys.exit(2)
    finally:
        GlobalHydra.instance().clear()
    a = rep["all"]
    print(f"{PROG} | scene {cfg.scene.source} | {n_frames} frames | {a['pixels']:,} pixels with perfect depth | "
          f"holes {100 * a['holes']:.1f}% | RMSE {1000 * a['rmse']:.1f} mm")
    print(format_depth_report(rep))
    if json_path:
        with open(json_path, "w") as fh:
            json.dump({"overrides": overrides, "frames": n_frames, **rep}, fh, indent=1)
        print(f"report: {json_path}")


if __name__ == "__main__":
    main()
