"""``diffuser-lab-depth-report``: what the depth sensor model does to a scene's depth.

    diffuser-lab-depth-report [--json FILE] [--beside FILE.json ...] [HYDRA OVERRIDES ...]
    python -m diffuser_lab.cli.depth_report scene=scannet0470 depth.quantization=disparity

The scene is composed from the same config as ``diffuser-lab`` (``depth=sensor`` unless the
overrides pick another ``depth`` option). Rendered sources (demo, mesh_views) are loaded twice,
with perfect and with sensor depth (the same seeded camera path); real sources once, their depth
taken as "perfect" and the model applied on top. Prints the frames, the pixels and a markdown
table of :func:`diffuser_lab.data.depth_stats.depth_error_report` (RMSE, holes by range bin); ``--json``
also writes the report as JSON.

Then the holes of the depth on its own (:func:`diffuser_lab.data.depth_stats.depth_hole_stats`: at
discontinuities, in smooth regions, in blobs, by range and incidence): for a rendered source the
sensor model's depth (pixels where the perfect render hit nothing are ignored: they are not the
sensor's), for a real source the real depth itself. ``--beside FILE.json`` (repeatable) puts the
hole statistics of an earlier ``--json`` report in a column beside this scene's, e.g. real depth
beside the model's::

    diffuser-lab-depth-report scene=scannet_frames scene.options.root=PATH/scene0014_00 --json real.json
    diffuser-lab-depth-report scene=scannet0470 --beside real.json
"""
from __future__ import annotations

import json
import sys
from dataclasses import replace

from diffuser_lab import progress
from diffuser_lab.cli.main import config_dir, one_line
from diffuser_lab.config import DepthModel, register, to_object
from diffuser_lab.data import sources
from diffuser_lab.data.depth_stats import depth_error_report, depth_hole_stats, format_depth_report, format_hole_stats
from diffuser_lab.data.sensor import noisy_frames, sensor_model
from diffuser_lab.data.taxonomy import resolve_taxonomy
from diffuser_lab.runs.pipeline import load_scene
from diffuser_lab.runs.resolve import resolve

PROG = "diffuser-lab-depth-report"


def report_for(cfg) -> tuple[dict, int]:
    """(depth_error_report over every frame with ``holes``: the depth_hole_stats of the sensor depth
    of a rendered source or the real depth of a real one, number of frames) for a composed :class:`Config`."""
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
        Ks = [f.K for f in perfect.frames]
    rep = depth_error_report(p, q)
    # the same rule on both: the model's depth where the mesh was hit, or the real depth as it is
    rep["holes"] = (depth_hole_stats(q, Ks, ignore=[a <= 0 for a in p], edge_jump=depth_cfg.edge_jump) if rendered
                    else depth_hole_stats(p, Ks, edge_jump=depth_cfg.edge_jump))
    return rep, len(p)


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
    beside = []
    while "--beside" in args:
        i = args.index("--beside")
        if i + 1 >= len(args):
            print(f"{PROG}: error: --beside needs a JSON file written by --json", file=sys.stderr)
            sys.exit(2)
        try:
            with open(args[i + 1]) as fh:
                b = json.load(fh)
            beside.append((b.get("name", args[i + 1]), b["holes"]))
        except (OSError, ValueError, KeyError) as exc:
            print(f"{PROG}: error: --beside {args[i + 1]}: not a --json report with hole statistics ({one_line(exc)})",
                  file=sys.stderr)
            sys.exit(2)
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
    rendered = sources.get(cfg.scene.source).rendered
    name = f"{cfg.scene.name or cfg.scene.source}, {'model (sensor) depth' if rendered else 'real depth'}"
    print(f"\nholes of the {'sensor model' if rendered else 'real'} depth on its own (depth_hole_stats):")
    print(format_hole_stats([(name, rep["holes"]), *beside]))
    if json_path:
        with open(json_path, "w") as fh:
            json.dump({"overrides": overrides, "frames": n_frames, "name": name, **rep}, fh, indent=1)
        print(f"report: {json_path}")


if __name__ == "__main__":
    main()
