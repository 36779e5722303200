"""Every picture of the README and the documentation site, made from real runs (seeded, reproducible).

    python scripts/make_pictures.py                      # all of them into docs/images/
    python scripts/make_pictures.py --only overview,iterations --out /tmp/pictures

Each picture comes from a run of this package on a seeded scene (the demo room, the procedural city),
drawn with matplotlib: the 3D views are the run's points splatted into a virtual pinhole camera with
a z-buffer (numpy, no display needed), so the script runs headless. The sweep's plot and the
reliability diagram are :mod:`analysis.plots`' own PNGs of a real sweep run through the command line;
the report's paired section is ``analysis.report --html``'s page in a real browser (chromium --headless).
The viewer's screenshots come from ``scripts/viewer_screenshots.py`` (the real Rerun viewer under
Xvfb) when that script is there. PNGs are written palette-quantised (small: the docs' images stay
under 4 MB together, tests/test_docs.py).

Takes a few minutes on 2 cores (the city's tiled run and the sweep are the long ones).
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402
from PIL import Image  # noqa: E402

from diffuser_lab.data.geometry import project  # noqa: E402
from diffuser_lab.data.render import intrinsics, look_at  # noqa: E402
from diffuser_lab.data.scene import IGNORE  # noqa: E402

# the runs (diffuser_lab.run and the protocols) are imported where they run: drawing alone stays light

SEED = 0
GREY = np.array([200, 200, 200], np.uint8)  # unlabeled points / pixels
BACKGROUND = np.array([255, 255, 255], np.uint8)


# --- drawing ---------------------------------------------------------------------------------------

def splat(points: np.ndarray, colors: np.ndarray, K: np.ndarray, T_cw: np.ndarray, shape: tuple[int, int],
          radius: int = 1) -> np.ndarray:
    """(H, W, 3) uint8 image of ``points`` (N, 3) world metres with ``colors`` (N, 3) uint8 seen by
    the pinhole camera ``K`` (3, 3), ``T_cw`` (4, 4) world-to-camera: each point covers a square of
    (2 radius + 1)^2 pixels, the nearest point wins (z-buffer by sorting), white elsewhere."""
    h, w = shape
    u, v, z = project(points, K, T_cw)  # Eq. 2; NaN behind the camera
    front = np.flatnonzero(np.isfinite(u) & np.isfinite(v))
    u0, v0 = np.rint(u[front]).astype(np.int64), np.rint(v[front]).astype(np.int64)
    d = np.arange(-radius, radius + 1)
    du, dv = (a.ravel() for a in np.meshgrid(d, d))
    u = (u0[:, None] + du).ravel()
    v = (v0[:, None] + dv).ravel()
    z = np.repeat(z[front], du.size)
    src = np.repeat(front, du.size)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    flat, z, src = (v * w + u)[inside], z[inside], src[inside]
    order = np.lexsort((z, flat))  # per pixel, nearest first
    flat, src = flat[order], src[order]
    first = np.r_[True, flat[1:] != flat[:-1]]
    img = np.empty((h * w, 3), np.uint8)
    img[:] = BACKGROUND
    img[flat[first]] = colors[src[first]]
    return img.reshape(h, w, 3)


def label_colors(labels: np.ndarray, palette: np.ndarray) -> np.ndarray:
    """(N,) class ids -> (N, 3) uint8 colours, grey where IGNORE."""
    out = np.empty((labels.shape[0], 3), np.uint8)
    out[:] = GREY
    ok = labels != IGNORE
    out[ok] = palette[labels[ok]]
    return out


def heat_colors(values: np.ndarray, cmap: str = "inferno", lo: float | None = None, hi: float | None = None) -> np.ndarray:
    lo = np.nanmin(values) if lo is None else lo
    hi = np.nanmax(values) if hi is None else hi
    rgba = matplotlib.colormaps[cmap](np.clip((values - lo) / max(hi - lo, 1e-12), 0, 1))
    return (rgba[:, :3] * 255).astype(np.uint8)


class Dollhouse:
    """An oblique camera above a room's near corner; the ceiling and the two near walls are cut away
    (by position: any cloud of the room, the batch's or a growing map's, is cut the same way)."""

    def __init__(self, points: np.ndarray, shape=(420, 560), fov=54.0):
        lo, hi = points.min(0), points.max(0)
        self.lo, self.hi = lo, hi
        size = hi - lo
        centre = (lo + hi) / 2
        eye = np.array([lo[0] - 0.45 * size[0], lo[1] - 0.6 * size[1], hi[2] + 1.3 * size[2]])
        self.T_cw = look_at(eye, np.array([centre[0], centre[1], lo[2] + 0.2 * size[2]]))
        self.shape = shape
        self.K = intrinsics(shape[1], shape[0], fov)

    def keep(self, points: np.ndarray) -> np.ndarray:
        lo, hi = self.lo, self.hi
        return (points[:, 2] < hi[2] - 0.3) & (points[:, 0] > lo[0] + 0.12) & (points[:, 1] > lo[1] + 0.12)

    def __call__(self, points: np.ndarray, colors: np.ndarray, radius: int = 2) -> np.ndarray:
        k = self.keep(points)
        return splat(points[k], colors[k], self.K, self.T_cw, self.shape, radius)

    def frustum(self, ax, K: np.ndarray, T_cw: np.ndarray, shape, depth: float = 0.6, color="black") -> None:
        """Draw a frame's camera (its image rectangle at ``depth`` metres) into ``ax``."""
        h, w = shape
        corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)
        rays = np.c_[corners, np.ones(4)] @ np.linalg.inv(K).T * depth
        R, t = T_cw[:3, :3], T_cw[:3, 3]
        world = (rays - t) @ R  # camera -> world
        centre = -R.T @ t
        uv = np.stack(project(np.vstack([centre, world]), self.K, self.T_cw)[:2], 1)
        for i in range(1, 5):
            ax.plot(uv[[0, i], 0], uv[[0, i], 1], color=color, lw=1.2)
        ring = [1, 2, 3, 4, 1]
        lim = ax.get_xlim(), ax.get_ylim()
        ax.plot(uv[ring, 0], uv[ring, 1], color=color, lw=1.8)
        ax.set_xlim(*lim[0]), ax.set_ylim(*lim[1])


def legend(fig, names, palette, present, ncol=None, **kw) -> None:
    handles = [Patch(facecolor=palette[c] / 255.0, edgecolor="none", label=names[c]) for c in present]
    fig.legend(handles=handles, loc="lower center", ncol=ncol or min(len(handles), 8), frameon=False,
               fontsize=9, handlelength=1.2, columnspacing=1.0, **kw)


def imshow(ax, img, title: str) -> None:
    ax.imshow(img, interpolation="nearest")
    ax.set_title(title, fontsize=10)
    ax.set_axis_off()


def save(fig, path: Path, colors: int = 128) -> Path:
    """A palette PNG (``colors`` colours, optimised): a few tens of KB a picture."""
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=100, facecolor="white", bbox_inches="tight", pad_inches=0.08)
    plt.close(fig)
    quantise(tmp, path, colors)
    tmp.unlink()
    print(f"{path} ({path.stat().st_size / 1024:.0f} KB)")
    return path


def quantise(src: Path, dst: Path, colors: int = 128) -> None:
    Image.open(src).convert("RGB").quantize(colors, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE
                                            ).save(dst, optimize=True)


# --- the runs ----------------------------------------------------------------------------------------

def config(*overrides: str):
    """The resolved config of these command-line overrides (as ``diffuser-lab OVERRIDES`` composes it)."""
    from hydra import compose, initialize_config_dir

    from diffuser_lab.cli.main import config_dir
    from diffuser_lab.config import register, to_object
    from diffuser_lab.runs.resolve import resolve

    register()
    with initialize_config_dir(config_dir=config_dir(), version_base="1.3", job_name="pictures"):
        return resolve(to_object(compose("config", overrides=[f"seed={SEED}", *overrides])))


def demo_run():
    """The demo room's default run (seed 0), with the labels after chosen iterations."""
    steps = (1, 3, 10, 200)
    seen: dict[int, np.ndarray] = {}

    def observer(it, Z, stats):
        if it in steps:
            lab = Z.argmax(1).astype(np.int16)
            lab[Z.max(1) <= 0] = IGNORE  # no evidence reached the point yet
            seen[it] = lab

    from diffuser_lab import run

    res = run(config(), observer=observer)
    return res, seen


def overview(res, out: Path) -> Path:
    """A frame's 2D prediction, the 3D labels (Diffuser), the ground truth: the whole idea."""
    tax = res.scene.taxonomy
    pal = np.asarray(tax.colors)
    f = res.frames[12]
    cam = Dollhouse(res.scene.points)
    pred2d = label_colors(f.labels.ravel(), pal).reshape(*f.shape, 3)
    pred3d = cam(res.scene.points, label_colors(res.labels, pal))
    gt = cam(res.scene.points, label_colors(res.scene.gt_labels, pal))
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.6))
    imshow(axes[0], pred2d, f"a 2D network's labels of frame {f.name}\n(simulated, with its mistakes)")
    imshow(axes[1], pred3d, f"3D labels after the diffusion, {len(res.frames)} frames\n"
                            f"mIoU {res.metrics['miou']:.1f} (Bayesian fusion {res.baseline['bayesian']['miou']:.1f})")
    cam.frustum(axes[1], f.K, f.T_cw, f.shape)
    imshow(axes[2], gt, "ground truth")
    present = np.unique(res.scene.gt_labels[(res.scene.gt_labels != IGNORE) & cam.keep(res.scene.points)])
    legend(fig, tax.names, pal, present, ncol=(len(present) + 1) // 2)
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    return save(fig, out / "overview.png")


def iterations(res, seen: dict, out: Path) -> Path:
    """The labels after 1, 5, 20 and 200 iterations of Z <- P Z + B."""
    pal = np.asarray(res.scene.taxonomy.colors)
    cam = Dollhouse(res.work_points)
    fig, axes = plt.subplots(2, 2, figsize=(9.5, 7.4))
    axes = axes.ravel()
    gt = res.scene.gt_labels if res.voxels is None else None  # the demo diffuses its own points
    for ax, it in zip(axes, sorted(seen)):
        lab = seen[it]
        title = f"iteration {it}: {100.0 * np.mean(lab != IGNORE):.0f}% labelled"
        if gt is not None:
            scored = gt != IGNORE
            title += f", {100.0 * np.mean(lab[scored] == gt[scored]):.1f}% right"
        imshow(ax, cam(res.work_points, label_colors(lab, pal)), title)
    fig.tight_layout()
    return save(fig, out / "iterations.png")


def online_map(out: Path) -> Path:
    """protocol=online, online.map=growing: the map and its labels after a few of the 30 frames."""
    from diffuser_lab.hooks import RunHooks
    from diffuser_lab.runs.online import online

    at = (2, 9, 19, 29)
    shots = {}

    class Shots(RunHooks):
        def on_online_frame(self, frame, update):
            if update.index in at:
                shots[update.index] = (update.points.copy(), update.labels.copy(), update.metrics.get("miou"))

    cfg = config("protocol=online", "online.map=growing")
    res = online(cfg, hooks=Shots())
    pal = np.asarray(res.scene.taxonomy.colors)
    cam = Dollhouse(res.scene.points)  # the room's box: the map grows inside it
    fig, axes = plt.subplots(2, 2, figsize=(9.5, 7.4))
    for ax, i in zip(axes.ravel(), at):
        pts, lab, miou = shots[i]
        title = f"after frame {i + 1}: {pts.shape[0]:,} points"
        imshow(ax, cam(pts, label_colors(lab, pal)), title + (f", mIoU {miou:.1f}" if miou is not None else ""))
    fig.tight_layout()
    return save(fig, out / "online.png")


def city_tiles(out: Path, tmp: Path) -> Path:
    """scene=city (2 x 2 blocks) labelled by protocol=tiled: the labels from above, the tiles' grid."""
    from diffuser_lab.runs.tiled import tiled

    size = 41.0  # 3 x 3 tiles on the 2 x 2 blocks' 120 m (and their points' noise)
    cfg = config("scene=city", "predictions=realistic_city", "protocol=tiled", f"tiling.size={size:g}",
                 "scene.options.point_spacing=0.4")
    res = tiled(cfg, run_dir=tmp / "city")
    tax = res.scene.taxonomy
    pal = np.asarray(tax.colors)
    pts = res.scene.points
    lo, hi = pts.min(0), pts.max(0)
    # from above: a camera straight down, far enough to see the whole city
    span = float(max(hi[0] - lo[0], hi[1] - lo[1]))
    centre = (lo + hi) / 2
    shape = (520, 520)
    K = intrinsics(shape[1], shape[0], 40.0)
    T = look_at([centre[0], centre[1], hi[2] + 1.45 * span], [centre[0], centre[1], lo[2]], up=(0, 1, 0))
    fig, axes = plt.subplots(1, 2, figsize=(11, 6.0))
    imshow(axes[0], splat(pts, label_colors(res.labels, pal), K, T, shape),
           f"scene=city, 2 x 2 blocks, {pts.shape[0]:,} points:\nlabels of protocol=tiled "
           f"(mIoU {res.metrics['miou']:.1f}, Bayesian fusion {res.baseline['bayesian']['miou']:.1f}), tiles dashed")
    imshow(axes[1], splat(pts, label_colors(res.scene.gt_labels, pal), K, T, shape), "ground truth")
    # the tiles' edges: x-y lines projected into the top view
    nx, ny = res.grid
    size = res.tile_m  # tiling.size fitted to the cloud (runs.tiled.fitted_edge)
    origin = lo[:2]  # tile_grid's: the cloud's x-y minimum
    for ax in axes[:1]:
        for i in range(nx + 1):
            x = origin[0] + i * size
            seg = np.array([[x, origin[1], lo[2]], [x, origin[1] + ny * size, lo[2]]])
            _line(ax, seg, K, T)
        for j in range(ny + 1):
            y = origin[1] + j * size
            seg = np.array([[origin[0], y, lo[2]], [origin[0] + nx * size, y, lo[2]]])
            _line(ax, seg, K, T)
    present = np.unique(res.scene.gt_labels[res.scene.gt_labels != IGNORE])
    legend(fig, tax.names, pal, present, ncol=8)
    fig.tight_layout(rect=(0, 0.08, 1, 0.97))
    return save(fig, out / "city_tiles.png")


def _line(ax, seg, K, T):
    uv = np.stack(project(seg, K, T)[:2], 1)
    lim = ax.get_xlim(), ax.get_ylim()
    ax.plot(uv[:, 0], uv[:, 1], color="black", lw=1.3, ls="--")
    ax.set_xlim(*lim[0]), ax.set_ylim(*lim[1])  # the image's extent, not the lines'



def feature_query(out: Path) -> Path:
    """predictions=features: a word's cosine similarity with every point's diffused feature."""
    from diffuser_lab import run
    from diffuser_lab.method.queries import similarity

    res = run(config("predictions=features"))
    lift = res.space
    names = list(lift.queries.names)
    words = ["chair", "bed", "floor"]
    sim = similarity(lift.method, lift.queries)
    cam = Dollhouse(res.work_points)
    fig, axes = plt.subplots(1, len(words), figsize=(3.9 * len(words), 3.3))
    for ax, word in zip(axes, words):
        s = sim[:, names.index(word)]
        imshow(ax, cam(res.work_points, heat_colors(s, lo=0.0, hi=float(np.nanmax(s)))), f'query "{word}"')
    sm = plt.cm.ScalarMappable(cmap="inferno", norm=plt.Normalize(0, 1))
    fig.colorbar(sm, ax=axes, fraction=0.02, pad=0.01, label="cosine (0 to the query's best)")
    return save(fig, out / "query_heatmap.png", colors=192)


def sweep_plots(out: Path, tmp: Path) -> list[Path]:
    """A real sweep through the command line (+experiment=k, seeds 0 and 1), then analysis.plots."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), DIFFUSER_LAB_PROGRESS="0")
    subprocess.run([sys.executable, "-m", "diffuser_lab", "-m", "+experiment=k", "seed=0,1"],
                   cwd=tmp, env=env, check=True, stdout=subprocess.DEVNULL)
    sweeps = sorted((tmp / "logs" / "multirun" / "k").iterdir())
    env_run = dict(cwd=ROOT, env=env, check=True, stdout=subprocess.DEVNULL)
    plots = tmp / "plots"
    subprocess.run([sys.executable, "-m", "analysis.plots", str(sweeps[-1]), "--out", str(plots)], **env_run)
    # the reliability diagram of the paper's k (24) alone: one row, seeds pooled
    k24 = sorted(str(p) for p in sweeps[-1].iterdir() if p.is_dir() and "graph.k=24" in p.name)
    plots24 = tmp / "plots24"
    subprocess.run([sys.executable, "-m", "analysis.plots", *k24, "--out", str(plots24)], **env_run)
    made = []
    for src, name in ((plots / "miou_vs_graph.k.png", "sweep_k.png"), (plots24 / "reliability.png", "calibration.png")):
        if not src.is_file():
            raise SystemExit(f"analysis.plots made no {src.name} in {src.parent}: {sorted(p.name for p in src.parent.iterdir())}")
        quantise(src, out / name)
        print(f"{out / name} ({(out / name).stat().st_size / 1024:.0f} KB)")
        made.append(out / name)
    return made


def report_page(out: Path, tmp: Path) -> Path | None:
    """The paired section of ``analysis.report --html`` (+experiment=methods, seeds 0-5, the demo room)
    as a real browser shows it (chromium --headless; none installed: no picture, a line says so)."""
    import shutil

    from PIL import ImageOps

    from analysis.html import to_html

    browser = next((shutil.which(b) for b in ("chromium", "chromium-browser", "google-chrome") if shutil.which(b)), None)
    if browser is None:
        print("no chromium on PATH (apt-get install chromium): no report picture")
        return None
    env = dict(os.environ, PYTHONPATH=str(ROOT), DIFFUSER_LAB_PROGRESS="0")
    sweep = tmp / "methods"
    subprocess.run([sys.executable, "-m", "diffuser_lab", "-m", "+experiment=methods", "seed=0,1,2,3,4,5", "record=off",
                    "output.labels_ply=false", f"hydra.sweep.dir={sweep}"], cwd=tmp, env=env, check=True,
                   stdout=subprocess.DEVNULL)
    rep = tmp / "report"
    subprocess.run([sys.executable, "-m", "analysis.report", str(sweep), "--out", str(rep), "--html"], cwd=ROOT,
                   env=env, check=True, stdout=subprocess.DEVNULL)
    md = (rep / "report.md").read_text()
    page = rep / "paired.html"  # the section alone: the page's styles, its table and the forest plot
    page.write_text(to_html(md[md.index("## Paired differences"):md.index("## The same points")], rep, "paired"))
    shot = tmp / "report.png"
    subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", f"--screenshot={shot}",
                    "--window-size=1440,1400", page.as_uri()], check=True, capture_output=True)
    im = Image.open(shot).convert("RGB")
    bottom = ImageOps.invert(im).getbbox()[3]  # the page's last non-white row
    im = im.crop((0, 0, im.width, min(im.height, bottom + 16)))
    im.resize((1152, round(im.height * 1152 / im.width)), Image.LANCZOS).save(tmp / "report_small.png")
    quantise(tmp / "report_small.png", out / "report_paired.png")
    print(f"{out / 'report_paired.png'} ({(out / 'report_paired.png').stat().st_size / 1024:.0f} KB)")
    return out / "report_paired.png"


def viewer_shots(out: Path) -> list[Path]:
    """The real Rerun viewer's tabs, by scripts/viewer_screenshots.py (when that script exists)."""
    path = ROOT / "scripts" / "viewer_screenshots.py"
    if not path.exists():
        print(f"{path} not there: no viewer screenshots")
        return []
    spec = importlib.util.spec_from_file_location("viewer_screenshots", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.shoot_all(out)


PICTURES = ("overview", "iterations", "online", "city", "query", "sweep", "report", "viewer")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "images")
    ap.add_argument("--only", default=",".join(PICTURES), help=f"comma-separated subset of {','.join(PICTURES)}")
    args = ap.parse_args(argv)
    only = set(args.only.split(","))
    if only - set(PICTURES):
        ap.error(f"--only {args.only}: expected names among {','.join(PICTURES)}")
    args.out.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("DIFFUSER_LAB_PROGRESS", "0")
    with tempfile.TemporaryDirectory(prefix="pictures-") as t:
        tmp = Path(t)
        if only & {"overview", "iterations"}:
            res, seen = demo_run()
            if "overview" in only:
                overview(res, args.out)
            if "iterations" in only:
                iterations(res, seen, args.out)
        if "online" in only:
            online_map(args.out)
        if "query" in only:
            feature_query(args.out)
        if "city" in only:
            city_tiles(args.out, tmp)
        if "sweep" in only:
            sweep_plots(args.out, tmp)
        if "report" in only:
            report_page(args.out, tmp)
        if "viewer" in only:
            viewer_shots(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
