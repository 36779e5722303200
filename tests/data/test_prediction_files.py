"""A 2D network's outputs from files: mapped label PNGs (unmapped counted) and probabilities."""

import numpy as np
from PIL import Image

from diffuser_lab.config import default_config
from diffuser_lab.data.scene import IGNORE, SCANNET20, SCANNET20_NYU40_IDS
from diffuser_lab.runs.pipeline import run


def test_label_pngs_in_nyu40_are_mapped_and_unmapped_counted(small_demo_scene, tmp_path):
    to_nyu = np.array(SCANNET20_NYU40_IDS, np.uint16)
    n_otherprop = 0
    for i, f in enumerate(small_demo_scene.frames):
        ids = np.where(f.gt_labels == IGNORE, 0, to_nyu[np.maximum(f.gt_labels, 0)]).astype(np.uint16)
        if i == 0:
            ids[:10, :10] = 40  # otherprop: not a ScanNet-20 class
            n_otherprop = 100
        Image.fromarray(ids).save(tmp_path / f"{f.name}.png")
    cfg = default_config(**{"predictions.source": "files", "predictions.folder": str(tmp_path),
                            "predictions.mapping": "nyu40_to_scannet20", "solver.max_iter": 60})
    res = run(cfg, scene=small_demo_scene)
    zero_ids = sum(int((f.gt_labels == IGNORE).sum()) for f in small_demo_scene.frames)
    assert res.predictions_stats["label_files"] == len(small_demo_scene.frames)
    assert res.predictions_stats["unmapped_pixels"] == zero_ids + n_otherprop - int(
        (small_demo_scene.frames[0].gt_labels[:10, :10] == IGNORE).sum())
    assert res.predictions_2d["miou"] > 95  # the files hold (almost) the ground truth


def test_probability_files_are_soft_evidence(small_demo_scene, tmp_path):
    C = SCANNET20.num_classes
    for f in small_demo_scene.frames:
        p = np.full(f.shape + (C,), 0.01, np.float32)
        lab = np.maximum(f.gt_labels, 0)
        np.put_along_axis(p, lab[..., None].astype(np.int64), 0.8, axis=2)
        np.save(tmp_path / f"{f.name}.npy", np.moveaxis(p, 2, 0))  # (C, H, W) is accepted too
    cfg = default_config(**{"predictions.source": "files", "predictions.folder": str(tmp_path),
                            "solver.max_iter": 60})
    res = run(cfg, scene=small_demo_scene)
    assert res.predictions_stats["probability_files"] == len(small_demo_scene.frames)
    m = res.evidence.mass
    links = res.evidence.links
    np.testing.assert_allclose(m.sum(1), links, rtol=1e-4)  # each linked pixel carries a mass of 1
    assert m.max() < links.max()  # ... spread over the classes, not one-hot
    hard = run(default_config(**{"predictions.source": "gt", "solver.max_iter": 60}), scene=small_demo_scene)
    assert np.mean(res.bayesian_labels == hard.bayesian_labels) > 0.99  # argmax of the sums as with gt


def test_layout_auto_takes_d_from_the_run_s_queries(tmp_path):
    """Issue 52 item 5: a (30, 40, 64) patch grid is (h, w, D) when the run's queries say D = 64 (auto
    alone took the smallest axis: D = 30, and the run stopped on the queries' D); without queries, the
    first frame's map decides D by the auto rule; every frame must have it."""
    import pytest

    from diffuser_lab.data.embeddings import write_queries
    from diffuser_lab.data.predictions import with_predictions
    from diffuser_lab.data.prediction_files import load_feature_prediction
    from diffuser_lab.data.scene import Frame

    rng = np.random.default_rng(0)
    frames = [Frame(f"f{i}", np.eye(3), np.eye(4), np.ones((60, 80), np.float32)) for i in range(3)]
    for f in frames:  # loop over frames: one (30, 40, 64) map each
        np.save(tmp_path / f"{f.name}.npy", rng.random((30, 40, 64)).astype(np.float16))
    assert load_feature_prediction(tmp_path / "f0.npy").shape == (40, 64, 30)  # auto alone: D = 30
    assert load_feature_prediction(tmp_path / "f0.npy", dim=64).shape == (30, 40, 64)
    queries = write_queries(tmp_path / "q.npz", list(SCANNET20.names), rng.random((SCANNET20.num_classes, 64)))
    cfg = default_config(**{"predictions.source": "features", "predictions.embeddings": "files",
                            "predictions.folder": str(tmp_path), "predictions.queries": str(queries)}).predictions
    assert [f.features.shape for f in with_predictions(frames, cfg, SCANNET20)] == [(30, 40, 64)] * 3
    np.save(tmp_path / "f2.npy", rng.random((30, 40, 32)).astype(np.float16))  # another D: one line naming it
    with pytest.raises(ValueError, match=r"f2\.npy: features of shape \(40, 32, 30\) \(auto\), expected D = 64"):
        with_predictions(frames, cfg, SCANNET20)[2]
