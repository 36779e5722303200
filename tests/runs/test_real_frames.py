"""Real sensor depth: ScanNet scene0014_00's 27 real frames (../shared/data/scannet_frames) through
both protocols with the correlated network (``predictions=realistic``), seed 0, at the scene's
default 4 cm voxels, and the rule that carries label-filt to the back-projected points on a
hand-made two-frame example.

Only orderings measured to hold on seed 0 with a margin are asserted (docs/regimes.md "Real frames:
ScanNet scene0014_00" has the 3-seed tables). Not asserted: direct < LDLS (+2.0 on these 8 targets,
+1.5 on all 27, +1.3 over 3 seeds with seed 1 at +0.2; 2026-12-07, LDLS with K = 10 and a 5x5 window) and the global Diffuser >= Bayesian + 6 (seed 0: +2.5; 3 seeds
+8.8 ± 5.5, so seed 0 is the weak one).
"""
import numpy as np
import pytest
from conftest import SHARED, compose

from diffuser_lab.data.capture import carry_frame_labels
from diffuser_lab.data.scene import IGNORE, Frame

SCANNET = SHARED / "data" / "scannet_frames" / "scene0014_00"
needs_scannet = pytest.mark.skipif(not (SCANNET / "_info.txt").is_file(),
                                   reason=f"the real ScanNet frames are absent ({SCANNET})")
REAL = ["scene=scannet_frames", f"scene.options.root={SCANNET}", "predictions=realistic", "seed=0", "record=off",
        "output.labels_ply=false"]
TARGETS = ["protocol.max_targets=8"]  # the first 8 of the 27 frames as targets (13 s instead of 50 s)
N_TARGETS = 8
# Measured on these 8 targets, seed 0, 4 cm voxels (2026-12-07: keyed draws, LDLS with K = 10 and a 5x5
# window): direct 34.4, LDLS 36.4, Bayesian-5 35.9, Diffuser-1 41.9, Diffuser-5 43.3 (2D input 41.7); all 27:
# 39.0, 40.5, 41.4, 42.9, 43.5 (47.0). The gaps asserted are 7.5 (Diffuser-1 - direct), 5.5 (Diffuser-1 -
# LDLS) and 7.5 (Diffuser-5 - Bayesian-5): each asserted >= 3 (the paper's Diffuser-1 - direct is +4.7); on
# all 27 targets they are 3.9, 2.4 and 2.1.
MARGIN = 3.0


def test_carry_rule_on_two_frames():
    """Two 11x11 views of four points at 1 m (the second camera 0.1 m to the right): the rule is one
    vote per pixel that sees a point (projection + depth check), the majority label, ties to the
    lower id; IGNORE pixels and pixels whose depth fails the check cast no vote."""
    pts = np.array([[0, 0, 1], [0.2, 0, 1], [-0.2, 0, 1], [0, 0.2, 1]], np.float32)  # (4, 3) metres
    K = np.array([[10, 0, 5], [0, 10, 5], [0, 0, 1.0]])
    T_b = np.eye(4)
    T_b[0, 3] = -0.1  # world-to-camera of a camera at x = +0.1: the points land 1 px further left
    a_lab = np.full((11, 11), IGNORE, np.int16)
    b_lab = np.full((11, 11), IGNORE, np.int16)
    a_lab[5, 5], a_lab[5, 7], a_lab[7, 5] = 2, 4, 7  # p0, p1, p3 in view A; p2's pixel (5, 3) unlabelled
    b_lab[5, 4], b_lab[5, 6], b_lab[5, 2], b_lab[7, 4] = 2, 5, 6, 9  # p0 agrees, p1 disagrees (5 vs 4)
    b_depth = np.ones((11, 11), np.float32)
    b_depth[7, 4] = 0.5  # something in front of p3 in view B: its label 9 is not p3's
    frames = [Frame("a", K, np.eye(4), np.ones((11, 11), np.float32), gt_labels=a_lab),
              Frame("b", K, T_b, b_depth, gt_labels=b_lab)]
    labels, st = carry_frame_labels(pts, frames, 20, depth_tol=0.05)
    # p0: 2 twice; p1: 4 vs 5, a tie -> the lower id 4; p2: B's 6 only; p3: A's 7 only (B fails the depth check)
    assert labels.tolist() == [2, 4, 6, 7]
    assert st["points_labelled"] == 4 and st["points_disagreeing"] == 1
    assert abs(st["vote_agreement"] - 5 / 6) < 1e-9  # chosen-label votes 2+1+1+1 of 6


@pytest.mark.slow
@needs_scannet
def test_real_frames_global_protocol():
    """Global protocol, all 27 frames, seed 0: Diffuser above Bayesian (measured 44.1 vs 41.6, +2.5;
    asserted with a 1.5-point margin: +1.0), the carried ground truth agrees with 98.9 % of the votes."""
    from diffuser_lab.runs.pipeline import run

    res = run(compose(*REAL))
    g = res.scene.frames.info["gt_from_frames"]
    assert len(res.scene.frames) == 27 and g["points_labelled"] > 0.9 * res.scene.n_points
    assert g["vote_agreement"] > 0.97 and 0 < g["points_disagreeing"] < 0.05 * g["points_labelled"]
    d, b = res.metrics["miou"], res.baseline["bayesian"]["miou"]
    assert d >= b + 1.0, (d, b)
    cal = res.metrics["calibration"]
    assert cal["diffuser"]["nll"] < cal["bayesian"]["nll"] / 2, cal  # measured 0.7 vs 3.8 nats


@pytest.mark.slow
@needs_scannet
def test_real_frames_single_frame_orderings():
    """Single-frame protocol on the first 8 target frames, seed 0: Diffuser-1 beats direct projection
    and LDLS, Diffuser-5 beats Bayesian-5, each by 3 points or more (measured gaps above)."""
    from diffuser_lab.runs.single_frame import single_frame

    sf = single_frame(compose(*REAL, "protocol=single_frame", *TARGETS))
    m = {f"{r['method']}_{r['views']}v": r["miou"] for r in sf.rows}
    assert len(sf.targets) == N_TARGETS and sf.scene.frames.info["cloud"].startswith("back-projected")
    assert m["diffuser_1v"] >= m["direct_1v"] + MARGIN, m
    assert m["diffuser_1v"] >= m["ldls_1v"] + MARGIN, m
    assert m["diffuser_5v"] >= m["bayesian_5v"] + MARGIN, m
    assert m["direct_1v"] < sf.predictions_2d["miou"], m  # 14 % of the pixels have no depth: direct leaves them


@needs_scannet
def test_the_loader_on_the_real_frames():
    """Every frame: the depth intrinsics (for 640x480) at the depth image's size, depth in metres
    (a bathroom: valid depths within 0.3-5 m, median 0.5-3 m), rigid world-to-camera poses, the
    label-filt image resized to the depth image."""
    from diffuser_lab.data.intrinsics import read_intrinsics_file
    from diffuser_lab.runs.pipeline import load_scene

    cfg = compose(*REAL)
    scene = load_scene(cfg.scene)
    Kd, _ = read_intrinsics_file(SCANNET / "intrinsic" / "intrinsic_depth.txt")
    assert len(scene.frames) == 27
    for f in scene.frames:
        assert f.depth.shape == f.gt_labels.shape == (480, 640) and np.allclose(f.K, Kd[:3, :3])
        d = f.depth[f.depth > 0]
        assert 0.3 <= d.min() and d.max() <= 5.0 and 0.5 <= np.median(d) <= 3.0, (f.name, d.min(), d.max())
        R = np.asarray(f.T_cw)[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-5)
        assert abs(np.linalg.det(R) - 1) < 1e-5
