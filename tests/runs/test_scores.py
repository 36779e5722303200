"""output.scores (issue 58 item 4): scores.npy holds each point's class distribution (Eq. 16's
normalised row, all zero where nothing reached it), labels.ply / the LAS output / run.rrd carry the
points' top score, margin and entropy, and the run's calibration figures are those of the saved
scores: computed again from the folder they are summary.json's, number for number."""
import json
import math

import numpy as np
import pytest
from conftest import SMALL_DEMO, run_cli

from diffuser_lab.config import ConfigError
from diffuser_lab.method.calibration import confidence, point_confidence, point_rows, stored
from diffuser_lab.runs.records import json_ready
from diffuser_lab.runs.resolve import default_config
from diffuser_lab.runs.scores import calibration_of_run, read_scores


def test_stored_rows_are_each_rows_own_in_any_chunk_of_rows():
    """scores.npy is written in chunks of original points and scored in chunks of annotated ones:
    a row's float16 distribution must not depend on the rows beside it."""
    rng = np.random.default_rng(3)
    Z = (rng.random((5000, 20)) ** 6 * rng.uniform(0.01, 100, (5000, 1))).astype(np.float32)
    Z[7] = 0  # a point nothing reached
    full = stored(Z)
    assert full.dtype == np.float16 and not full[7].any()
    assert np.abs(full[np.arange(5000) != 7].astype(np.float32).sum(1) - 1).max() < 5e-3
    order = rng.permutation(5000)
    parts = np.concatenate([stored(Z[order[a:a + 333]]) for a in range(0, 5000, 333)])
    np.testing.assert_array_equal(parts, full[order])
    rows = rng.integers(0, 5000, 9000)
    import diffuser_lab.method.calibration as cal_mod

    old, cal_mod.CHUNK = cal_mod.CHUNK, 1000
    try:
        got = np.concatenate([p for _, _, p in point_rows(Z, rows, len(rows))])
    finally:
        cal_mod.CHUNK = old
    np.testing.assert_array_equal(got, full[rows])


def test_confidence_is_top_score_margin_and_entropy():
    p = np.array([[0.5, 0.3, 0.2], [0, 0, 0], [0, 1, 0], [0.25, 0.25, 0.5]], np.float16)
    c = confidence(p)
    q = p.astype(np.float64)
    assert c.shape == (4, 3) and c.dtype == np.float32
    np.testing.assert_allclose(c[0], [q[0, 0], q[0, 0] - q[0, 1], -sum(x * math.log(x) for x in q[0])], rtol=1e-6)
    assert c[1, 0] == 0 and c[1, 1] == 0 and math.isnan(c[1, 2])  # no distribution
    assert c[2].tolist() == [1.0, 1.0, 0.0]  # one class: certain
    assert c[3, 1] == pytest.approx(0.25) and c[3, 2] == pytest.approx(1.5 * math.log(2), rel=1e-6)
    np.testing.assert_array_equal(point_confidence(p.astype(np.float32), np.array([3, 0])), c[[3, 0]])


def test_scores_run_in_the_global_protocol_only():
    assert default_config(**{"output.scores": True}).output.scores
    for protocol in ("single_frame", "online"):
        with pytest.raises(ConfigError, match=rf"^output\.scores=true: .* protocol=global_3d, not protocol={protocol}$"):
            default_config(**{"output.scores": True, "protocol.name": protocol})


def _figures(d: dict) -> dict:
    """As summary.json holds them (JSON, NaN -> null)."""
    return json.loads(json.dumps(json_ready(d)))


@pytest.mark.slow
@pytest.mark.parametrize("method, extra", [("diffuser", ["scene.voxel_size=0.1"]), ("bayesian", [])])
def test_a_scores_run_saves_its_distributions_and_its_calibration_is_theirs(tmp_path, method, extra):
    from plyfile import PlyData

    d = tmp_path / "run"
    p = run_cli(*SMALL_DEMO, *extra, f"method={method}", "output.scores=true", "output.clouds=[las]",
                "record=off", "split=test", "output.quiet=true", f"hydra.run.dir={d}")
    assert p.returncode == 0, p.stderr[-2000:]
    summary = json.loads((d / "summary.json").read_text())
    assert summary["split"] == "test" and summary["files"]["scores"] == "scores.npy"
    scores, gt, _ = read_scores(d)
    labels = np.load(d / "labels.npy")
    n, c = summary["n_points"], summary["n_classes"]
    assert scores.shape == (n, c) and scores.dtype == np.float16 and gt.shape == (n,)
    p32 = np.asarray(scores, np.float32)
    top = p32.max(1)
    # Eq. 16: the label is the argmax of the row (float16 rounding keeps the order, may make ties);
    # a point nothing reached has an all-zero row and no label
    lab = labels >= 0
    assert (p32[np.flatnonzero(lab), labels[lab]] == top[lab]).all()
    assert (top[~lab] == 0).all() and (top[lab] > 0).all() and (~lab).any() == (method == "bayesian")
    assert np.abs(p32[lab].sum(1) - 1).max() < 5e-3
    # the figures computed from the folder are summary.json's, and they are the saved rows' (changed rows: others)
    mine = summary["metrics"]["calibration"][method]
    assert _figures(calibration_of_run(d)) == mine
    assert calibration_of_run(d, temperature=2.0)["nll"] != mine["nll"]
    wrong = np.load(d / "scores.npy")[:, ::-1].copy()
    np.save(d / "scores.npy", wrong)
    assert _figures(calibration_of_run(d))["brier"] != mine["brier"]
    # the confidence of labels.ply and labels.las: of the saved rows (run.rrd's: tests/recording/test_viewer.py)
    conf = confidence(scores)
    v = PlyData.read(str(d / "labels.ply"))["vertex"].data
    import laspy

    las = laspy.read(str(d / "labels.las"))
    for j, name in enumerate(("confidence", "margin", "entropy")):
        np.testing.assert_array_equal(np.asarray(v[name]), conf[:, j])
        np.testing.assert_array_equal(np.asarray(las[name]), conf[:, j])


@pytest.mark.slow
def test_the_default_run_writes_no_scores(tmp_path):
    d = tmp_path / "run"
    p = run_cli(*SMALL_DEMO, "record=off", "output.quiet=true", f"hydra.run.dir={d}")
    assert p.returncode == 0, p.stderr[-2000:]
    summary = json.loads((d / "summary.json").read_text())
    assert not (d / "scores.npy").exists() and "scores" not in summary["files"] and summary["split"] is None
    assert "scores" not in summary["timings_s"]
    with pytest.raises(FileNotFoundError, match="no scores.npy, expected a run with output.scores=true"):
        read_scores(d)
