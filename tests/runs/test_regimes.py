"""Issue 18's end-to-end inequalities on the real scene: sensor-like depth and a view-correlated
network (``depth=sensor predictions=realistic``), seed 0, both protocols; each with a margin where
the 3-seed table of docs/regimes.md leaves one. Skipped without ../shared/data."""
from __future__ import annotations

import json

import pytest

from conftest import SHARED, run_cli

MESH = SHARED / "data" / "scannet" / "scene0470_00" / "scene0470_00_vh_clean_2.labels.ply"
pytestmark = [pytest.mark.slow,  # runs of the real scene
              pytest.mark.skipif(not MESH.is_file(), reason=f"the real ScanNet scene is not at {MESH}")]
REGIME = ["scene=scannet0470", "depth=sensor", "predictions=realistic", "seed=0", "record=off"]


def _summary(tmp_path, *extra):
    d = tmp_path / "run"
    p = run_cli(*REGIME, *extra, f"hydra.run.dir={d}")
    assert p.returncode == 0, p.stderr[-2000:]
    return json.loads((d / "summary.json").read_text())


def test_global_protocol_diffuser_beats_bayesian_by_six(tmp_path):
    s = _summary(tmp_path)
    assert s["metrics"]["miou"] >= s["baseline"]["bayesian"]["miou"] + 6.0, s["metrics"]["miou"]
    cal = s["metrics"]["calibration"]
    assert cal["diffuser"]["nll"] < cal["bayesian"]["nll"]  # hard votes put no mass where they are wrong


# Single-frame protocol, this regime, 2026-12-07 (docs/results/regimes.md "Table II's order examined"),
# seeds 0 / 1 / 2: direct 44.7 / 42.3 / 46.5, LDLS 48.2 / 45.9 / 50.4, Bayesian-5 49.2 / 45.8 / 49.5,
# Diffuser-1 50.6 / 48.7 / 52.0, Diffuser-5 55.4 / 52.0 / 55.3. Each gap is asserted on seed 0 with
# the 3 seeds' mean gap less their spread (max - min) as its margin, rounded down to 0.1:
ORDER_MARGINS = {  # (higher row, lower row): margin;  gaps on seeds 0 / 1 / 2, mean, spread
    (("ldls", 1), ("direct", 1)): 3.3,  # +3.54 / +3.65 / +3.91, mean 3.70, spread 0.38 (the paper: +2.5)
    (("diffuser", 1), ("ldls", 1)): 1.0,  # +2.32 / +2.79 / +1.61, mean 2.24, spread 1.18 (the paper: +2.2)
    (("diffuser", 1), ("bayesian", 5)): 0.6,  # +1.38 / +2.96 / +2.50, mean 2.28, spread 1.58 (the paper: +1.4)
    (("diffuser", 5), ("diffuser", 1)): 2.1,  # +4.84 / +3.30 / +3.22, mean 3.79, spread 1.63 (the paper: +1.4)
    (("diffuser", 5), ("bayesian", 5)): 5.5,  # +6.22 / +6.25 / +5.72, mean 6.06, spread 0.53 (the paper: +2.8)
    (("diffuser", 1), ("direct", 1)): 5.0,  # +5.85 / +6.44 / +5.52, mean 5.94, spread 0.92 (the paper: +4.7)
}


def test_single_frame_protocol_has_the_papers_order(tmp_path):
    """The paper's Table II order, direct < LDLS < Bayesian-5 < Diffuser-1 < Diffuser-5 (53.7 < 56.2
    < 57.0 < 58.4 < 59.8), as far as it holds here on all 3 seeds: every inequality but LDLS <
    Bayesian-5, each by the margin of ORDER_MARGINS. Not asserted: Bayesian-5 - LDLS, +0.94 / -0.17 /
    -0.90 on seeds 0 / 1 / 2 (mean -0.04; the paper: +0.8), a tie within the seeds' spread; the
    results page says so."""
    s = _summary(tmp_path, "protocol=single_frame")
    r = {(x["method"], x["views"]): x["miou"] for x in s["rows"]}
    for (hi, lo), margin in ORDER_MARGINS.items():
        assert r[hi] >= r[lo] + margin, (hi, r[hi], lo, r[lo], margin)


def test_filling_pixels_without_depth_is_a_named_option(tmp_path):
    """protocol.fill_missing_depth (not the paper's protocol) labels the pixels sensor depth left
    empty from their nearest pixel with depth: every row scores at least as well on this scene,
    and the run says it is not the paper's protocol."""
    d = tmp_path / "filled"
    p = run_cli(*REGIME, "protocol=single_frame", "protocol.max_targets=8", "protocol.fill_missing_depth=true",
                f"hydra.run.dir={d}")
    assert p.returncode == 0, p.stderr[-2000:]
    assert "not the paper's protocol" in p.stdout
    filled = json.loads((d / "summary.json").read_text())
    plain = _summary(tmp_path, "protocol=single_frame", "protocol.max_targets=8")
    assert filled["fill_missing_depth"] is True and plain["fill_missing_depth"] is False
    for a, b in zip(filled["rows"], plain["rows"]):
        assert (a["method"], a["views"]) == (b["method"], b["views"])
        assert a["accuracy"] > b["accuracy"], (a["method"], a["views"], a["accuracy"], b["accuracy"])
