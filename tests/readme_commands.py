"""The commands of README.md's ``bash`` and ``python`` blocks: read, classified, their placeholders
filled. Used by tests/test_readme.py (which runs them with a smaller scene appended to the long
sweeps) and, to run every one of them verbatim in a checkout and print one line and the wall
time of each, from the command line::

    .venv/bin/python tests/readme_commands.py [--only REGEX] [--log FILE]   # from the checkout's root

(the own-data placeholders are filled with the small datasets of tests/datasets.py, written to
a temporary folder; a command that cannot run here prints why).
"""
from __future__ import annotations

import functools
import os
import re
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared"
README = ROOT / "README.md"
EXPERIMENTS = sorted(p.stem for p in (ROOT / "conf" / "experiment").glob("*.yaml"))
# ``+experiment=NAME scene=scannet0470``: every experiment runs on the demo; on the real scene the ones
# whose keys meet what a mesh scene changes (its graph, methods, sensor depth, frames, features); the
# others sweep the same keys there as on the demo (the suite's minutes: docs/testing.md)
SCANNET_EXPERIMENTS = {"k", "methods", "depth_noise", "keyframes", "lifters", "views"}
# The long sweeps on the smallest scene that still shows each sweep's effect (mIoU falling with
# the noise, with the iterations past the early stop: measured 2026-12-04) and keys none sweeps:
DEMO_SMALL = ["scene.options.point_spacing=0.15", "scene.options.image_width=80",
              "scene.options.image_height=60"]  # ~3.6k points instead of ~51k, 80x60 views
SCANNET_SMALL = ["scene.voxel_size=0.08", "scene.options.image_width=80", "scene.options.image_height=60",
                 "seed=0"]  # 8 cm voxels, 80x60 views, one seed of the three
SINGLE_FRAME_SMALL = ["protocol.max_targets=8"]
# A search (hydra.sweeper.tune): 2 trials on one validation room, one test room for the tuned value
# and what it is compared with (4 jobs), on the small demo
TUNE_SMALL = ["hydra.sweeper.tune.n_trials=2", "hydra.sweeper.tune.validation.demo.seed=3",
              "hydra.sweeper.tune.test.demo.seed=0", "~hydra.sweeper.tune.test.scannet0470"]
TUNE_EXPERIMENTS = {p.stem for p in (ROOT / "conf" / "experiment").glob("*.yaml") if "\n    tune:" in p.read_text()}
"""Experiments that search (their sweeper's ``tune`` section) rather than sweep a grid."""
VENV = Path(sys.prefix)
HAVE_SHARED = (SHARED / "data" / "scannet").is_dir()
HAVE_7SCENES = (SHARED / "data" / "7scenes_sample" / "camera-intrinsics.txt").is_file()
CAPTURES = ("NERFSTUDIO_DIR", "COLMAP_DIR", "REPLICA_DIR", "SENSREADER_DIR", "TEMPLATES_DIR", "BAG")
"""Placeholders of the capture formats' commands: the real 7-Scenes frames written in each layout."""


@dataclass
class Command:
    """One README command: where it stands, its text, and how this test runs it."""

    line: int  # README line number
    section: str
    text: str  # as written (NAME expanded)
    lang: str = "bash"
    append: list[str] = field(default_factory=list)
    skip: str = ""  # why it is not run here
    key: str = ""  # what it does, for the checks

    @property
    def id(self) -> str:
        short = re.sub(r"[^A-Za-z0-9=+._/-]+", "_", self.text.replace(".venv/bin/", ""))[:60]
        return f"L{self.line}-{short}"


def _blocks(text: str):
    """(first line number, language, lines) of each fenced block."""
    lines = text.splitlines()
    i = 0
    section = ""
    while i < len(lines):
        if lines[i].startswith("#"):
            section = lines[i].lstrip("# ").strip()
        m = re.match(r"^```(\w*)\s*$", lines[i])
        if m:
            j = i + 1
            while j < len(lines) and not lines[j].startswith("```"):
                j += 1
            yield i + 2, m.group(1), lines[i + 1:j], section
            i = j
        i += 1


def _strip_comment(line: str) -> str:
    return re.split(r"\s+#\s", line, maxsplit=1)[0].rstrip()


def readme_commands() -> list[Command]:
    cmds: list[Command] = []
    for first, lang, lines, section in _blocks(README.read_text()):
        if lang == "python":
            cmds.append(Command(first, section, "\n".join(lines), lang="python", key="python"))
            continue
        if lang != "bash":
            continue
        for k, raw in enumerate(lines):
            text = _strip_comment(raw.strip())
            if not text or text.startswith("#"):
                continue
            names = [None]
            if "+experiment=NAME" in text:
                names = [n for n in EXPERIMENTS if "scene=scannet0470" not in text or n in SCANNET_EXPERIMENTS]
            for name in names:
                t = text.replace("+experiment=NAME", f"+experiment={name}") if name else text
                cmds.append(classify(Command(first + k, section, t)))
    return cmds


def classify(c: Command) -> Command:
    """How each kind of README command runs here (first rule that matches)."""
    t = c.text
    if t.startswith("bash scripts/dev.sh test") and " -m " in t:
        c.key, c.append = "quick", ["--collect-only", "-q"]  # the quick loop: what it selects
    elif t.startswith("bash scripts/dev.sh test"):
        c.skip = "the test command itself: CI runs it, this is that run"
    elif re.match(r"^\.venv/bin/rerun \S+\.(rrd|mcap)$", t) or " --view" in t:
        c.skip, c.key = "opens the Rerun viewer window (no display here); the file it opens is checked", "viewer"
    elif "hydra/launcher=slurm" in t and not shutil.which("sbatch"):
        c.skip, c.key = "no SLURM here (no sbatch): the same command line is composed and checked instead", "slurm"
    elif t.startswith(".venv/bin/pip install"):
        c.key, c.append = "pip", ["--dry-run"]  # resolves the extras together without changing the venv
    elif " -m +experiment=" in t:
        c.key = "sweep"
        # one seed of the three, as on the real scene; the k sweeps keep theirs (the seeds' mean +- std
        # table, and the launchers compared with the basic one on the same jobs)
        c.append = SCANNET_SMALL if "scene=scannet0470" in t else \
            DEMO_SMALL + ([] if re.search(r"\+experiment=k\b", t) else ["seed=0"])
        if re.search(r"\+experiment=(\w+)", t).group(1) in TUNE_EXPERIMENTS:
            c.append = [*c.append, *TUNE_SMALL]
    elif " -m " in t and "diffuser-lab " in t:
        c.key = "multirun"
    elif "diffuser-lab --cfg" in t:
        c.key = "cfg"
    elif re.match(r"^\.venv/bin/diffuser-lab( |$)", t) or t.startswith("bash scripts/dev.sh demo"):
        c.key = "run"
        if "protocol=single_frame" in t:
            c.append = SINGLE_FRAME_SMALL
    elif "diffuser-lab-inspect" in t:
        c.key = "inspect"
    elif "diffuser-lab-query" in t:
        c.key = "query"
    elif "diffuser-lab-bench" in t:
        c.key = "bench"
    elif "-m analysis." in t:
        c.key = "analysis"
    else:
        c.key = "shell"
    if "scene=scannet_frames" in t:
        c.append = ["scene.options.max_frames=8"]  # 8 of the 27 real frames
    if "scene=city" in t:
        c.append = ["scene.options.blocks_x=1", "scene.options.blocks_y=1", "scene.options.point_spacing=0.5"]  # ~40k points
    if ("scannet0470" in t or "../shared" in t) and not HAVE_SHARED and not c.skip:
        c.skip = f"needs the real data in {SHARED / 'data'} (absent)"
    if any(p in t for p in CAPTURES) and not HAVE_7SCENES and not c.skip:
        c.skip = f"its fixture is written from the real 7-Scenes sample in {SHARED / 'data'} (absent)"
    return c





def chain(c: Command) -> str:
    """The chain a command runs in: the commands whose outputs it reads (its ``<...>`` placeholders
    match the newest folder the chain made) run before it in the same scratch folder; any other
    command is a chain of its own. tests/test_readme.py checks that every placeholder has its chain."""
    t = c.text
    if ("+experiment=k" in t and "scene=" not in t) or "logs/multirun/k/" in t:
        return "k-demo"  # the basic and joblib sweeps (same metrics), then the analysis of the newest
    if "_demo" in t or (c.key == "run" and not re.search(r"\b(scene|protocol)=", t)):
        return "demo-runs"  # the demo's runs, then the commands reading the newest diffuser/ldls runs
    if "_scannet0470" in t or ("scene=scannet0470" in t and "protocol=online" in t):
        return "online-scannet0470"
    return c.id


@functools.lru_cache(maxsize=1)
def readme_chains() -> dict[str, str]:
    """Each README command's test id -> its :func:`chain` (what tests/conftest.py schedules)."""
    return {c.id: chain(c) for c in readme_commands()}


def _labelled_rgbd(root: Path, world: dict) -> Path:
    """The RGB-D fixture with a label image for every frame (it leaves frame 1 out on purpose)."""
    from datasets import NYU, _save_u16

    _save_u16(root / "frame-000001.label.png", NYU[world["views"][1][2]])
    return root


def _newest(repo: Path, pattern: str) -> str:
    hits = sorted(repo.glob(pattern), key=lambda p: p.stat().st_mtime)
    assert hits, f"README placeholder {pattern!r}: nothing made by the commands before it matches"
    return str(hits[-1].relative_to(repo))


def resolve(text: str, work: dict) -> str:
    """Fill the placeholders: <...> path parts from what earlier commands made, CAPS from datasets."""
    for token in sorted(set(re.findall(r"[^\s\"']*<[a-z_]+>[^\s\"']*", text)), key=len, reverse=True):
        text = text.replace(token, _newest(work["repo"], re.sub(r"<[a-z_]+>", "*", token)))
    for name, value in work["placeholders"].items():
        text = re.sub(rf"(?<![\w.]){re.escape(name)}(?![\w])", value, text)
    return text


def _env() -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR",)}
    env["PYTHONUNBUFFERED"] = "1"
    return env


def own_data(folder: Path) -> dict[str, str]:
    """The CAPS placeholders of the own-data commands -> small datasets written under ``folder``."""
    sys.path.insert(0, str(ROOT / "tests"))
    from datasets import make_world, write_label_predictions, write_mesh_ply, write_rgbd, write_scannet

    from datasets import write_lab_layout, write_mseg_predictions

    world = make_world()
    folder.mkdir(parents=True, exist_ok=True)
    return {
        "MESH.ply": str(write_mesh_ply(folder / "room.labels.ply", world)),
        "SCANNET_SCENE": str(write_scannet(folder, world)),
        "RGBD_FOLDER": str(_labelled_rgbd(write_rgbd(folder, world), world)),
        "PRED_DIR": str(write_label_predictions(folder / "predictions", world, ["0", "1", "2", "3"])),
        "MSEG_PRED_DIR": str(write_mseg_predictions(folder / "mseg", world, ["0", "1", "2", "3"])),
        # the layout of conf/scene/my_rgbd_lab.yaml: (raw >> 3) / 1e4 m reaches 0.82 m, so a room at 1:8
        "LAB_FOLDER": str(write_lab_layout(folder, scaled_world(world, 0.125), depth_scale=1e4)),
        **(captures(folder / "captures") if HAVE_7SCENES else {}),
    }


def _test_module(name: str):
    """A format's test module (tests/data/sources/<name>.py), for its fixture writer."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, ROOT / "tests" / "data" / "sources" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def captures(folder: Path) -> dict[str, str]:
    """The capture formats' placeholders (:data:`CAPTURES`): 4 real 7-Scenes frames written in each
    layout by the formats' own test writers, with ground-truth label images where the layout has them:
    the grey-level classes of tests/toy_networks.py as ScanNet-20 ids (wall, floor, cabinet, bed; as
    NYU40 ids 1-4 for ScanNet's layouts), so the default simulated network runs and is scored."""
    import numpy as np
    from PIL import Image

    sys.path.insert(0, str(ROOT / "tests"))
    from captures import seven_frames
    from toy_networks import grey_levels

    frames = seven_frames(4, 20)
    grey = {f["name"]: grey_levels(np.asarray(Image.open(f["color_path"]).convert("RGB"))) for f in frames}
    K = frames[0]["K"]
    out = {"NERFSTUDIO_DIR": _test_module("test_nerfstudio").write_nerfstudio(folder, frames, labels=grey)}
    rep = _test_module("test_replica").write_replica(folder, frames)
    for i, f in enumerate(frames):  # loop over 4 frames: Replica's label images
        Image.fromarray(grey[f["name"]]).save(rep / "results" / f"semantic{i:06d}.png")
    out["REPLICA_DIR"] = rep
    tm = _test_module("test_templates")
    sens = tm.write_sensreader(folder / "sensreader", frames, K)
    split = tm.write_split(folder / "kitchen", frames, K)  # {scene}: the root's name
    (split / "labels").mkdir()
    for f in frames:  # loop over 4 frames: label-filt (NYU40 ids) and the split layout's labels
        n = int(f["name"].split("-")[1])
        Image.fromarray((grey[f["name"]] + 1).astype(np.uint8)).save(sens / f"frame-{n:06d}.label.png")
        Image.fromarray(grey[f["name"]]).save(split / "labels" / f"{n}.png")
    out["SENSREADER_DIR"], out["TEMPLATES_DIR"] = sens, split
    out["BAG"] = _test_module("test_rosbag").write_ros2_bag(folder / "capture_bag", frames, extra_depth=False)
    colmap = ROOT / "tests" / "data" / "sources" / "test_colmap.py"
    if colmap.is_file():
        out["COLMAP_DIR"] = _test_module("test_colmap").write_readme_fixture(folder / "colmap", frames, grey)
    return {k: str(v) for k, v in out.items()}


def scaled_world(world: dict, s: float) -> dict:
    """The fixture world at scale ``s`` (its mesh, camera positions and depth; the same images)."""
    import numpy as np

    poses = []
    for T in world["poses"]:
        T = np.array(T, np.float64)
        T[:3, 3] *= s
        poses.append(T)
    views = [(d * np.float32(s), lab, lab_c) for d, lab, lab_c in world["views"]]
    return {**world, "verts": world["verts"] * s, "poses": poses, "views": views}


def main(argv=None) -> int:
    """Run every README command verbatim from the current directory (a checkout's root)."""
    import argparse
    import subprocess
    import tempfile
    import time

    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("--only", help="run only the commands matching this regular expression")
    ap.add_argument("--log", help="also write each command's full output to this file")
    a = ap.parse_args(argv)
    work = {"repo": Path.cwd(), "placeholders": own_data(Path(tempfile.mkdtemp(prefix="readme-data-")))}
    log = open(a.log, "w") if a.log else None
    failed = 0
    for c in readme_commands():
        if a.only and not re.search(a.only, c.text):
            continue
        if c.skip or c.key == "pip":
            print(f"SKIP  {c.text}  ({c.skip or 'installs packages'})", flush=True)
            continue
        try:
            text = resolve(c.text, work)
        except AssertionError as exc:
            print(f"FAIL  {c.text}  ({exc})", flush=True)
            failed += 1
            continue
        t0 = time.perf_counter()
        argv_ = [sys.executable, "-c", text] if c.lang == "python" else ["bash", "-c", text]
        p = subprocess.run(argv_, env=_env(), capture_output=True, text=True)
        dt = time.perf_counter() - t0
        out = [ln for ln in p.stdout.splitlines() if ln.strip()]
        # the line that says most: a result row, a sweep's end, a file written, else the last one
        said = [r"^(diffuser|ldls|direct|bayesian) ", r"^sweep .* jobs ok", r"^(wrote |\{|result )", r"^\d+ runs"]
        say = next((ln for pat in said for ln in out if re.match(pat, ln)),
                   out[-1] if out else (p.stderr.strip().splitlines() or [""])[-1])
        print(f"{'ok  ' if p.returncode == 0 else 'FAIL'}  {dt:7.1f} s  {c.text.splitlines()[0][:110]}\n"
              f"              -> {say[:150]}", flush=True)
        failed += p.returncode != 0
        if log:
            log.write(f"$ {text}\n# exit {p.returncode}, {dt:.1f} s\n{p.stdout}{p.stderr}\n")
            log.flush()
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
