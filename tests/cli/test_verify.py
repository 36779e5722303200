"""`diffuser-lab-verify` and what it reads: every run's summary.json and records carry what made it
(inputs and outputs hashed), and a re-run from the run folder says identical or what differs."""
import json
import shutil

import numpy as np
import pytest
from conftest import SMALL_DEMO, run_cli
from datasets import make_world, write_scannet
from PIL import Image

from diffuser_lab.cli.inspect import main as inspect_main
from diffuser_lab.cli.verify import main as verify_main
from diffuser_lab.data import inputs
from diffuser_lab.recording.rerun_log import read_provenance

SCANNET = ["scene=scannet", "scene.options.frame_step=1", "solver.max_iter=40"]


@pytest.fixture(scope="module")
def scannet_run(tmp_path_factory):
    """A ScanNet export of 4 frames (one with ScanNet's -inf pose) and a run of it, records on."""
    base = tmp_path_factory.mktemp("verify")
    root = write_scannet(base, make_world())
    run = base / "run"
    p = run_cli(*SCANNET, f"scene.options.root={root}", f"hydra.run.dir={run}")
    assert p.returncode == 0, p.stderr[-2000:]
    return root, run


def _verify(capsys, run, out, err=None):
    """verify's exit status and lines printed (``err``: a list that gets its stderr)."""
    code = verify_main([str(run), "--out", str(out)])
    got = capsys.readouterr()
    if err is not None:
        err.append(got.err)
    return code, got.out.splitlines()


def _own_run(tmp_path):
    """An export and its run of this test's own (it edits or removes the inputs)."""
    root = write_scannet(tmp_path, make_world())
    run = tmp_path / "run"
    p = run_cli(*SCANNET, f"scene.options.root={root}", f"hydra.run.dir={run}", "record=off")
    assert p.returncode == 0, p.stderr[-2000:]
    return root, run


@pytest.mark.slow
def test_summary_and_records_carry_the_inputs_and_outputs(scannet_run, capsys):
    root, run = scannet_run
    s = json.loads((run / "summary.json").read_text())
    inp, out = s["inputs"], s["outputs"]
    listed = inputs.read_list(run / "inputs.tsv")
    frames = [e for e in listed if e.role == "frames"]
    # 3 frames (the -inf pose's skipped after its pose was read): depth, pose, label-filt, colour
    assert {e.path.split("/")[-2] for e in frames} == {"depth", "pose", "label-filt", "color"}
    assert inp["manifests"]["frames"] == {"count": len(frames), "bytes": sum(e.size for e in frames),
                                          "sha256": inputs.manifest(e.sha256 for e in frames)}
    roles = {f["role"]: f for f in inp["files"]}
    assert {"mesh", "intrinsics", "mapping", "taxonomy"} <= set(roles) and "frames" not in roles
    mesh = root / "scene0999_00_vh_clean_2.ply"
    assert any(f["path"] == str(mesh) and f["size"] == mesh.stat().st_size for f in inp["files"])
    assert len(inp["config_sha256"]) == 64 and "generator" not in inp
    assert inp["hashing"]["files"] == len(listed) and inp["hashing"]["hashed"] + inp["hashing"]["cached"] >= len(listed)
    labels = run / "labels.npy"
    assert out["files"]["labels.npy"] == {"size": labels.stat().st_size, "sha256": inputs.sha256_file(labels)[1]}
    assert set(out["files"]) == {"labels.npy", "labels.ply", "bayesian_labels.npy", "gt_labels.npy"}
    assert len(out["figures_sha256"]) == 64
    for record in (run, run / "run.rrd"):  # run.mcap's metadata, run.rrd's recording property
        assert inspect_main([str(record), "--no-table"]) == 0
        text = capsys.readouterr().out
        assert f"config sha256 {inp['config_sha256'][:12]}" in text
        assert f"inputs    {inp['sha256'][:12]}: frames {len(frames)} files" in text
        assert f"mesh {mesh} " in text and f"labels.npy {out['files']['labels.npy']['sha256'][:12]}" in text
        assert f"figures {out['figures_sha256'][:12]}" in text
    replay = run.parent / "replay.rrd"  # re-logged from run.mcap: what made the run comes along
    assert inspect_main([str(run), "--to-rrd", str(replay)]) == 0
    assert read_provenance(replay) == read_provenance(run / "run.rrd")
    assert read_provenance(replay)["inputs"] == inp and read_provenance(replay)["outputs"] == out


@pytest.mark.slow
def test_a_run_verifies_identical(scannet_run, tmp_path, capsys):
    _, run = scannet_run
    code, lines = _verify(capsys, run, tmp_path / "again")
    assert code == 0, lines
    assert lines[0].startswith("identical: labels bit for bit (") and lines[0].endswith("nothing changed since")
    assert "inputs    same" in "\n".join(lines)
    new = json.loads((tmp_path / "again" / "summary.json").read_text())
    assert new["verify"]["identical"] is True and new["overrides"] == json.loads((run / "summary.json").read_text())["overrides"]
    assert new["outputs"] == json.loads((run / "summary.json").read_text())["outputs"]
    assert (tmp_path / "again" / ".hydra" / "config.yaml").read_text() == (run / ".hydra" / "config.yaml").read_text()
    err = []
    code, _ = _verify(capsys, run, tmp_path / "again", err)  # never into a folder that holds a run
    assert code == 2 and f"--out {tmp_path / 'again'}: not empty" in err[0]


@pytest.mark.slow
def test_an_input_edited_in_place_is_found_and_named(tmp_path, capsys):
    root, run = _own_run(tmp_path)
    depth = root / "depth" / "0.png"
    d = np.array(Image.open(depth))
    d[30, 40] += 700  # one pixel, 0.7 m further
    Image.fromarray(d).save(depth)  # the same file, rewritten
    code, lines = _verify(capsys, run, tmp_path / "again")
    assert code == 1
    # the file named; the labels may or may not follow one pixel (here: a point further or not)
    assert lines[0].startswith(f"differs in its inputs: 1 file changed (frames): {depth}; ") or \
        lines[0].startswith("differs: ") and lines[0].endswith(f"changed since: inputs (1 file changed (frames): {depth})")
    assert f"inputs    1 file changed (frames): {depth}" in lines


@pytest.mark.slow
def test_a_different_commit_is_named(scannet_run, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(scannet_run[1], run)
    s = json.loads((run / "summary.json").read_text())
    here = s["provenance"]["diffuser_lab"]["commit"]
    s["provenance"]["diffuser_lab"]["commit"] = "0123456789ab" + "0" * 28  # as if made at another commit
    (run / "summary.json").write_text(json.dumps(s))
    code, lines = _verify(capsys, run, tmp_path / "again")
    assert code == 0 and lines[0].startswith("identical: ") and lines[0].endswith("changed since: commit")
    assert f"commit    0123456789ab -> {(here or 'unknown')[:12]}" in lines


@pytest.mark.slow
def test_a_run_whose_inputs_are_gone_says_which(tmp_path, capsys):
    root, run = _own_run(tmp_path)
    (root / "pose" / "1.txt").unlink()
    code, lines = _verify(capsys, run, tmp_path / "again")
    assert code == 1 and lines == [f"cannot re-run: 1 of its inputs is gone: {root / 'pose' / '1.txt'} (frames)"]
    assert not (tmp_path / "again").exists()


@pytest.mark.slow
@pytest.mark.parametrize("kind,extra", [
    ("single_frame", ["protocol=single_frame", "protocol.max_targets=2", "protocol.window=3"]),
    ("online", ["protocol=online", "online.rate=0", "online.finish=0"]),
    ("features", ["predictions=features", "predictions.dim=32"]),
])
def test_every_kind_of_run_verifies_identical(kind, extra, tmp_path, capsys):
    run = tmp_path / "run"
    p = run_cli(*SMALL_DEMO, *extra, f"hydra.run.dir={run}")
    assert p.returncode == 0, p.stderr[-2000:]
    gen = json.loads((run / "summary.json").read_text())["inputs"]["generator"]
    assert gen == {"source": "demo", "seed": 0}  # a procedural scene names its generator
    code, lines = _verify(capsys, run, tmp_path / "again")
    assert code == 0 and lines[0].startswith("identical: "), lines


@pytest.mark.slow
def test_one_job_of_a_sweep_and_an_online_run_with_idle_steps(tmp_path, capsys):
    p = run_cli("-m", *SMALL_DEMO, "protocol=online", "online.rate=30,0", "online.finish=0",
                f"hydra.sweep.dir={tmp_path / 'sweep'}")
    assert p.returncode == 0, p.stderr[-2000:]
    idle, still = sorted((tmp_path / "sweep").glob("*online.rate=*"), key=lambda d: "rate=0" in d.name)
    code, lines = _verify(capsys, still, tmp_path / "still")
    assert code == 0 and lines[0].startswith("identical: ")
    code, lines = _verify(capsys, idle, tmp_path / "idle")
    # the idle steps follow the wall clock: said in the verdict (identical only by chance)
    assert code == 0 and lines[0].startswith("identical: ") or \
        code == 1 and lines[0].startswith("differs (as expected: online.rate=30: an online run's idle steps")


@pytest.mark.slow  # ~40 s: two local Ray instances start
def test_a_tiled_run_on_ray_verifies_identical(scannet_run, tmp_path, capsys):
    pytest.importorskip("ray")
    root, _ = scannet_run
    run = tmp_path / "run"
    p = run_cli(*SCANNET, f"scene.options.root={root}", "scene.voxel_size=0", "protocol=tiled", "tiling.size=2",
                "tiling.workers=2", f"hydra.run.dir={run}")
    assert p.returncode == 0, p.stderr[-2000:]
    s = json.loads((run / "summary.json").read_text())
    assert s["tiling"]["n_tiles"] > 1 and {t["status"] for t in s["tiling"]["tiles"]} == {"done"}
    assert all("inputs" not in t for t in s["tiling"]["tiles"])
    # the frames the Ray workers read are the run's inputs: the untiled run's frame files
    untiled = inputs.read_list(scannet_run[1] / "inputs.tsv")
    frames = {e.path for e in inputs.read_list(run / "inputs.tsv") if e.role == "frames"}
    assert frames and frames <= {e.path for e in untiled if e.role == "frames"}
    code, lines = _verify(capsys, run, tmp_path / "again")
    assert code == 0 and lines[0].startswith("identical: labels bit for bit ("), lines
