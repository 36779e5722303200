"""Paired comparisons (analysis/paired.py) on constructed data whose answer is known: the sign-flip
p-value's exact values, the bootstrap interval's, the matching of runs to their reference at the same
seed and scene, the common support's scores, the splits' one line. The end-to-end report on a sweep:
tests/analysis/test_sweep_analysis.py."""
import json
from pathlib import Path

import numpy as np
import pytest

from analysis import paired
from analysis.runs import Run


# --- the statistics ------------------------------------------------------------------------------

def test_a_constant_shift_over_six_pairs_has_p_two_in_64_and_a_point_interval():
    d = paired.paired_difference([1.0] * 6)
    assert d.n == 6 and d.mean == 1.0 and (d.low, d.high) == (1.0, 1.0)
    assert d.p == 2 / 64 and d.exact  # only all-plus and all-minus of the 64 sign flips are as extreme
    assert d.significant and d.why == ""
    assert d.cell() == "+1.0 [+1.0, +1.0] p 0.031"


def test_no_shift_has_an_interval_around_zero_and_p_one():
    d = paired.paired_difference([0.5, -0.5, 0.3, -0.3, 0.1, -0.1])
    assert d.mean == pytest.approx(0.0, abs=1e-15)
    assert d.low < 0 < d.high and d.p == 1.0
    assert not d.significant and d.why == "interval crosses 0" and d.cell().endswith(" n.s.")


def test_the_sign_flip_p_counts_the_flips_as_extreme_as_the_data():
    # |d| = 1..6, sum 21; a flip set S gives 21 - 2 sum(S): >= the observed 19 for S = {} or {1}: 2 of 64
    assert paired.paired_difference([-1, 2, 3, 4, 5, 6]).p == 2 * 2 / 64
    assert paired.paired_difference([1, -1, 1, -1]).p == 1.0


def test_three_pairs_of_one_sign_are_not_significant_by_design():
    d = paired.paired_difference([5.6, 5.9, 4.8])
    assert d.low > 0 and d.p == 0.25  # 2 / 2^3: the smallest p three pairs can give
    assert not d.significant and d.why == "p 0.25 >= 0.05 (smallest p at 3 pairs: 0.25)"


def test_the_percentile_interval_of_two_pairs_is_their_range():
    # resampled means of (0, 10): 0, 5, 10 with probabilities 1/4, 1/2, 1/4: the 2.5th and 97.5th percentiles
    d = paired.paired_difference([0.0, 10.0])
    assert (d.low, d.high) == (0.0, 10.0) and d.p == 1.0


def test_many_pairs_draw_sign_flips_and_the_same_differences_get_the_same_interval():
    d = paired.paired_difference([1.0] * 20)
    assert not d.exact and d.p < 1e-3  # 9,999 random flips of 2^20
    noisy = np.sin(np.arange(20.0)) + 0.4
    a, b = paired.paired_difference(noisy), paired.paired_difference(list(noisy))
    assert (a.low, a.high, a.p) == (b.low, b.high, b.p) and not a.exact and a.low < a.mean < a.high


def test_one_pair_and_none_have_no_interval():
    one, none = paired.paired_difference([3.0]), paired.paired_difference([None, float("nan")])
    assert (one.n, one.low, one.p) == (1, None, 1.0) and one.why == "1 pair" and one.cell() == "+3.0 p 1 n.s."
    assert none.n == 0 and none.cell() == "-"


# --- matching runs -------------------------------------------------------------------------------

def _run(k: str, seed: int, miou: float, tmp: Path = Path("/nonexistent"), **summary) -> Run:
    s = {"status": "ok", "metrics": {"miou": miou, "accuracy": 50.0 + miou / 2, "coverage": 100.0,
                                     "per_class_iou": {"wall": miou + 1, "floor": miou - 1}},
         "baseline": {"bayesian": {"miou": miou - 10}}, **summary}
    return Run(path=tmp / f"k{k}_s{seed}", summary=s, overrides={"graph.k": k, "seed": str(seed)})


def _sweep(shifts: dict, seeds=range(6)) -> list[Run]:
    return [_run(k, s, 60.0 + shift + 0.5 * s) for k, shift in shifts.items() for s in seeds]


def test_each_configuration_is_paired_with_the_default_at_the_same_seed():
    runs = _sweep({"8": -2.0, "24": 0.0, "48": 1.5})
    cmp = paired.compare_configurations(runs)
    assert cmp.reference == {"graph.k": "24"} and "default run" in cmp.how
    assert [r.config for r in cmp.rows] == [{"graph.k": "8"}, {"graph.k": "48"}]
    k8, k48 = cmp.rows
    assert k8.diffs["miou"].mean == pytest.approx(-2.0) and k8.diffs["miou"].p == 2 / 64
    assert k48.diffs["accuracy"].mean == pytest.approx(0.75) and k48.diffs["coverage"].mean == 0.0
    assert k8.per_class["wall"].mean == pytest.approx(-2.0) and k8.per_class["wall"].n == 6
    assert cmp.unmatched == [] and "miou_common" not in cmp.metrics  # no labels: no common support


def test_a_run_without_a_partner_is_listed_not_dropped_silently():
    runs = [r for r in _sweep({"8": -2.0, "24": 0.0}) if not (r.overrides["graph.k"] == "24" and r.overrides["seed"] == "5")]
    (row,) = paired.compare_configurations(runs).rows
    assert row.diffs["miou"].n == 5 and row.pairs[-1][0] == "4"
    unmatched = paired.compare_configurations(runs).unmatched
    assert len(unmatched) == 1 and unmatched[0].startswith("`k8_s5`: no run of `graph.k=24` at seed=5")


def test_a_named_reference_and_the_keys_held_equal():
    runs = [Run(r.path, r.summary, {**r.overrides, "graph.use_normals": n})
            for n in ("true", "false") for r in _sweep({"8": -2.0, "16": 0.0}, seeds=range(3))]
    cmp = paired.compare_configurations(runs)  # normals' default (true) is swept, k's (24) is not
    assert cmp.reference == {"graph.use_normals": "true"} and cmp.held == ["graph.k"]
    assert {tuple(c.items()) for c in cmp.references} == {(("graph.k", "8"), ("graph.use_normals", "true")),
                                                          (("graph.k", "16"), ("graph.use_normals", "true"))}
    cmp = paired.compare_configurations(runs, {"graph.k": "16"})
    assert cmp.held == ["graph.use_normals"] and len(cmp.rows) == 2
    assert all(r.reference["graph.k"] == "16" and r.reference["graph.use_normals"] == r.config["graph.use_normals"]
               for r in cmp.rows)
    with pytest.raises(ValueError, match=r"^--reference graph.k=12: no run has graph.k=12 \(values: 8, 16\)$"):
        paired.compare_configurations(runs, {"graph.k": "12"})
    with pytest.raises(ValueError, match=r"^--reference graph.sigma_s=1: graph.sigma_s is not a key the runs vary"):
        paired.compare_configurations(runs, {"graph.sigma_s": "1"})
    with pytest.raises(ValueError, match="expected KEY=VALUE"):
        paired.parse_assignments(["graph.k"])


def test_the_bayesian_baseline_of_the_same_runs():
    (cfg8, d8), (cfg24, _) = paired.baseline_differences(_sweep({"8": -2.0, "24": 0.0}))
    assert cfg8 == {"graph.k": "8"} and cfg24 == {"graph.k": "24"}
    assert d8["miou"].mean == pytest.approx(10.0) and d8["miou"].p == 2 / 64 and d8["miou"].n == 6


def test_runs_of_both_splits_are_refused_in_one_table_unless_asked():
    runs = [_run("8", s, 50.0, split="validation" if s < 3 else "test") for s in range(9)]
    with pytest.raises(ValueError) as err:
        paired.check_splits(runs, mix=False)
    assert str(err.value) == ("runs of the validation and test splits in one table (3 validation, 6 test); "
                              "pass --mix-splits to allow")
    paired.check_splits(runs, mix=True)
    paired.check_splits(runs[3:], mix=False)  # one split: fine


def test_the_split_is_a_column_of_the_tables_when_a_run_names_one():
    from diffuser_lab.runs.results import aggregate, run_rows

    runs = [_run("8", s, 50.0 + s, split="validation" if s < 2 else "test") for s in range(5)]
    cols, rows = aggregate(runs)
    assert cols[:2] == ["graph.k", "split"]
    assert [(r["split"], r["runs"], r["miou"]) for r in rows] == [("test", 3, 53.0), ("validation", 2, 50.5)]
    assert "split" in run_rows(runs)[0]
    assert "split" not in aggregate([_run("8", 1, 1.0)])[0]  # no run names one: no column


# --- the common support --------------------------------------------------------------------------

def _folder(tmp: Path, name: str, k: str, labels, bayes, gt, seed: int = 0) -> Run:
    d = tmp / name
    d.mkdir()
    np.save(d / "labels.npy", np.asarray(labels, np.int16))
    np.save(d / "bayesian_labels.npy", np.asarray(bayes, np.int16))
    np.save(d / "gt_labels.npy", np.asarray(gt, np.int16))
    s = {"status": "ok", "n_classes": 3, "metrics": {"miou": 1.0}, "overrides": [f"graph.k={k}", f"seed={seed}"]}
    (d / "summary.json").write_text(json.dumps(s))
    return Run(path=d, summary=s, overrides={"graph.k": k, "seed": str(seed)})


def test_the_common_support_scores_every_method_on_the_points_all_of_them_label(tmp_path):
    from diffuser_lab.method.metrics import score

    gt = np.array([0, 0, 1, 1, 2, 2, 0, 1])
    a = np.array([0, 1, 1, 1, 2, -1, 0, 1])  # leaves point 5 unlabelled
    b = np.array([0, 0, 1, 2, 2, 2, -1, 1])  # leaves point 6
    bayes = np.array([0, 0, -1, 1, 2, 2, 0, 1])  # leaves point 2
    runs = [_folder(tmp_path, "a", "8", a, bayes, gt), _folder(tmp_path, "b", "24", b, bayes, gt)]
    sup = paired.common_support(runs)
    keep = np.array([1, 1, 0, 1, 1, 0, 0, 1], bool)
    assert sup.sizes == [("seed=0", 5, 8)] and sup.baseline
    names = ["0", "1", "2"]
    for r, lab in zip(runs, (a, b)):
        want = score(lab[keep], gt[keep], names)
        assert sup.scores[r.path]["miou_common"] == pytest.approx(want["miou"])
        assert sup.scores[r.path]["accuracy_common"] == pytest.approx(want["accuracy"])
        assert sup.scores[r.path]["bayesian_miou_common"] == pytest.approx(score(bayes[keep], gt[keep], names)["miou"])
    assert sup.line().startswith("Common support: the points that every compared run and every run's Bayesian "
                                 "baseline label (per seed and scene): 62.5 % of the points (5 of 8 at seed=0)")
    cmp = paired.compare_configurations(runs, support=sup)
    assert cmp.rows[0].diffs["miou_common"].mean == pytest.approx(
        score(a[keep], gt[keep], names)["miou"] - score(b[keep], gt[keep], names)["miou"])


def test_a_bad_labels_file_is_one_line_naming_it(tmp_path):
    run = _folder(tmp_path, "a", "8", [0, 1], [0, 1], [0, 1])
    np.save(run.path / "labels.npy", np.zeros((2, 2), np.float32))
    with pytest.raises(ValueError, match=r"labels.npy: shape \(2, 2\) dtype float32, expected \(2,\) integer class ids"):
        paired.common_support([run])


def test_the_paired_command_prints_the_interval_and_why(capsys):
    assert paired.main(["--x", "54.4,54.7,53.6", "--y", "42.3,39.1,40.1"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("x - y over 3 pairs: +13.7 [+12.1, +15.6] p 0.25 n.s.")
    assert out[1] == "not significant: p 0.25 >= 0.05 (smallest p at 3 pairs: 0.25)"
    assert paired.main(["--x", "1,2", "--y", "1"]) == 2
    assert capsys.readouterr().err.strip() == "paired: error: --x has 2 values, --y 1: expected one pair per unit"
