"""Two run folders compared (diffuser_lab/runs/compare.py) and the figures a summary's hash covers
(runs/report.py figures): on folders written here, no run."""
import copy
import json

import numpy as np

from diffuser_lab.data import inputs
from diffuser_lab.runs.compare import compare, flat_figures, nondeterminism
from diffuser_lab.runs.report import figures

SUMMARY = {
    "status": "ok", "started": "2026-12-07T10:00:00", "overrides": ["graph.k=8"], "kernels": "numba",
    "provenance": {"host": "a", "machine": {"cpu_model": "X", "isa": "avx512"}, "versions": {"numpy": "2.4.6"},
                   "diffuser_lab": {"version": "0.1.0", "commit": "a" * 40, "dirty": False}},
    "metrics": {"miou": 77.0, "per_class_iou": {"wall": 90.5}},
    "timings_s": {"total": 2.0}, "memory": {"peak_rss_gb": 0.4},
    "tiling": {"tiles": [{"id": "0_0", "points": 10, "time_s": 1.5, "node": "n1", "pid": 7, "peak_rss_gb": 0.2}]},
    "online": {"latency_ms": {"median": 9.0}, "frames": [{"changed": 5, "steps_ms": 3.0}]},
    "inputs": {"config_sha256": "c" * 64, "list": "inputs.tsv"},
    "outputs": {"files": {"labels.npy": {"size": 1, "sha256": "1" * 64}}},
}


def _run(path, summary, labels, entries):
    path.mkdir()
    (path / "summary.json").write_text(json.dumps(summary))
    np.save(path / "labels.npy", np.asarray(labels, np.int16))
    inputs.write_list(path / "inputs.tsv", entries)
    return path


def test_figures_leave_out_how_where_and_when_a_run_ran():
    f = figures(SUMMARY)
    assert set(f) == {"metrics", "tiling", "online"}
    assert f["tiling"]["tiles"] == [{"id": "0_0", "points": 10}] and f["online"] == {"frames": [{"changed": 5}]}
    other = copy.deepcopy(SUMMARY)
    other["tiling"]["tiles"][0].update(time_s=9.0, node="n2", pid=8)
    other["timings_s"]["total"] = 5.0
    assert figures(other) == f
    other["metrics"]["per_class_iou"]["wall"] = 90.6
    assert flat_figures(other)["metrics.per_class_iou.wall"] == 90.6 != flat_figures(SUMMARY)["metrics.per_class_iou.wall"]


def test_compare_counts_labels_figures_outputs_and_what_changed(tmp_path):
    e = [inputs.Entry("frames", "/d/0.png", 5, "a" * 64), inputs.Entry("mesh", "/d/m.ply", 9, "b" * 64)]
    old = _run(tmp_path / "old", SUMMARY, [0, 1, 2, -1], e)
    same = _run(tmp_path / "same", SUMMARY, [0, 1, 2, -1], e)
    c = compare(old, same)
    assert c.identical and c.labels_differ == 0 and c.n_points == 4 and not c.changed and c.figures == 5
    s = copy.deepcopy(SUMMARY)
    s["metrics"]["miou"] = 76.5
    s["provenance"]["diffuser_lab"]["commit"] = "b" * 40
    s["provenance"]["versions"]["numpy"] = "2.3.1"
    s["kernels"] = "numpy"
    s["outputs"]["files"] = {"labels.npy": {"size": 1, "sha256": "2" * 64},
                             "labels_ros2/labels_ros2.mcap": {"size": 3, "sha256": "4" * 64}}
    s2 = copy.deepcopy(SUMMARY)
    s2["outputs"]["files"]["labels_ros2/labels_ros2.mcap"] = {"size": 3, "sha256": "3" * 64}
    (old / "summary.json").write_text(json.dumps(s2))
    edited = [inputs.Entry("frames", "/d/0.png", 5, "f" * 64)]
    new = _run(tmp_path / "new", s, [0, 1, 3, 3], edited)
    c = compare(old, new)
    assert not c.identical and c.labels_differ == 2
    assert c.figures_differ == [("metrics.miou", 77.0, 76.5)]
    assert c.outputs_differ == ["labels.npy"] and c.outputs_timed == ["labels_ros2/labels_ros2.mcap"]
    assert c.changed["commit"] == [("commit", "a" * 12, "b" * 12)] and c.changed["versions"] == [("numpy", "2.4.6", "2.3.1")]
    assert c.changed["kernels"] == [("kernels", "numba", "numpy")] and "machine" not in c.changed
    assert [x.path for x in c.inputs["changed"]] == ["/d/0.png"] and [x.path for x in c.inputs["gone"]] == ["/d/m.ply"]
    short = _run(tmp_path / "short", SUMMARY, [0, 1], e)
    assert compare(old, short).labels_differ == -1


def test_what_cannot_give_the_same_labels_twice():
    assert nondeterminism({"protocol": {"name": "online"}, "online": {"rate": 30.0}}).startswith("online.rate=30:")
    assert nondeterminism({"protocol": {"name": "online"}, "online": {"rate": 0.0}}) is None
    assert nondeterminism({"protocol": {"name": "global_3d"}, "online": {"rate": 30.0}}) is None
    assert "follow" in nondeterminism({"protocol": {"name": "online"}, "scene": {"options": {"follow": True}}})
