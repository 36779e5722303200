"""Every command in README.md's ``bash`` and ``python`` blocks, run as written.

The commands are read from README.md itself (tests/readme_commands.py), so the README and this
test cannot drift apart: a new command in the README is run here, or this test fails until a
rule there says why it cannot run. They run in README order in scratch working directories laid
out like a checkout (the venv, scripts/, analysis/ and ``../shared`` linked in), one per chain of
commands that read each other's outputs (``readme_commands.chain``; chains run side by side on
pytest-xdist's workers), with no
``hydra.run.dir`` or ``hydra.sweep.dir``: outputs land where a user finds them. Placeholders are
filled from what the earlier commands made (``<stamp>``, ``<date>/<time>``: the newest match) or
from small datasets this test writes (``MESH.ply``, ``SCANNET_SCENE``, ``RGBD_FOLDER``,
``PRED_DIR``). The long sweeps get a smaller scene appended, never an output folder.
"""
from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import pytest
from readme_commands import (
    EXPERIMENTS,
    SCANNET_EXPERIMENTS,
    HAVE_SHARED,
    README,
    ROOT,
    SHARED,
    TUNE_EXPERIMENTS,
    VENV,
    Command,
    _env,
    chain,
    own_data,
    readme_commands,
    resolve,
)

COMMANDS = readme_commands()


# ----------------------------------------------------------------------------- the working directories

@pytest.fixture(scope="session")
def readme_data(tmp_path_factory):
    """The own-data placeholders' small datasets, written once per test process."""
    if not (VENV / "bin" / "diffuser-lab").exists():
        pytest.skip(f"diffuser-lab is not installed in {VENV} (run bash scripts/dev.sh setup)")
    base = tmp_path_factory.mktemp("readme-data")
    return own_data(base / "data")


@pytest.fixture(scope="session")
def works(tmp_path_factory, readme_data):
    """One scratch folder per chain (:func:`readme_commands.chain`), laid out as a user's checkout:
    repo/ (where the commands run) beside shared/. A chain's commands run in README order in its
    folder; chains are independent, so pytest-xdist may run them on different workers."""
    made: dict[str, dict] = {}

    def get(chain: str) -> dict:
        if chain not in made:
            base = tmp_path_factory.mktemp("readme")
            repo = base / "repo"
            repo.mkdir()
            # no pyproject.toml: scripts/dev.sh must never reinstall the venv from this copy (it would
            # point the editable install here); the package itself is imported from the checkout
            for name in ("scripts", "analysis", "tests"):
                (repo / name).symlink_to(ROOT / name)
            (repo / ".venv").symlink_to(VENV)
            if HAVE_SHARED:
                (base / "shared").symlink_to(SHARED)
            made[chain] = {"repo": repo, "state": {}, "placeholders": readme_data}
        return made[chain]

    return get


def execute(c: Command, work: dict) -> subprocess.CompletedProcess:
    text = resolve(c.text, work)
    cwd = work["repo"]
    if c.lang == "python":
        argv = [str(VENV / "bin" / "python"), "-c", text]
    else:
        argv = ["bash", "-c", " ".join([text, *c.append])]
    if c.key == "quick":  # the checkout's own suite (its pyproject.toml's options)
        cwd = ROOT
    if c.key == "pip":  # installs `.`: the checkout itself (a dry run changes nothing)
        cwd = ROOT
        argv = ["bash", "-c", " ".join([text.replace(".venv/bin/pip", f"{VENV}/bin/pip"), *c.append])]
    return subprocess.run(argv, cwd=cwd, env=_env(), capture_output=True, text=True, timeout=1200)


# ----------------------------------------------------------------------------- checks

def _summary(repo: Path, run_dir: str) -> dict:
    return json.loads((repo / run_dir / "summary.json").read_text())


def _printed_block_after(cmd_line: int, marker: str) -> list[str]:
    """The plain code block after ``marker`` that follows README line ``cmd_line`` (a sample output)."""
    lines = README.read_text().splitlines()
    i = next(k for k in range(cmd_line, len(lines)) if marker in lines[k])
    start = next(k for k in range(i, len(lines)) if lines[k].strip() == "```")
    end = next(k for k in range(start + 1, len(lines)) if lines[k].startswith("```"))
    return lines[start + 1:end]


def _rows(lines) -> dict[str, list[float]]:
    out = {}
    for ln in lines:
        m = re.match(r"^(diffuser|bayesian \(baseline\)|2D predictions|(?:online|batch) (?:diffuser|bayesian))\s+"
                     r"([\d.\s]+)$", ln.strip())
        if m:
            out[m.group(1)] = [float(x) for x in m.group(2).split()]
    return out


def check_run(c: Command, p, work):
    m = re.search(r"^run folder: (\S+)$", p.stdout, re.M)
    assert m, f"no 'run folder:' line in\n{p.stdout[-2000:]}"
    run_dir = Path(m.group(1))
    assert run_dir.resolve().is_relative_to((work["repo"] / "logs" / "runs").resolve()), run_dir
    s = json.loads((run_dir / "summary.json").read_text())
    assert s["status"] == "ok"
    if s.get("protocol") == "online":
        assert re.search(r"^diffuser-lab online \| scene ", p.stdout, re.M), p.stdout[-2000:]
        assert "per frame [ms]" in p.stdout and len(s["online"]["frames"]) == s["n_frames"]
    elif s.get("protocol") != "single_frame":
        assert re.search(r"^diffuser-lab \| scene ", p.stdout, re.M)
        if s["metrics"] is None:  # no ground truth: what was labelled, as the README says
            assert "no ground truth: no mIoU; diffuser labelled" in p.stdout, p.stdout[-2000:]
        elif "features" in s:  # a features run: its baselines, the files diffuser-lab-query reads
            assert "average (baseline)" in p.stdout and "best view (baseline)" in p.stdout, p.stdout[-2000:]
            # the baselines' features: (N, D) files, or with the reduced basis (predictions.basis=auto) in it
            assert {"features", "queries", "gt_labels"} <= set(s["files"]), s["files"]
            assert "features_average" in s["files"] or "features_basis" in s["files"], s["files"]
        else:
            assert "bayesian (baseline)" in p.stdout, p.stdout[-2000:]
    if "LAB_FOLDER" in c.text:
        said = re.search(r"diffuser labelled\s+([\d,]+) of ([\d,]+) points", README.read_text())
        assert said and f"labelled {said.group(1)} of {said.group(2)} points" in p.stdout, p.stdout[-2000:]
    if "predictions=model" in c.text:
        assert re.search(r"model \S+, \d+ frames run, \d+ from cache", p.stdout), p.stdout[-2000:]
    # the README's sample outputs are what the command prints, to the printed digit: the spread measured
    # across the forced instruction sets (numba/OpenBLAS/numpy at host, avx2 and generic x86-64;
    # tests/test_isa.py) and under an emulated AVX2 CPU (qemu: the ray caster's kernels) is 0.0
    for marker, cond in (("It prints", c.text.startswith("bash scripts/dev.sh demo")),
                         ("The global protocol (", c.text == ".venv/bin/diffuser-lab scene=scannet0470"),
                         ("The first prints", c.text == ".venv/bin/diffuser-lab scene=scannet0470 protocol=online")):
        if cond:
            want, got = _rows(_printed_block_after(c.line, marker)), _rows(p.stdout.splitlines())
            assert want and set(want) == set(got), (want, got)
            for k in want:
                worst = max(abs(a - b) for a, b in zip(want[k], got[k]))
                assert worst < 0.05, f"README prints {k} {want[k]}, the run {got[k]}"


def _sweep(p, work) -> tuple[int, Path, list[dict]]:
    m = re.search(r"^sweep: (\d+) jobs -> (\S+)$", p.stdout, re.M)
    assert m, p.stdout[-2000:]
    n, sweep_dir = int(m.group(1)), work["repo"] / m.group(2)
    done = re.findall(rf"^\[(\d+)/{n}\] (\S+): (?!FAILED)", p.stdout, re.M)
    assert sorted(int(i) for i, _ in done) == list(range(1, n + 1)), p.stdout[-3000:]
    assert f"{n} of {n} jobs ok" in p.stdout and "| miou |" in p.stdout  # the table at the end
    jobs = sorted(sweep_dir.glob("*/summary.json"))
    assert len(jobs) == n
    summaries = [json.loads(j.read_text()) | {"_dir": j.parent.name} for j in jobs]
    assert all(s["status"] == "ok" for s in summaries)
    return n, sweep_dir, summaries


def _readme_jobs(name: str) -> int:
    m = re.search(rf"^\| `{name}` \|.*\| (\d+) \|$", (ROOT / "docs" / "sweeps.md").read_text(), re.M)
    assert m, f"docs/sweeps.md's experiment table has no row for {name} with its number of jobs"
    return int(m.group(1))


def _seeds(name: str) -> int:
    from omegaconf import OmegaConf

    params = OmegaConf.load(ROOT / "conf" / "experiment" / f"{name}.yaml").hydra.sweeper.params
    return len(str(params.seed).split(","))


def check_sweep(c: Command, p, work):
    n, sweep_dir, summaries = _sweep(p, work)
    name = re.search(r"\+experiment=(\w+)", c.text).group(1)
    scene = "scannet0470" if "scene=scannet0470" in c.text else "demo"
    rel = sweep_dir.relative_to(work["repo"])
    assert re.fullmatch(rf"logs/multirun/{name}/\d{{4}}-\d\d-\d\d_\d\d-\d\d-\d\d-\d{{6}}_{scene}", str(rel)), rel
    if name in TUNE_EXPERIMENTS:  # a search: its own job count, test jobs after the validation ones
        check_tune(c, n, sweep_dir, summaries)
        return
    assert n == _readme_jobs(name) // (_seeds(name) if "seed=0" in c.append else 1)
    launcher = re.search(r"hydra/launcher=(\w+)", c.text)
    metrics = {s["_dir"]: s["metrics"]["miou"] for s in summaries}
    # the small scene still shows the effect: more 2D noise, or iterating towards the fixed point, costs mIoU
    for key, first, last in (("predictions.strength", "0", "2"), ("solver.max_iter", "10", "20000")):
        if name in ("noise", "iterations") and any(o.startswith(key + "=") for s in summaries for o in s["overrides"]):
            by = {v: [s["metrics"]["miou"] for s in summaries if f"{key}={v}" in s["overrides"]] for v in (first, last)}
            assert sum(by[first]) / len(by[first]) > sum(by[last]) / len(by[last]) + 5, (name, by)
    if launcher is None:
        work["state"].setdefault("basic", {})[(name, scene)] = metrics
    else:  # the same jobs give the same metrics as with the basic launcher
        basic = work["state"].get("basic", {}).get((name, scene))
        assert basic is not None, "the README shows the basic-launcher sweep of this experiment first"
        assert metrics == basic, (launcher.group(1), metrics, basic)
        if launcher.group(1) == "submitit_local":
            assert not list(sweep_dir.rglob("%j")), "submitit left a literal %j folder"


def check_tune(c: Command, n: int, sweep_dir: Path, summaries: list[dict]):
    """A search (hydra.sweeper.tune): the README's job count is the full one; shrunk (TUNE_SMALL) it
    has 2 trials x 1 validation job and 1 test job x (the tuned value + each compared one); every job
    says its split, the validation ones come first, and the preset was written."""
    from omegaconf import OmegaConf

    name = re.search(r"\+experiment=(\w+)", c.text).group(1)
    tune_cfg = OmegaConf.load(ROOT / "conf" / "experiment" / f"{name}.yaml").hydra.sweeper.tune
    trials, arms = tune_cfg.n_trials, 1 + len(tune_cfg.compare)
    val = len(str(tune_cfg.validation.demo.seed).split(","))
    tests = sum(len(str(s.seed).split(",")) for s in tune_cfg.test.values())
    assert _readme_jobs(name) == trials * val + tests * arms
    assert n == 2 * 1 + 1 * arms
    splits = [s["split"] for s in sorted(summaries, key=lambda s: int(s["_dir"].split("_")[0]))]
    assert splits == ["validation"] * 2 + ["test"] * arms, splits
    assert (sweep_dir / "tuned" / f"{name}.yaml").is_file() and (sweep_dir / "tune.json").is_file()


def check_multirun(c: Command, p, work):
    n, sweep_dir, _ = _sweep(p, work)
    rel = sweep_dir.relative_to(work["repo"])
    assert re.fullmatch(r"logs/multirun/\d{4}-\d\d-\d\d/\d\d-\d\d-\d\d-\d{6}", str(rel)), rel


def check_slurm(c: Command, work):
    """No cluster: compose the README's command line and check what submitit would be given."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from diffuser_lab.config import register
    from diffuser_lab.runs import launchers

    args = resolve(c.text, work).split()[1:]
    assert args[0] == "-m"
    register()
    launchers.register()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=args[1:], return_hydra_config=True)
    GlobalHydra.instance().clear()
    assert cfg.hydra.launcher._target_.endswith("SlurmLauncher")
    part = re.search(r"hydra\.launcher\.partition=(\S+)", c.text)
    assert part and cfg.hydra.launcher.partition == part.group(1)
    assert cfg.hydra.launcher.cpus_per_task >= 1 and cfg.hydra.launcher.timeout_min > 0
    assert "${hydra.sweep.dir}" in str(cfg.hydra.launcher._get_node("submitit_folder")._value())


def check_analysis(c: Command, p, work):
    out = Path(work["repo"]) / re.search(r"--(?:out|rrd) (\S+)", c.text).group(1)
    if "analysis.collect" in c.text:
        assert "| graph.k |" in p.stdout and out.with_suffix(".csv").is_file() and out.with_suffix(".md").is_file()
    elif "analysis.plots" in c.text:
        assert {"convergence.png", "miou_vs_graph.k.png", "per_class_iou.png"} <= {q.name for q in out.glob("*.png")}
    elif "analysis.report" in c.text:
        md = (out / "report.md").read_text()
        assert md.startswith("# Experiment k"), md[:200]
        assert "Reference: `graph.k=24` (the default run's" in md and "![forest](forest.png)" in md
        if "--html" in c.text:
            page = (out / "report.html").read_text()
            assert page.count('src="data:image/png;base64,') == md.count("](") and 'src="forest.png"' not in page
    elif "analysis.compare" in c.text:
        assert out.is_file() and out.stat().st_size > 1000 and "differ" in p.stdout.lower()


def check_inspect(c: Command, p, work):
    if "--at" in c.text:
        assert re.search(r"^wrote z\.npy: Z at iteration 100", p.stdout, re.M), p.stdout
    elif "--scores" in c.text:
        assert "wrote scores.rrd" in p.stdout and "scores of chair, table" in p.stdout, p.stdout
    elif "--to-rrd" in c.text:
        assert "wrote replay.rrd" in p.stdout and (work["repo"] / "replay.rrd").stat().st_size > 1000
    elif "--foxglove-layout" in c.text:
        import json as _json

        layout = _json.loads((work["repo"] / "layout.json").read_text())
        assert "configById" in layout and "/diffusion/labels" in (work["repo"] / "layout.json").read_text()
    elif "cut.mcap" in c.text:
        assert "TRUNCATED" in p.stdout and "recorded" in p.stdout
    else:
        assert "complete" in p.stdout and re.search(r"^recorded\s+\d+ iterations", p.stdout, re.M)


def check_bench(c: Command, p, work):
    if "--write-demo-input" in c.text:
        assert p.stdout.startswith("wrote demo30k.npz")
    else:
        fig = json.loads(p.stdout.strip().splitlines()[-1])
        assert fig["n_points"] > 20_000 and fig["iterations"] == 100 and fig["total_s"] > 0


def check_pip(c: Command, p, work):
    if p.returncode != 0 and re.search(r"(NewConnectionError|Could not fetch|Network is unreachable)", p.stderr):
        pytest.skip("no package index reachable for the dry run")
    assert p.returncode == 0, p.stderr[-3000:]
    assert "conflict" not in (p.stdout + p.stderr).lower(), p.stderr[-3000:]


def check_quick(c: Command, p, work):
    """The quick loop selects the equations, loaders, config checks and bad-input tests (most of the
    suite's tests) and none with the slow marker (docs/testing.md)."""
    m = re.search(r"^(\d+)/(\d+) tests collected \((\d+) deselected\)", p.stdout, re.M)
    assert m, p.stdout[-2000:]
    quick, total, slow = map(int, m.groups())
    assert quick + slow == total and quick > total // 2 and slow > 100, m.group(0)
    for module in ("tests/method/test_diffusion.py", "tests/data/test_prediction_files.py",
                   "tests/cli/test_bad_input.py", "tests/test_config.py"):
        assert f"{module}::" in p.stdout, module
    assert "tests/test_readme.py::test_readme_command[" not in p.stdout


def check_query(c: Command, p, work):
    """The relabelled run's table (Diffuser and both baselines) and its files, next to the run's."""
    assert re.search(r"^diffuser\s+[\d.]+\s+[\d.]+", p.stdout, re.M), p.stdout[-2000:]
    assert "average (baseline)" in p.stdout and "best view (baseline)" in p.stdout
    run_dir = work["repo"] / resolve(c.text, work).split()[1]
    assert (run_dir / "query_labels.npy").is_file() and (run_dir / "query.json").is_file()


CHECKS = {"run": check_run, "quick": check_quick, "query": check_query, "sweep": check_sweep, "multirun": check_multirun, "analysis": check_analysis,
          "inspect": check_inspect, "bench": check_bench, "pip": check_pip,
          "cfg": lambda c, p, w: "graph:" in p.stdout or pytest.fail(p.stdout[-1000:])}


def test_readme_is_short():
    """The README is for users (at most 15,000 bytes); measurements and references live in docs/."""
    assert len(README.read_bytes()) <= 15_000
    for link in re.findall(r"\]\((docs/[\w.-]+)\)", README.read_text()):
        assert (ROOT / link).is_file(), link


def test_readme_lists_every_experiment():
    """The README names every experiment; docs/sweeps.md has each one's row with its job count."""
    table = set(re.findall(r"^\| `(\w+)` \|.*\| \d+ \|$", (ROOT / "docs" / "sweeps.md").read_text(), re.M))
    assert table == set(EXPERIMENTS), (table, EXPERIMENTS)
    assert SCANNET_EXPERIMENTS <= set(EXPERIMENTS), SCANNET_EXPERIMENTS - set(EXPERIMENTS)
    text = README.read_text()
    a = text.index("The ablations ship as named experiments")
    named = set(re.findall(r"`(\w+)`", text[a:text.index("```", a)]))
    assert set(EXPERIMENTS) <= named, set(EXPERIMENTS) - named
    assert any("+experiment=NAME" in c_text for c_text in text.splitlines())


def test_every_placeholder_reads_its_own_chain():
    """A command that names an earlier command's output (``<stamp>``, ``<date>/<time>_...``) runs in
    the chain of a command before it, so that its folder holds what it reads."""
    seen: set[str] = set()
    for c in COMMANDS:
        if "<" in c.text and c.key not in ("pip",):
            assert chain(c) in seen, (c.text, chain(c))
        seen.add(chain(c))


@pytest.mark.slow
@pytest.mark.parametrize("cmd", COMMANDS, ids=[c.id for c in COMMANDS])
def test_readme_command(cmd: Command, works):
    work = works(chain(cmd))
    if cmd.key == "slurm":
        check_slurm(cmd, work)
        pytest.skip(cmd.skip + " (composed: ok)")
    if cmd.key == "viewer":
        target = resolve(cmd.text, work).split()[1]
        assert (work["repo"] / target).exists(), target
        pytest.skip(cmd.skip)
    if cmd.skip:
        pytest.skip(cmd.skip)
    # dev.sh's stamps: .installed-test (everything: the test command) covers the demo's .installed
    stamps = [VENV / ".installed-test"] + ([VENV / ".installed"] if cmd.text.startswith("bash scripts/dev.sh demo") else [])
    fresh = [s for s in stamps if s.is_file() and s.stat().st_mtime >= (ROOT / "pyproject.toml").stat().st_mtime]
    if cmd.text.startswith("bash scripts/dev.sh") and not fresh:
        pytest.skip(f"{VENV} is not set up by scripts/dev.sh for this pyproject.toml: the script would install")
    p = execute(cmd, work)
    if cmd.key == "pip":
        return check_pip(cmd, p, work)
    assert p.returncode == 0, f"exit {p.returncode}\n--- stdout\n{p.stdout[-3000:]}\n--- stderr\n{p.stderr[-3000:]}"
    assert "Traceback" not in p.stderr, p.stderr[-3000:]
    check = CHECKS.get(cmd.key)
    if check is not None:
        check(cmd, p, work)
