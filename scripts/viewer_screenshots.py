"""Screenshots of the real Rerun viewer, one per run kind, each run as the README runs it.

    PYTHONPATH=$PWD python scripts/viewer_screenshots.py OUT_DIR [--kinds batch,online] [--keep RUNS_DIR]

Each kind is run with the ``diffuser-lab`` command (its README line, plus
``hydra.run.dir`` into a scratch folder and ``output.quiet=true``), then its ``run.rrd`` is opened
in the viewer of the environment (``rerun`` beside the Python that runs this) in Xvfb on Mesa's
lavapipe Vulkan (``apt-get install xvfb mesa-vulkan-drivers imagemagick``): a picture of the
screen 12 s later (:data:`WAIT_S`: longer for a kind that loads longer) gives
``OUT_DIR/viewer-<kind>.png``, the run's own layout at the recording's last time, shrunk to
1200 px wide and quantised to 256 colours (ImageMagick: ~270 KB each).
``scripts/make_pictures.py`` (the documentation's pictures) calls :func:`shoot_all`.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

KINDS: dict[str, list[str]] = {
    # README "Quick start": the demo room, global protocol
    "batch": [],
    # README "Online": the map built from the depth
    "online": ["protocol=online", "online.map=growing"],
    # README "Outdoor, tiles, clusters": the demo room in 2 m tiles
    "tiled": ["protocol=tiled", "tiling.size=2"],
    # README "Real data": the single-frame protocol (Table II), on the demo room, its first 8 target frames
    "single-frame": ["protocol=single_frame", "protocol.max_targets=8"],
    # the same on a one-block city (cityscapes19, the README's city at a quarter of its size)
    "tiled-city": ["scene=city", "predictions=realistic_city", "scene.options.blocks_x=1", "scene.options.blocks_y=1",
                   "scene.options.point_spacing=0.3", "protocol=tiled", "tiling.size=25"],
}
WINDOW = "1600x1000"
WIDTH = 1200
WAIT_S = {"single-frame": 40.0}
"""Seconds from the viewer's start to the picture where a kind needs more than the default 12 s:
the single-frame record (8 targets' diffusions, ~11 MB) was still loading after 12 s under
lavapipe on a loaded 2-core machine (empty views, 2026-12-07), whole after 40 s."""


def _bin(name: str) -> str:
    exe = Path(sys.executable).with_name(name)
    return str(exe) if exe.is_file() else name


def run_kind(kind: str, run_dir: Path, timeout: float = 600.0) -> Path:
    """Run ``kind`` (:data:`KINDS`) into ``run_dir``; returns its run.rrd."""
    cmd = [_bin("diffuser-lab"), *KINDS[kind], "output.quiet=true", f"hydra.run.dir={run_dir}"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    rrd = run_dir / "run.rrd"
    if p.returncode != 0 or not rrd.is_file():
        raise RuntimeError(f"{kind}: {' '.join(cmd)} failed ({p.returncode}): {p.stderr.strip()[-400:]}")
    return rrd


def free_display(first: int = 90) -> int:
    """An X display number no server holds (no /tmp/.X<n>-lock): a viewer of an earlier shot
    still on a reused display would be in the picture."""
    n = first
    while Path(f"/tmp/.X{n}-lock").exists() or Path(f"/tmp/.X11-unix/X{n}").exists():
        n += 1
    return n


def screenshot(rrd: Path, png: Path, window: str = WINDOW, wait_s: float = 12.0, display: int | None = None) -> Path:
    """The viewer's window on ``rrd`` (its default blueprint), ``wait_s`` after it started, as ``png``,
    shrunk and quantised: the real viewer in an X server of its own (Xvfb), as a user opens it
    (``rerun --headless --screenshot-to`` shoots before a recording with a timeline has loaded)."""
    missing = [f"{exe} ({pkg})" for exe, pkg in (("Xvfb", "xvfb"), ("import", "imagemagick"),
                                                 ("convert", "imagemagick")) if shutil.which(exe) is None]
    if missing:
        raise RuntimeError(f"not installed: {', '.join(missing)}; apt-get install xvfb imagemagick mesa-vulkan-drivers")
    png.parent.mkdir(parents=True, exist_ok=True)
    raw = png.with_suffix(".raw.png")
    w, h = window.split("x")
    display = free_display() if display is None else display
    env = dict(os.environ, DISPLAY=f":{display}", WGPU_BACKEND="vulkan")
    # -extension Composite: without it the viewer gets a 32-bit visual and draws black
    xvfb = subprocess.Popen(["Xvfb", f":{display}", "-screen", "0", f"{w}x{h}x24", "-extension", "Composite"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    viewer = None
    try:
        time.sleep(1.0)
        viewer = subprocess.Popen([_bin("rerun"), str(rrd), "--new", "--window-size", window],
                                  env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(wait_s)
        subprocess.run(["import", "-window", "root", str(raw)], env=env, check=True, timeout=60)
    finally:
        for p in (viewer, xvfb):
            if p is not None:
                p.terminate()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
    subprocess.run(["convert", str(raw), "-resize", f"{WIDTH}x>", "-colors", "256", "-strip", f"PNG8:{png}"],
                   check=True, timeout=120)
    raw.unlink()
    return png


def shoot_all(out_dir: Path, kinds: list[str] | None = None, runs_dir: Path | None = None) -> list[Path]:
    """Run each kind (:data:`KINDS`, all by default) and write ``out_dir/viewer-<kind>.png``, the
    viewer on its run.rrd; returns the PNGs' paths. ``runs_dir``: keep the runs there (default: a
    temporary folder, removed)."""
    out_dir = Path(out_dir)
    tmp = None if runs_dir is not None else tempfile.TemporaryDirectory(prefix="viewer-shots-")
    base = Path(runs_dir if runs_dir is not None else tmp.name)
    try:
        return [screenshot(run_kind(k, base / k), out_dir / f"viewer-{k}.png", wait_s=WAIT_S.get(k, 12.0))
                for k in (kinds or list(KINDS))]
    finally:
        if tmp is not None:
            tmp.cleanup()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--kinds", default=",".join(KINDS), help=f"comma-separated, of {', '.join(KINDS)}")
    ap.add_argument("--keep", type=Path, default=None, help="keep the runs in this folder")
    ap.add_argument("--rrd", type=Path, default=None, help="shoot this run.rrd only (no run), as --kinds' one kind")
    a = ap.parse_args(argv)
    kinds = [k for k in a.kinds.split(",") if k]
    bad = [k for k in kinds if k not in KINDS]
    if bad:
        ap.error(f"--kinds: unknown {', '.join(bad)}; expected some of {', '.join(KINDS)}")
    try:
        shots = ([screenshot(a.rrd, a.out_dir / f"viewer-{kinds[0]}.png", wait_s=WAIT_S.get(kinds[0], 12.0))]
                 if a.rrd is not None
                 else shoot_all(a.out_dir, kinds, a.keep))
    except (RuntimeError, subprocess.SubprocessError, OSError) as exc:
        print(f"viewer_screenshots: error: {exc}", file=sys.stderr)
        return 1
    for p in shots:
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
