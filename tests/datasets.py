"""Small datasets the tests write in the layouts the loaders read: the demo room rendered from a
few cameras, saved as a ScanNet export and as a posed RGB-D folder (7-Scenes naming), and the
labelled mesh itself. Used by test_sources.py and by test_readme.py (the README's own-data commands)."""
from pathlib import Path

import numpy as np
from PIL import Image
from plyfile import PlyData, PlyElement

from diffuser_lab.data.render import MeshRenderer, intrinsics, look_at
from diffuser_lab.data.scene import SCANNET20, SCANNET20_NYU40_IDS
from diffuser_lab.data.sources.demo import demo_mesh
from diffuser_lab.data.sources.scannet import scaled_intrinsics

W, H = 80, 60  # depth resolution of the fixtures
CW, CH = 200, 150  # "colour" resolution (2.5x, like ScanNet's 1296x968 vs 640x480)
EYES = [(2.0, 1.5, 1.6), (2.2, 1.5, 1.6), (2.4, 1.6, 1.6), (2.6, 1.7, 1.6)]
TARGET = (3.8, 3.2, 0.6)
BAD_POSE = 2  # frame written with an all -inf pose (ScanNet's "tracking lost")
NYU = np.append(np.array(SCANNET20_NYU40_IDS), 0)  # SCANNET20 id -> NYU40 id; IGNORE (-1) -> 0


def make_world() -> dict:
    """Demo room mesh, its renderer, cameras and the rendered depth/label images."""
    verts, tris, tri_lab = demo_mesh(0)
    r = MeshRenderer(verts, tris, tri_lab)
    K = intrinsics(W, H, 70.0)
    Kc = scaled_intrinsics(K, (H, W), (CH, CW))
    poses = [look_at(e, TARGET) for e in EYES]
    views = []
    for T in poses:  # loop over 4 views
        depth, lab = r.render(K, T, W, H)
        _, lab_c = r.render(Kc, T, CW, CH)
        assert np.count_nonzero(depth) > 0.9 * depth.size, "the fixture cameras must see the room"
        views.append((depth, lab, lab_c))
    return dict(verts=verts, tris=tris, tri_lab=tri_lab, K=K, Kc=Kc, poses=poses, views=views)


def _save_u16(path, arr):
    Image.fromarray(np.asarray(arr, np.uint16)).save(path)


def _write_mesh(path, verts, tris, labels=None):
    dt = [("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("alpha", "u1")]
    if labels is not None:
        dt.append(("label", "u2"))
    v = np.zeros(len(verts), dt)
    v["x"], v["y"], v["z"] = verts.T
    v["red"], v["green"], v["blue"], v["alpha"] = 100, 150, 200, 255
    if labels is not None:
        v["label"] = labels
    f = np.zeros(len(tris), [("vertex_indices", "i4", (3,))])
    f["vertex_indices"] = tris
    PlyData([PlyElement.describe(v, "vertex"), PlyElement.describe(f, "face")]).write(str(path))


def _vertex_nyu(world):
    lab = np.zeros(len(world["verts"]), np.int64)
    lab[world["tris"].ravel()] = np.repeat(NYU[world["tri_lab"]], 3)  # box vertices are not shared
    return lab


def _c2w(T_cw):
    return np.linalg.inv(T_cw)


def write_scannet(parent: Path, world: dict) -> Path:
    """A ScanNet export ``parent/scene0999_00`` of the world (frame 2 has ScanNet's -inf "tracking lost" pose)."""
    root = Path(parent) / "scene0999_00"
    for sub in ("color", "depth", "pose", "intrinsic", "label-filt"):
        (root / sub).mkdir(parents=True)
    _write_mesh(root / "scene0999_00_vh_clean_2.ply", world["verts"], world["tris"])
    _write_mesh(root / "scene0999_00_vh_clean_2.labels.ply", world["verts"], world["tris"], _vertex_nyu(world))
    for name, K in (("intrinsic_depth.txt", world["K"]), ("intrinsic_color.txt", world["Kc"])):
        K4 = np.eye(4)
        K4[:3, :3] = K
        np.savetxt(root / "intrinsic" / name, K4)
    for i, (T, (depth, _, lab_c)) in enumerate(zip(world["poses"], world["views"])):
        _save_u16(root / "depth" / f"{i}.png", np.rint(depth * 1000))
        _save_u16(root / "label-filt" / f"{i}.png", NYU[lab_c])
        Image.fromarray(SCANNET20.colorize(lab_c)).save(root / "color" / f"{i}.jpg")
        np.savetxt(root / "pose" / f"{i}.txt", np.full((4, 4), -np.inf) if i == BAD_POSE else _c2w(T))
    return root


def write_rgbd(parent: Path, world: dict) -> Path:
    """A posed RGB-D folder ``parent/seq`` (7-Scenes naming, 65535 = invalid depth; NYU40 label
    images ``frame-XXXXXX.label.png`` for every frame but frame 1)."""
    root = Path(parent) / "seq"
    root.mkdir()
    np.savetxt(root / "camera-intrinsics.txt", world["K"])
    for i, (T, (depth, lab, lab_c)) in enumerate(zip(world["poses"], world["views"])):
        stem = root / f"frame-{i:06d}"
        d = np.rint(depth * 1000)
        d[depth == 0] = 65535  # 7-Scenes' invalid marker
        _save_u16(f"{stem}.depth.png", d)
        np.savetxt(f"{stem}.pose.txt", _c2w(T))
        Image.fromarray(SCANNET20.colorize(lab_c)).save(f"{stem}.color.jpg")  # colour at another size
        if i != 1:
            _save_u16(f"{stem}.label.png", NYU[lab_c])
    return root


def write_mesh_ply(path: Path, world: dict) -> Path:
    """The room as a labelled mesh PLY (per-vertex NYU40 ``label``), as ScanNet's ``.labels.ply``."""
    _write_mesh(path, world["verts"], world["tris"], _vertex_nyu(world))
    return Path(path)


def write_label_predictions(folder: Path, world: dict, names: list[str]) -> Path:
    """A "network's" NYU40 label PNGs at depth resolution, one per frame name (the rendered truth)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for name, (_, lab, _) in zip(names, world["views"]):
        _save_u16(folder / f"{name}.png", NYU[lab])
    return folder


def write_mseg_predictions(folder: Path, world: dict, names: list[str]) -> Path:
    """An MSeg network's label PNGs (universal taxonomy ids, 255 = unlabeled) at depth resolution:
    each ScanNet-20 class of the rendered truth written as the first MSeg class that maps to it
    (diffuser_lab/data/mappings/mseg_universal_to_scannet20.csv)."""
    from diffuser_lab.data.mapping import load_mapping

    m = load_mapping("mseg_universal_to_scannet20", SCANNET20)
    lut = np.full(SCANNET20.num_classes, 255, np.uint8)
    for src in np.flatnonzero(m.lut >= 0)[::-1]:  # the first source id of each target wins
        lut[m.lut[src]] = src
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for name, (_, lab, _) in zip(names, world["views"]):
        Image.fromarray(np.where(lab >= 0, lut[np.clip(lab, 0, None)], 255).astype(np.uint8)).save(folder / f"{name}.png")
    return folder


def encode_depth(depth_m, scale: float, shift: int = 0, kind: str = "plain", flags: int = 0) -> np.ndarray:
    """Metres -> raw 16-bit values as a depth camera writes them: round(d * scale), then shifted left
    by ``shift`` with ``flags`` in the freed low bits (``plain``) or rotated left (``circular``, SUN3D)."""
    v = np.rint(np.asarray(depth_m, np.float64) * scale).astype(np.uint32)
    if kind == "plain":
        out = (v << shift) | (np.uint32(flags) & ((1 << shift) - 1))
        out[v == 0] = 0
        assert (out <= 0xFFFF).all(), "depth does not fit 16 bits with this scale and shift"
    else:
        assert (v <= 0xFFFF).all(), "depth does not fit 16 bits with this scale"
        out = ((v << shift) | (v >> (16 - shift))) if shift else v
    return (out & 0xFFFF).astype(np.uint16)


def write_lab_layout(parent: Path, world: dict, *, name: str = "lab", intrinsics_file="camera-intrinsics.color.txt",
                     prefix="frame-", color="color.png", depth="depth.png", pose="pose.txt", segm="segm.png",
                     label=None, depth_scale=1000.0, shift=3, kind="plain", world_to_camera=False) -> Path:
    """A posed RGB-D folder in another lab's layout (the names are arguments): colour, depth encoded by
    :func:`encode_depth` (flags 0b101 in the low bits for ``plain``; 0 = no depth), 4x4 poses
    (camera-to-world unless ``world_to_camera``), a network's NYU40 ids at colour resolution
    (``segm``) and optionally ground truth (``label``) in the same space."""
    root = Path(parent) / name
    root.mkdir(parents=True)
    np.savetxt(root / intrinsics_file, world["K"])
    for i, (T, (d, lab, lab_c)) in enumerate(zip(world["poses"], world["views"])):
        stem = root / f"{prefix}{i:06d}"
        _save_u16(f"{stem}.{depth}", encode_depth(d, depth_scale, shift, kind, flags=5))
        np.savetxt(f"{stem}.{pose}", T if world_to_camera else _c2w(T))
        if color:
            Image.fromarray(SCANNET20.colorize(lab_c)).save(f"{stem}.{color}")
        if segm:
            _save_u16(f"{stem}.{segm}", NYU[lab_c])
        if label:
            _save_u16(f"{stem}.{label}", NYU[lab_c])
    return root


def write_tum(parent: Path, world: dict, name: str = "rgbd_dataset_freiburg2_fixture") -> tuple[Path, dict]:
    """A TUM RGB-D sequence of the world's views: rgb/ depth/ PNGs (depth x 5000), rgb.txt, depth.txt,
    groundtruth.txt (quaternion camera-to-world poses). The clocks differ: RGB 5 ms after depth, poses 3 ms
    before; two extra depth images are unmatched: one has its RGB 50 ms away, one no pose within 0.02 s.
    Returns the folder and the expected association (depth index -> view, RGB stems, depth times)."""
    from scipy.spatial.transform import Rotation

    root = Path(parent) / name
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    t0 = 1305031102.0
    views = list(range(len(world["views"])))
    t_depth = [t0 + 0.1 * k for k in views] + [t0 + 1.0, t0 + 2.0]  # two extras, dropped
    t_rgb = [t + 0.005 for t in t_depth[:-2]] + [t0 + 1.05, t0 + 2.005]
    t_pose = [t - 0.003 for t in t_depth[:-2]] + [t0 + 1.003, t0 + 2.5]
    src = views + [0, 1]  # the extras show views 0 and 1 again
    rgb_lines, depth_lines, gt_lines = ["# color images", "# timestamp filename"], ["# depth maps"], \
        ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    for td, tr, tp, v in zip(t_depth, t_rgb, t_pose, src):
        d, _, lab_c = world["views"][v]
        _save_u16(root / "depth" / f"{td:.6f}.png", np.rint(d * 5000))
        Image.fromarray(SCANNET20.colorize(world["views"][v][1])).save(root / "rgb" / f"{tr:.6f}.png")
        depth_lines.append(f"{td:.6f} depth/{td:.6f}.png")
        rgb_lines.append(f"{tr:.6f} rgb/{tr:.6f}.png")
        T_wc = _c2w(world["poses"][v])
        q = Rotation.from_matrix(T_wc[:3, :3]).as_quat()  # x y z w
        gt_lines.append(f"{tp:.6f} " + " ".join(f"{x:.9f}" for x in (*T_wc[:3, 3], *q)))
    # the lists are not required to be sorted: write rgb.txt reversed
    (root / "rgb.txt").write_text("\n".join(rgb_lines[:2] + rgb_lines[2:][::-1]) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    expected = {"views": views, "rgb_stems": [f"{t:.6f}" for t in t_rgb[:-2]], "t_depth": t_depth[:-2]}
    return root, expected


def scannet_mesh(folder: Path) -> dict:
    """A real ScanNet mesh (``<scene>_vh_clean_2.ply`` and its ``.labels.ply``, e.g. ../shared/data's
    scene0470_00) as :func:`write_scannet_sequence` takes it: vertices, triangles, per-vertex NYU40
    labels and colours."""
    from diffuser_lab.data.meshes import read_labelled_mesh

    folder = Path(folder)
    verts, tris, _, colors = read_labelled_mesh(folder / f"{folder.name}_vh_clean_2.ply")
    _, _, labels, _ = read_labelled_mesh(folder / f"{folder.name}_vh_clean_2.labels.ply")
    return dict(verts=verts, tris=tris, labels=labels, colors=colors)


def demo_room_mesh() -> dict:
    """The demo room as :func:`write_scannet_sequence` takes it (colours: its classes' palette)."""
    verts, tris, tri_lab = demo_mesh(0)
    world = dict(verts=verts, tris=tris, tri_lab=tri_lab)
    labels = _vertex_nyu(world)
    colors = SCANNET20.colorize(np.clip(np.searchsorted(NYU[:-1], labels), 0, len(NYU) - 2)).astype(np.uint8)
    return dict(verts=verts, tris=tris, labels=labels, colors=colors)


def sweep_poses(verts: np.ndarray, n_views: int, *, arc_deg: float = 100.0, track_m: float = 1.0) -> list[np.ndarray]:
    """``n_views`` world-to-camera poses of a hand-held sweep across a room: from a third of the way
    along its long axis the camera walks ``track_m`` further along it, at three quarters of the mesh's
    height, panning ``arc_deg`` about the long axis' direction and looking 25 degrees down (even steps:
    with 100 views, 1 cm and 1 degree a frame: a slow hand at 30 Hz)."""
    lo, hi = verts.min(0).astype(np.float64), verts.max(0).astype(np.float64)
    a = 0 if hi[0] - lo[0] >= hi[1] - lo[1] else 1
    out = []
    for s in np.linspace(-0.5, 0.5, n_views):  # loop over views
        eye = (lo + hi) / 2
        eye[a] = lo[a] + (hi[a] - lo[a]) / 3 + (s + 0.5) * track_m
        eye[2] = lo[2] + 0.75 * (hi[2] - lo[2])
        yaw = np.deg2rad(s * arc_deg) + (np.pi / 2 if a == 1 else 0.0)
        out.append(look_at(eye, eye + [np.cos(yaw), np.sin(yaw), -np.tan(np.deg2rad(25.0))]))
    return out


def write_scannet_sequence(parent: Path, n_frames: int, mesh: dict | None = None, *, n_views: int = 12,
                           name: str = "scene0998_00", depth_size=(60, 80), color_size=(150, 200),
                           fov_deg: float = 60.0, mistakes: float = 0.1, seed: int = 0) -> Path:
    """A ScanNet export of ``n_frames`` frames at sensor rate: ``parent/name`` with the mesh's PLYs,
    ``depth/<i>.png`` (16-bit mm, ``depth_size`` = (H, W)), ``color/<i>.jpg`` (``color_size``, the
    mesh's colours with sensor noise, quality 90), ``pose/<i>.txt``, ``intrinsic/`` (depth and colour K)
    and beside it ``predictions/<i>.png``: a network's NYU40 labels at depth resolution (the rendered
    truth with a ``mistakes`` share of each image, one seeded rectangle, set to another class).

    The camera sweeps back and forth (:func:`sweep_poses`, ``n_views`` distinct views, ping-pong:
    frame i shows view ``i mod (2 n_views - 2)`` folded), as a hand-held scan does; each view is
    rendered once and a frame that repeats one is a hard link to its files (a 5,000-frame export
    costs the disk of ``n_views`` frames). ``mesh``: :func:`scannet_mesh` or :func:`demo_room_mesh`
    (default). ScanNet's full sizes: ``depth_size=(480, 640), color_size=(968, 1296)``."""
    import os

    mesh = mesh if mesh is not None else demo_room_mesh()
    root = Path(parent) / name
    for sub in ("color", "depth", "pose", "intrinsic"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    preds = Path(parent) / "predictions"
    preds.mkdir(exist_ok=True)
    verts, tris, vlab, vcol = mesh["verts"], mesh["tris"], mesh["labels"], mesh["colors"]
    world = dict(verts=verts, tris=tris, tri_lab=np.zeros(len(tris), np.int64))
    _write_mesh(root / f"{name}_vh_clean_2.ply", verts, tris)
    _write_mesh(root / f"{name}_vh_clean_2.labels.ply", verts, tris, vlab)
    (H, W), (CH_, CW_) = depth_size, color_size
    K = intrinsics(W, H, fov_deg)
    Kc = scaled_intrinsics(K, (H, W), (CH_, CW_))
    for fname, k in (("intrinsic_depth.txt", K), ("intrinsic_color.txt", Kc)):
        K4 = np.eye(4)
        K4[:3, :3] = k
        np.savetxt(root / "intrinsic" / fname, K4)
    r = MeshRenderer(verts, tris, np.zeros(len(tris), np.int64))
    tri_nyu = np.asarray(vlab, np.int64)[tris[:, 0]]
    tri_col = np.append(vcol[tris].mean(1), [[0, 0, 0]], 0).astype(np.float32)  # no hit: black
    poses = sweep_poses(verts, n_views)
    period = max(2 * n_views - 2, 1)
    for i in range(n_frames):  # loop over frames: a view's files are written once, then linked
        v = i % period
        v = v if v < n_views else period - v
        files = [root / "depth" / f"{i}.png", root / "color" / f"{i}.jpg", root / "pose" / f"{i}.txt",
                 preds / f"{i}.png"]
        if i != v:
            for f, src in zip(files, (root / "depth" / f"{v}.png", root / "color" / f"{v}.jpg",
                                      root / "pose" / f"{v}.txt", preds / f"{v}.png")):
                os.link(src, f)
            continue
        T = poses[v]
        depth, _, prim = r._render(K, T, W, H)
        nyu = np.where(prim < len(tris), np.append(tri_nyu, 0)[prim], 0)
        _, _, prim_c = r._render(Kc, T, CW_, CH_)
        rng = np.random.default_rng([seed, v])
        rgb = tri_col[prim_c] + rng.normal(0, 4.0, (CH_, CW_, 3))
        Image.fromarray(np.clip(np.rint(rgb), 0, 255).astype(np.uint8)).save(files[1], quality=90)
        _save_u16(files[0], np.rint(depth * 1000))
        np.savetxt(files[2], _c2w(T))
        pred = nyu.copy()
        if mistakes > 0:  # one rectangle of a wrong class over a ``mistakes`` share of the image
            h, w = max(1, int(H * np.sqrt(mistakes))), max(1, int(W * np.sqrt(mistakes)))
            r0, c0 = rng.integers(0, H - h + 1), rng.integers(0, W - w + 1)
            pred[r0:r0 + h, c0:c0 + w] = NYU[rng.integers(0, len(NYU) - 1)]
        _save_u16(files[3], pred)
    return root
