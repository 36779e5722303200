"""``python -m diffuser_lab.cli.consistency [hydra overrides]``: the frames' 2D mIoU and the view
consistency of their predictions (:func:`diffuser_lab.method.consistency.view_consistency`; what
docs/simulated-network.md calibrates against)."""
from __future__ import annotations

import sys
from typing import Sequence

from hydra import compose, initialize_config_dir

from diffuser_lab.cli.main import config_dir
from diffuser_lab.config import register, to_object
from diffuser_lab.method.consistency import view_consistency
from diffuser_lab.data.predictions import with_predictions
from diffuser_lab.data.taxonomy import resolve_taxonomy
from diffuser_lab.method.metrics import confusion_matrix, scores_from_confusion
from diffuser_lab.runs.pipeline import load_scene
from diffuser_lab.runs.resolve import resolve


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    register()
    with initialize_config_dir(config_dir=config_dir(), version_base="1.3", job_name="consistency"):
        cfg = resolve(to_object(compose("config", overrides=args)))
    scene = load_scene(cfg.scene, resolve_taxonomy(cfg), cfg.depth)  # depth=sensor applies too
    tax = scene.taxonomy
    frames = [f for f in with_predictions(scene.frames, cfg.predictions, tax, scene.name)]
    conf = sum(confusion_matrix(f.labels, f.gt_labels, tax.num_classes) for f in frames)
    m2d = scores_from_confusion(conf, tax.names)["miou"]
    vc = view_consistency(frames, tax.num_classes, tax.names, depth_tol=cfg.evidence.depth_tol)
    print(f"{scene.name} | {len(frames)} frames | 2D mIoU {m2d:.1f} | view consistency (neighbours): "
          f"TC mIoU {vc['tc_miou']:.1f}, TC/2D {vc['tc_miou'] / m2d:.2f}, "
          f"same wrong class {vc['error_agreement']:.1f}%, wrong again {vc['error_overlap']:.1f}%")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
