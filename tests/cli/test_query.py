"""``diffuser-lab-query``: a features run folder made with numpy (no pipeline) relabelled with a
query file or an encoder; the table, the files, earlier queries kept, and one line for bad input."""
import json
import subprocess
import sys
import tomllib

import numpy as np
import pytest
from conftest import ROOT

from diffuser_lab.cli.query import main
from diffuser_lab.data.embeddings import prototypes, write_queries
from diffuser_lab.data.scene import IGNORE
from diffuser_lab.method.queries import Queries
from diffuser_lab.runs.query import query_run, read_run, table

NAMES = ["wall", "floor", "chair", "table", "sofa"]
N, D = 3000, 64
ENCODER = "diffuser_lab.data.embeddings.text_encoder"


def make_run(folder, *, dim=D, gt=True, best_view=True, seed=0):
    """A features run as the pipeline leaves it: Diffuser's features are the clean labels'
    prototypes (zero rows where nothing reached the point), the average baseline's are noisy."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    labels = rng.integers(0, len(NAMES), N).astype(np.int16)
    E = prototypes(NAMES, dim=dim)
    F = E[labels]
    F[:100] = 0  # nothing reached these points
    np.save(folder / "features.npy", F.astype(np.float16))
    A = E[labels] + 0.5 * rng.standard_normal((N, dim)).astype(np.float32)
    A[:200] = 0
    np.save(folder / "features_average.npy", A.astype(np.float16))
    if best_view:
        B = E[np.where(rng.random(N) < 0.8, labels, (labels + 1) % len(NAMES))]
        np.save(folder / "features_best_view.npy", B.astype(np.float16))
    truth = labels.copy()
    truth[-50:] = IGNORE  # unannotated
    if gt:
        np.save(folder / "gt_labels.npy", truth)
    (folder / "summary.json").write_text(json.dumps({"status": "ok", "taxonomy": "five",
                                                     "class_names": NAMES}))
    return folder, truth, E


@pytest.fixture
def run(tmp_path):
    folder, truth, E = make_run(tmp_path / "run")
    q = write_queries(tmp_path / "queries.npz", NAMES, E)
    return folder, truth, q


def _rows(out):
    return {line[:22].strip(): line[22:].split() for line in out.splitlines()
            if line.startswith(("diffuser ", "average", "best view"))}


def test_query_file_reproduces_the_labels_and_prints_the_table(run, capsys):
    folder, truth, q = run
    assert main([str(folder), "--queries", str(q)]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0] == (f"diffuser-lab-query | run run | 3,000 points x {D} | 5 queries -> 5 classes | "
                                   f"threshold none")
    rows = _rows(out)
    rec = json.loads((folder / "query.json").read_text())
    assert float(rows["diffuser"][0]) == pytest.approx(rec["metrics"]["diffuser"]["miou"], abs=0.05)
    assert float(rows["diffuser"][0]) > 95  # only the 100 points nothing reached miss
    assert set(rows) == {"diffuser", "average (baseline)", "best view (baseline)"}
    assert float(rows["diffuser"][2]) == pytest.approx(100 * (N - 100) / N, abs=0.05)  # cover
    assert float(rows["best view (baseline)"][0]) < float(rows["diffuser"][0])
    lab = np.load(folder / "query_labels.npy")
    assert lab.dtype == np.int16 and lab.shape == (N,)
    np.testing.assert_array_equal(lab[100:-50], truth[100:-50])
    assert (lab[:100] == IGNORE).all()
    assert rec["queries"] == NAMES and rec["query_classes"] == NAMES and rec["threshold"] is None
    assert set(rec["metrics"]) == {"diffuser", "average", "best_view"}
    assert rec["metrics"]["diffuser"]["accuracy"] == pytest.approx(100 * (N - 150) / (N - 50))
    assert rec["files"] == {"labels": "query_labels.npy", "record": "query.json"}
    assert "wrote query_labels.npy, query.json" in out


def test_earlier_queries_are_kept(run, capsys):
    folder, _, q = run
    for _ in range(3):
        assert main([str(folder), "--queries", str(q)]) == 0
    assert main([str(folder), "--queries", str(q), "--out", "clip"]) == 0
    for stem in ("", "_1", "_2", "_clip"):
        assert (folder / f"query_labels{stem}.npy").is_file() and (folder / f"query{stem}.json").is_file()
    assert main([str(folder), "--queries", str(q), "--out", "clip"]) == 2
    assert "--out clip: query_clip.json or query_labels_clip.npy already in" in capsys.readouterr().err


def test_encoder_threshold_background_and_mapping(tmp_path, capsys):
    folder, truth, _ = make_run(tmp_path / "run", dim=512, best_view=False)
    # the run's class names through the simulated text encoder: the prototypes again
    assert main([str(folder), "--encoder", ENCODER]) == 0
    acc = float(_rows(capsys.readouterr().out)["diffuser"][1])
    assert acc == pytest.approx(100 * (N - 150) / (N - 50), abs=0.05)  # all but the 100 points nothing reached
    # other words for the classes, mapped; 'person' stands for no class
    mapping = tmp_path / "map.csv"
    mapping.write_text("query,class\narmchair,chair\nground,floor\nperson,ignore\n")
    assert main([str(folder), "--encoder", ENCODER, "--names", "wall,ground,armchair,table,sofa,person",
                 "--mapping", str(mapping), "--out", "words"]) == 0
    rec = json.loads((folder / "query_words.json").read_text())
    assert rec["query_classes"] == ["wall", "floor", "chair", "table", "sofa", None]
    assert rec["source"] == f"encoder {ENCODER}" and rec["mapping"] == str(mapping)
    # a threshold above every cosine of another word: all background
    assert main([str(folder), "--encoder", ENCODER, "--names", "wall,floor,armchair,table,sofa",
                 "--mapping", str(mapping), "--threshold", "0.99", "--background", "Wall", "--out", "thr"]) == 1
    assert "map.csv line 3: query 'ground' is not in the query set" in capsys.readouterr().err
    mapping.write_text("armchair,chair\n")
    assert main([str(folder), "--encoder", ENCODER, "--names", "wall,floor,armchair,table,sofa",
                 "--mapping", str(mapping), "--threshold", "0.99", "--background", "Wall", "--out", "thr"]) == 0
    lab = np.load(folder / "query_labels_thr.npy")
    chair = truth == NAMES.index("chair")
    assert (lab[100:][chair[100:]] == 0).all()  # armchair is not chair's prototype: under 0.99 -> wall
    assert (lab[100:][truth[100:] == 1] == 1).all()
    assert json.loads((folder / "query_thr.json").read_text())["background"] == "wall"


def test_without_ground_truth(tmp_path, capsys):
    folder, _, E = make_run(tmp_path / "run", gt=False)
    q = write_queries(tmp_path / "q.npz", NAMES, E)
    assert main([str(folder), "--queries", str(q)]) == 0
    out = capsys.readouterr().out
    assert "no ground truth: no mIoU; diffuser labelled 2,900 of 3,000 points" in out
    assert json.loads((folder / "query.json").read_text())["metrics"]["diffuser"] is None


def test_library_face(run):
    folder, _, q = run
    res = query_run(read_run(folder), Queries.from_file(q), write=False)
    assert not list(folder.glob("query*"))
    assert res.metrics["diffuser"]["coverage"] == pytest.approx(100 * (N - 100) / N)
    assert "wrote" not in table(res)


@pytest.mark.parametrize("args, rc, msg", [
    (["RUN"], 2, "give --queries FILE or --encoder MODULE.FN"),
    (["RUN", "--queries", "Q", "--encoder", ENCODER], 2, "argument --encoder: not allowed with argument --queries"),
    (["RUN", "--queries", "Q", "--names", "a"], 2, "--names goes with --encoder"),
    (["RUN", "--queries", "Q", "--threshold", "2"], 2, "--threshold 2: expected a cosine in [-1, 1]"),
    (["RUN", "--queries", "Q", "--threshold", "x"], 2, "argument --threshold: invalid float value: 'x'"),
    (["RUN", "--queries", "Q", "--background", "wall"], 2, "--background goes with --threshold"),
    (["RUN", "--queries", "Q", "--threshold", "0.5", "--background", "lamp"], 2,
     "--background lamp: not a class of the run (wall, floor, chair, table, sofa)"),
    (["RUN", "--queries", "nothing.npz"], 2, "--queries nothing.npz: no such file"),
    (["RUN", "--queries", "Q", "--mapping", "nothing.csv"], 2, "--mapping nothing.csv: no such file"),
    (["RUN", "--queries", "Q", "--out", "../x"], 2, "--out '../x': expected a plain name"),
    (["RUN", "--queries", "Q", "--bogus"], 2, "unrecognized arguments: --bogus"),
    (["NOWHERE", "--queries", "Q"], 2, "NOWHERE: no such folder"),
    (["EMPTY", "--queries", "Q"], 2, "EMPTY: no features.npy, expected the folder of a run with predictions=features"),
    (["RUN", "--encoder", "nodots"], 2, "encoder 'nodots': expected module.fn"),
    (["RUN", "--encoder", "no_such_module_xyz.f"], 2, "module no_such_module_xyz does not import"),
    (["RUN", "--encoder", "builtins.len"], 1, "encoder builtins.len returned shape (), expected (5, D)"),
    (["RUN", "--encoder", ENCODER], 1, "encoder diffuser_lab.data.embeddings.text_encoder: embeddings of dimension "
                                       "512, expected 64 (the features of RUN)"),
    (["RUN", "--queries", "Q512"], 1, "Q512: embeddings of dimension 512, expected 64 (the features)"),
    (["RUN", "--queries", "BADQ"], 1, "BADQ: no 'embeddings' array (has: names)"),
    (["RUN", "--queries", "LAMPQ"], 1, "query 'lamp' is not a class of the taxonomy"),
    (["RUN", "--queries", "Q", "--mapping", "BADMAP"], 1, "BADMAP line 1: class 'furniture' is not in the taxonomy"),
    (["NOSUMMARY", "--queries", "Q"], 1, "NOSUMMARY: no summary.json"),
    (["NONAMES", "--queries", "Q"], 1, "NONAMES/summary.json: no 'class_names'"),
    (["BADGT", "--queries", "Q"], 1, "BADGT/gt_labels.npy: shape (7,) dtype int16, expected (3000,) class ids"),
    (["BADAVG", "--queries", "Q"], 1, "BADAVG/features_average.npy: not a .npy file"),
    (["ZIPBASIS", "--queries", "Q"], 1, "ZIPBASIS/features_basis.npz: unreadable .npz (BadZipFile: "),
    (["STRBASIS", "--queries", "Q"], 1, "STRBASIS/features_basis.npz [vectors]: vectors of shape (3,) dtype <U1, "
                                        "expected 2-d floats"),
])
def test_bad_input_gives_one_line(tmp_path, capsys, args, rc, msg):
    folder, _, E = make_run(tmp_path / "run")
    paths = {"RUN": folder, "Q": write_queries(tmp_path / "q.npz", NAMES, E),
             "Q512": write_queries(tmp_path / "q512.npz", NAMES, prototypes(NAMES)),
             "LAMPQ": write_queries(tmp_path / "lamp.npz", ["lamp"], E[:1]),
             "NOWHERE": tmp_path / "nowhere", "EMPTY": tmp_path}
    np.savez(tmp_path / "bad.npz", names=np.array(NAMES))
    paths["BADQ"] = tmp_path / "bad.npz"
    (tmp_path / "map.csv").write_text("chair,furniture\n")
    paths["BADMAP"] = tmp_path / "map.csv"
    for name in ("NOSUMMARY", "NONAMES", "BADGT", "BADAVG", "ZIPBASIS", "STRBASIS"):
        paths[name] = make_run(tmp_path / name.lower())[0]
    (paths["NOSUMMARY"] / "summary.json").unlink()
    (paths["NONAMES"] / "summary.json").write_text("{}")
    np.save(paths["BADGT"] / "gt_labels.npy", np.zeros(7, np.int16))
    (paths["BADAVG"] / "features_average.npy").write_bytes(b"not numpy")
    (paths["ZIPBASIS"] / "features_basis.npz").write_bytes(b"PK\x03\x04 cut short")  # the one array reader
    np.savez(paths["STRBASIS"] / "features_basis.npz", vectors=np.array(list("abc")))
    got = main([str(paths.get(a, a)) for a in args])
    err = capsys.readouterr().err
    for key, p in sorted(paths.items(), key=lambda kv: -len(str(kv[1]))):  # EMPTY (tmp_path) last
        err = err.replace(str(p), key)
    assert got == rc, err
    assert err.startswith("diffuser-lab-query: error: ") and err.count("\n") == 1 and msg in err, err


def test_console_script_and_exit_codes(run):
    """As a user runs it: the script is declared, and `python -m` answers in seconds."""
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["diffuser-lab-query"] == "diffuser_lab.cli.query:main"
    folder, _, q = run
    cmd = [sys.executable, "-m", "diffuser_lab.cli.query", str(folder)]
    ok = subprocess.run(cmd + ["--queries", str(q)], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert ok.returncode == 0 and "diffuser " in ok.stdout, ok.stderr
    bad = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert bad.returncode == 2 and bad.stderr.strip().count("\n") == 0 and "Traceback" not in bad.stderr
    help_ = subprocess.run(cmd[:-1] + ["--help"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert help_.returncode == 0 and "--threshold" in help_.stdout


def test_a_reduced_basis_run_says_what_its_basis_kept(tmp_path, capsys):
    """A run with predictions.basis=auto: the table and query.json say the basis' dimension and the
    share of the evidence it kept, and which queries are not the run's."""
    folder, _, E = make_run(tmp_path / "run")
    basis = {"kind": "auto", "dim": 13, "of": D, "queries_span": 5, "principal": 8, "probes": 3,
             "energy_pixels": 0.91, "energy_features": {"median": 0.995, "p5": 0.98}, "norm_error": {"median": 0.001, "p95": 0.004}}
    (folder / "summary.json").write_text(json.dumps({"status": "ok", "taxonomy": "five", "class_names": NAMES,
                                                     "features": {"dim": D, "queries": NAMES[:3], "basis": basis}}))
    q = write_queries(tmp_path / "queries.npz", NAMES, E)
    assert main([str(folder), "--queries", str(q)]) == 0
    out = capsys.readouterr().out
    assert ("features from a basis of 13 of 64 dimensions (the run's 5 queries + 8 principal directions): it kept "
            "91.0 % of the pixels' energy and ~99.5 % of a point's diffused feature (median; |f| within 0.1 %, 95 % "
            "within 0.4 %); 2 of these queries are not the run's") in out
    rec = json.loads((folder / "query.json").read_text())
    assert rec["basis"] == basis and rec["outside_run_queries"] == ["table", "sofa"]
