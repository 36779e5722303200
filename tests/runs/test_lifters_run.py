"""The lifting rules of 2024-2026 as registry entries (method=weighted, median, topk, vote), the
Tikhonov closed form (solver.tikhonov) and the affinity graph (graph.affinity) in the global and the
single-frame protocol, for labels and features; the bench's experiment and its table."""
import json

import numpy as np
import pytest

from diffuser_lab.config import ConfigError
from diffuser_lab.method import fusion
from diffuser_lab.runs.pipeline import run
from diffuser_lab.runs.resolve import default_config

TINY = {"scene.options.n_views": 6, "scene.options.point_spacing": 0.12, "record.mode": "off",
        "solver.max_iter": 40}
FEATURES = {"predictions.source": "features", "predictions.dim": 32}
RULES = [name for name, m in fusion.METHODS.items() if m.evidence == fusion.RULE]


@pytest.fixture(scope="module")
def tiny_scene():
    from diffuser_lab.runs.pipeline import load_scene

    return load_scene(default_config(**TINY).scene)


def test_the_four_rules_are_registry_entries():
    assert sorted(RULES) == ["median", "topk", "vote", "weighted"]
    assert all(not fusion.METHODS[r].graph and not fusion.METHODS[r].table_ii for r in RULES)


@pytest.mark.slow
@pytest.mark.parametrize("rule", RULES)
def test_each_rule_labels_labels_and_features_in_the_global_protocol(rule, tiny_scene):
    for extra in ({}, FEATURES):
        res = run(default_config(**TINY, **extra, **{"method.name": rule}), scene=tiny_scene)
        assert res.method == rule and res.diffusion is None
        seen = res.evidence.seen[res.rows]
        assert (res.labels[seen] >= 0).all() and (res.labels[~seen] < 0).all()  # no graph: evidence only
        # the rule lifts the same evidence as the Bayesian baseline (no graph): its mIoU near that one's and
        # its coverage the same (measured 2026-12-07: 22.5-24.4 against 24.1 / 24.4, coverage 44.8 both)
        bay = res.baseline["bayesian"]
        assert abs(res.metrics["miou"] - bay["miou"]) < 2.5 and res.metrics["miou"] > 20, (res.metrics["miou"], bay)
        assert res.metrics["coverage"] == bay["coverage"] and rule in res.metrics["calibration"]
        if extra and rule == "vote":  # class votes, no feature of its own
            assert res.space.method is None
        elif extra:
            assert res.space.method.shape == (res.work_points.shape[0], 32)


@pytest.mark.slow
def test_vote_on_one_hot_labels_is_the_bayesian_vote_and_topk1_is_the_best_view(tiny_scene):
    """Hard labels: a vote per view is the Bayesian sum of one-hot labels; features: the top view
    (k = 1) is the best-view baseline."""
    vote = run(default_config(**TINY, **{"method.name": "vote"}), scene=tiny_scene)
    np.testing.assert_array_equal(vote.labels, vote.bayesian_labels)
    top1 = run(default_config(**TINY, **FEATURES, **{"method.name": "topk", "method.top_k": 1}), scene=tiny_scene)
    best = top1.space.labels(top1.space.best_view)
    assert (top1.space.labels(top1.space.method) == best).mean() > 0.999
    assert abs(top1.metrics["miou"] - top1.baseline["best_view"]["miou"]) < 0.2


@pytest.mark.slow
def test_tikhonov_and_affinity_run_on_the_graph_and_change_nothing_by_default(tiny_scene):
    from diffuser_lab.method.evidence import Evidence
    from diffuser_lab.runs.pipeline import graph_variant

    cfg = default_config(**TINY)
    ev = Evidence(mass=np.ones((3, 2), np.float32), links=np.ones(3, np.int32))
    assert graph_variant(None, ev, cfg) is ev  # the defaults (affinity none, tikhonov 0): untouched
    plain = run(cfg, scene=tiny_scene)
    closed = run(default_config(**TINY, **{"solver.name": "exact", "solver.tikhonov": 1.0}), scene=tiny_scene)
    huge = run(default_config(**TINY, **{"solver.name": "exact", "solver.tikhonov": 1e6}), scene=tiny_scene)
    mass = huge.evidence.mass
    top2 = np.sort(mass, axis=1)[:, -2:]
    clear = (top2[:, 1] > top2[:, 0])[huge.rows]  # evidence with one largest class (no tie for the graph to break)
    # t -> inf: each point with evidence takes its own average (the Bayesian labels)
    assert clear.sum() > 100 and (huge.labels[clear] == huge.bayesian_labels[clear]).mean() > 0.995
    # t = 1 changes the solution of t = 0 (the same exact solver): labels moved on 31 % of the points, mIoU 33.7
    # -> 42.5 (measured 2026-12-07)
    bare = run(default_config(**TINY, **{"solver.name": "exact"}), scene=tiny_scene)
    assert not np.allclose(closed.diffusion.Z, bare.diffusion.Z, rtol=1e-3, atol=0)
    assert (closed.labels != bare.labels).mean() > 0.1 and closed.metrics["miou"] > bare.metrics["miou"] + 4
    assert closed.metrics["coverage"] > 95 and closed.metrics["miou"] > 35  # 99.0 and 42.5
    # affinity: the same edges, 38 % of their weights lowered by the features' similarity factor (<= 1)
    feat = run(default_config(**TINY, **FEATURES), scene=tiny_scene)
    aff = run(default_config(**TINY, **FEATURES, **{"graph.affinity": "features"}), scene=tiny_scene)
    np.testing.assert_array_equal(aff.graph.neighbors, feat.graph.neighbors)
    wa, wf = aff.graph.weights, feat.graph.weights
    assert (wa <= wf).all() and 0.2 < (wa < wf).mean() < 0.6, (wa < wf).mean()
    assert (aff.labels != feat.labels).mean() > 0.02 and aff.metrics["miou"] > 35  # 5.5 % moved; mIoU 41.1 (40.7)
    with pytest.raises(ValueError, match="graph.affinity=colour: the scene's cloud has no colours"):
        run(default_config(**TINY, **{"graph.affinity": "colour"}), scene=tiny_scene)


def test_rules_and_variants_outside_the_two_protocols_are_one_error():
    with pytest.raises(ConfigError, match="method.name=median: runs in protocol=global_3d or single_frame"):
        default_config(**{"method.name": "median", "protocol.name": "online"})
    with pytest.raises(ConfigError, match="graph.affinity=colour, solver.tikhonov=2: runs in"):
        default_config(**{"graph.affinity": "colour", "solver.tikhonov": 2.0, "protocol.name": "tiled"})


@pytest.mark.slow
def test_single_frame_rows_of_the_chosen_rule(tiny_scene):
    from diffuser_lab.runs.report import single_frame_summary
    from diffuser_lab.runs.single_frame import single_frame

    sf = single_frame(default_config(**TINY, **{"method.name": "median", "protocol.max_targets": 2,
                                                "protocol.window": 3}), scene=tiny_scene)
    rows = {(r["method"], r["views"]): r for r in sf.rows}
    assert list(rows) == [("direct", 1), ("ldls", 1), ("bayesian", 1), ("bayesian", 3), ("diffuser", 1),
                          ("diffuser", 3), ("median", 1), ("median", 3)]
    assert rows[("median", 1)]["miou"] == pytest.approx(rows[("bayesian", 1)]["miou"], abs=1e-9)  # one view
    s = single_frame_summary(sf)
    assert s["method"] == "median" and s["metrics"]["miou"] == rows[("median", 3)]["miou"]
    plain = single_frame(default_config(**TINY, **{"protocol.max_targets": 2, "protocol.window": 3}),
                         scene=tiny_scene)
    assert [r["method"] for r in plain.rows].count("median") == 0  # not a Table II row by default
    feat = single_frame(default_config(**TINY, **FEATURES, **{"method.name": "vote", "protocol.max_targets": 2,
                                                              "protocol.window": 3, "graph.affinity": "features",
                                                              "solver.tikhonov": 0.5}), scene=tiny_scene)
    assert {("vote", 3), ("best_view", 3)} <= {(r["method"], r["views"]) for r in feat.rows}


def test_memory_snapshot_sees_this_jobs_peak():
    from diffuser_lab.runs import memory

    import mmap

    if not memory.reset_peak():
        pytest.skip("/proc/self/clear_refs cannot reset the high-water mark here (Linux >= 4.0 can): the "
                    "process's peak is reported, which no job can reset")
    block = mmap.mmap(-1, 64 * 2**20)  # 64 MB of fresh pages (a freed heap may hold resident ones)
    block.write(b"x" * len(block))
    s = memory.snapshot()
    block.close()
    assert s["source"] == "VmHWM since the job's start"
    assert s["peak_rss_gb"] >= s["start_rss_gb"] + 0.05  # the block's 0.0625 GB
    memory.reset_peak()  # the next job's peak: the block is gone from it
    assert memory.snapshot()["peak_rss_gb"] < s["peak_rss_gb"] - 0.05


@pytest.mark.slow  # the report draws its plots (matplotlib): seconds
def test_the_lifters_report_has_one_row_per_rule_with_its_columns(tmp_path):
    from analysis.report import report

    for i, (lifter, pred, seed) in enumerate((a, p, s) for a in ("average", "median") for p in ("realistic", "features")
                                             for s in (0, 1)):
        d = tmp_path / "lifters" / f"{i}_job"
        d.mkdir(parents=True)
        m = 40.0 + (lifter == "median") + seed
        (d / "summary.json").write_text(json.dumps({
            "status": "ok", "method": "bayesian" if lifter == "average" else lifter, "scene": "demo",
            "overrides": [f"+lifter={lifter}", f"predictions={pred}", f"seed={seed}", "+experiment=lifters"],
            "metrics": {"miou": m, "accuracy": 70.0, "coverage": 80.0,
                        "calibration": {"bayesian" if lifter == "average" else lifter: {"ece": 5.0}}},
            "timings_s": {"total": 2.0, "load": 0.1}, "memory": {"peak_rss_gb": 0.5}, "diffusion": {"iterations": 0}}))
    md = report([str(tmp_path / "lifters")], tmp_path / "out").read_text()
    head = next(line for line in md.splitlines() if line.startswith("| lifter |"))
    assert head == ("| lifter | predictions | miou | accuracy | coverage | ece | total_s | load_s | peak_rss_gb | runs | "
                    "failed |")
    assert ("| median | realistic | 41.5 ± 0.5 | 70.0 ± 0.0 | 80.0 ± 0.0 | 5.0 ± 0.0 | 2.00 ± 0.00 | 0.10 ± 0.00 | "
            "0.50 ± 0.00 | 2 | 0 |") in md
    assert md.startswith("# Experiment lifters")
