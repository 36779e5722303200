"""Bad input gives one clear line (exit code non-zero, no traceback) or a one-line warning.

Each case starts from a small valid posed RGB-D folder (rendered from the demo room) and
breaks one thing, then runs the command line as a user would.
"""
import json

import numpy as np
import pytest
from conftest import run_cli
from PIL import Image
from plyfile import PlyData, PlyElement

from diffuser_lab.data.render import intrinsics, look_at
from diffuser_lab.data.sources.demo import make_demo_scene

W, H = 64, 48


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    """A posed RGB-D folder (3 frames, labels in ScanNet-20 ids) and the room's sampled cloud."""
    scene, renderer = make_demo_scene(seed=0, n_views=1, point_spacing=0.1)
    root = tmp_path_factory.mktemp("rgbd") / "seq"
    root.mkdir()
    K = intrinsics(W, H, 70.0)
    np.savetxt(root / "camera-intrinsics.txt", K)
    for i, eye in enumerate([(1.5, 1.2, 1.5), (2.0, 1.3, 1.5), (2.5, 1.4, 1.5)]):
        T = look_at(eye, (3.5, 3.0, 0.5))
        depth, lab = renderer.render(K, T, W, H)
        stem = root / f"frame-{i:06d}"
        Image.fromarray(np.rint(depth * 1000).astype(np.uint16)).save(f"{stem}.depth.png")
        Image.fromarray(np.where(lab < 0, 255, lab).astype(np.uint8)).save(f"{stem}.label.png")
        Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(f"{stem}.color.jpg")
        np.savetxt(f"{stem}.pose.txt", np.linalg.inv(T))
    (root.parent / "mapping.csv").write_text("source_id,source_name,target\n" + "".join(
        f"{i},{n},{n}\n" for i, n in enumerate(scene.taxonomy.names)) + "255,void,ignore\n")
    return root, scene


def write_ply(path, pts, labels=None):
    dt = [("x", "f4"), ("y", "f4"), ("z", "f4")] + ([("label", "u1")] if labels is not None else [])
    v = np.zeros(len(pts), dt)
    if len(pts):
        v["x"], v["y"], v["z"] = np.asarray(pts, np.float32).T
    if labels is not None:
        v["label"] = np.where(labels < 0, 255, labels)  # 255 = void in mapping.csv
    PlyData([PlyElement.describe(v, "vertex")]).write(str(path))


def copy(good, tmp_path):
    import shutil

    root, scene = good
    dst = tmp_path / "seq"
    shutil.copytree(root, dst)
    shutil.copy(root.parent / "mapping.csv", tmp_path / "mapping.csv")
    return dst, scene


def cli(root, *extra, cwd, predictions="gt"):
    args = ["scene=rgbd_folder", f"scene.options.root={root}", "scene.options.label_suffix=label.png",
            f"scene.options.mapping={root.parent / 'mapping.csv'}", "scene.options.cloud_voxel=0.05",
            f"predictions={predictions}", "record=off", "solver.max_iter=30", "graph.k=8", *extra]
    return run_cli(*args, f"hydra.run.dir={cwd / 'run'}", cwd=cwd)


def one_error(p, *needles):
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert p.returncode != 0, p.stdout
    assert len(lines) == 1 and lines[0].startswith("diffuser-lab: error:"), p.stderr
    assert "Traceback" not in p.stderr
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


def warnings_of(p):
    return [ln for ln in p.stderr.splitlines() if ln.startswith("diffuser-lab: warning:")]


def test_the_good_folder_runs(good, tmp_path):
    root, _ = copy(good, tmp_path)
    p = cli(root, cwd=tmp_path)  # the cloud back-projected from the depth frames
    assert p.returncode == 0, p.stderr
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert s["status"] == "ok" and s["predictions_2d"]["miou"] == 100 and not warnings_of(p)
    assert s["coverage_evidence"] > 90


def test_missing_folder(tmp_path):
    (tmp_path / "mapping.csv").write_text("source_id,source_name,target\n0,wall,wall\n")
    one_error(cli(tmp_path / "nope", cwd=tmp_path), "does not exist")


@pytest.mark.parametrize("scene,key", [("rgbd_folder", "scene.options.root"), ("scannet", "scene.options.root"),
                                       ("mesh_views", "scene.options.path")])
def test_missing_required_path_stops_at_start_up(scene, key, tmp_path):
    p = run_cli(f"scene={scene}", cwd=tmp_path)
    one_error(p, f"{key} is required")
    assert p.returncode == 2 and not (tmp_path / "logs").exists()  # nothing was started


def test_every_scene_source_has_one_shape():
    """Every scene source owns an options dataclass in its own module (``scene.options.KEY``, typed
    and range-checked); SceneConfig holds no source's keys; a required key is asked for only when
    its source is selected, by its new name."""
    import dataclasses

    from omegaconf import MISSING

    from diffuser_lab.config import Section, SceneConfig
    from diffuser_lab.data.sources import SOURCES
    from diffuser_lab.runs.resolve import default_config

    # besides its options, what every source's frames share: keyframes and the read-ahead (issue 52)
    assert {f.name for f in dataclasses.fields(SceneConfig)} == {"source", "name", "voxel_size", "options",
                                                                 "keyframe_translation", "keyframe_rotation_deg",
                                                                 "read_ahead"}
    for entry in SOURCES.values():
        assert entry.options is not None and issubclass(entry.options, Section), entry.name
        assert entry.options.KEY == "scene.options" and entry.options.__module__ == entry.load.__module__
    required = {e.name for e in SOURCES.values()
                if any(f.default is MISSING and f.default_factory is dataclasses.MISSING
                       for f in dataclasses.fields(e.options))}
    assert {"scannet", "mesh_views", "rgbd_folder", "tum", "colmap"} <= required
    assert type(default_config().scene.options).__name__ == "DemoOptions"
    for source in sorted(required):
        with pytest.raises(ValueError, match=r"^scene\.options\.\w+ is required"):
            default_config(**{"scene.source": source})


def test_an_old_spelling_names_the_new_key(tmp_path):
    """``scene.<source>.KEY`` (the built-in sources' spelling until 2026-12) stops with one line
    naming ``scene.options.KEY``, on the command line (also with -m) and in the library."""
    from diffuser_lab.config import ConfigError, default_config

    for args, new in ((["scene.demo.n_views=3"], "scene.options.n_views"),
                      (["-m", "+scene.city.blocks_x=1"], "scene.options.blocks_x")):  # forked commands (run_cli)
        p = run_cli(*args, cwd=tmp_path)
        one_error(p, f"is now {new}")
        assert p.returncode == 2 and not (tmp_path / "logs").exists()
    for old, new in (("scene.demo.n_views", "scene.options.n_views"), ("scene.scannet.root", "scene.options.root"),
                     ("scene.city.blocks_x", "scene.options.blocks_x")):
        with pytest.raises(ConfigError, match=f"{old} is now {new}"):
            default_config(**{old: 1})


def test_frame_counts_differ(good, tmp_path):
    root, _ = copy(good, tmp_path)
    (root / "frame-000001.pose.txt").unlink()
    one_error(cli(root, cwd=tmp_path), "3 depth", "2 pose")


def test_pose_not_rigid(good, tmp_path):
    root, _ = copy(good, tmp_path)
    T = np.loadtxt(root / "frame-000001.pose.txt")
    T[:3, :3] *= 1.5
    np.savetxt(root / "frame-000001.pose.txt", T)
    one_error(cli(root, cwd=tmp_path), "frame-000001.pose.txt", "rigid")


def test_pose_with_text(good, tmp_path):
    root, _ = copy(good, tmp_path)
    (root / "frame-000002.pose.txt").write_text("1 0 0 0\n0 1 zero 0\n")
    one_error(cli(root, cwd=tmp_path), "frame-000002.pose.txt")


def test_inverse_pose_convention_warns(good, tmp_path):
    root, scene = copy(good, tmp_path)
    for f in sorted(root.glob("*.pose.txt")):
        np.savetxt(f, np.linalg.inv(np.loadtxt(f)))  # world-to-camera written where camera-to-world belongs
    write_ply(tmp_path / "cloud.ply", scene.points)
    p = cli(root, f"scene.options.cloud={tmp_path / 'cloud.ply'}", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert any("inverse convention" in w for w in warnings_of(p)), p.stderr


def test_intrinsics_of_another_resolution(good, tmp_path):
    root, _ = copy(good, tmp_path)
    K = np.loadtxt(root / "camera-intrinsics.txt")
    K[:2] *= 4  # the colour camera's K at 4x the depth resolution
    np.savetxt(root / "camera-intrinsics.txt", K)
    one_error(cli(root, cwd=tmp_path), "principal point", "outside")


def test_label_ids_outside_the_mapping(good, tmp_path):
    root, _ = copy(good, tmp_path)
    lab = np.array(Image.open(root / "frame-000000.label.png"))
    lab[:4, :4] = 77
    Image.fromarray(lab).save(root / "frame-000000.label.png")
    one_error(cli(root, cwd=tmp_path), "77")


def test_depth_in_the_wrong_unit_warns(good, tmp_path):
    root, _ = copy(good, tmp_path)
    p = cli(root, "scene.options.depth_scale=1", cwd=tmp_path)  # millimetres read as metres
    assert any("depth_scale" in w for w in warnings_of(p)), p.stderr


@pytest.mark.parametrize("case,needle", [("nan", "NaN"), ("empty", "empty"), ("no_xyz", "x/y/z"),
                                         ("garbage", "PLY")])
def test_bad_point_clouds(good, tmp_path, case, needle):
    root, scene = copy(good, tmp_path)
    ply = tmp_path / "cloud.ply"
    if case == "nan":
        pts = scene.points.copy()
        pts[5] = np.nan
        write_ply(ply, pts)
    elif case == "empty":
        write_ply(ply, np.zeros((0, 3)))
    elif case == "no_xyz":
        v = np.zeros(10, [("a", "f4"), ("b", "f4")])
        PlyData([PlyElement.describe(v, "vertex")]).write(str(ply))
    else:
        ply.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99999999999\n\x00\x01")
    one_error(cli(root, f"scene.options.cloud={ply}", cwd=tmp_path), needle)


def test_k_not_smaller_than_n(good, tmp_path):
    root, scene = copy(good, tmp_path)
    write_ply(tmp_path / "cloud.ply", scene.points[:20])
    one_error(cli(root, f"scene.options.cloud={tmp_path / 'cloud.ply'}", "graph.k=20", cwd=tmp_path),
              "graph.k=20", "20")


def test_duplicate_points_give_no_nan(good, tmp_path):
    root, scene = copy(good, tmp_path)
    write_ply(tmp_path / "cloud.ply", np.repeat(scene.points, 3, axis=0),  # every point three times
              np.repeat(scene.gt_labels, 3))
    p = cli(root, f"scene.options.cloud={tmp_path / 'cloud.ply'}", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    labels = np.load(tmp_path / "run" / "labels.npy")
    assert s["status"] == "ok"
    # zero distances give finite weights: the diffusion still improves on Bayesian fusion
    # (the duplicates fill neighbour slots, so it reaches less far than on the plain cloud)
    assert s["metrics"]["miou"] > s["baseline"]["bayesian"]["miou"] + 3
    assert s["metrics"]["coverage"] > s["baseline"]["bayesian"]["coverage"]
    np.testing.assert_array_equal(labels[0::3], labels[1::3])  # duplicates agree


def test_no_frame_sees_any_point(good, tmp_path):
    root, scene = copy(good, tmp_path)
    write_ply(tmp_path / "cloud.ply", scene.points + np.float32([100.0, 0, 0]))  # the cloud is elsewhere
    p = cli(root, f"scene.options.cloud={tmp_path / 'cloud.ply'}", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert any("no frame sees any point" in w for w in warnings_of(p)), p.stderr
    assert (np.load(tmp_path / "run" / "labels.npy") == -1).all()  # nothing labelled, not class 0
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert s["coverage_evidence"] == 0 and s["n_unlabeled"] == s["n_points"]
    assert any("no frame sees" in w for w in s["warnings"])


def test_memory_budget_fails_early(good, tmp_path):
    root, _ = copy(good, tmp_path)
    one_error(cli(root, "memory_budget_gb=0.0001", cwd=tmp_path), "GiB", "memory_budget_gb")
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert s["status"] == "failed" and "memory_budget_gb" in s["error"]


def test_verbose_shows_the_traceback(good, tmp_path):
    root, _ = copy(good, tmp_path)
    (root / "frame-000001.pose.txt").unlink()
    p = cli(root, "--verbose", cwd=tmp_path)
    assert p.returncode != 0 and "Traceback" in p.stderr


def npy_depth(root, bad=None):
    """The folder's depth as .npy float metres (images.read_depth), frame 1's replaced by ``bad`` bytes."""
    for f in sorted(root.glob("*.depth.png")):
        out = f.with_name(f.name.replace(".depth.png", ".depth.npy"))
        np.save(out, np.asarray(Image.open(f), np.float32) / np.float32(1000))
        f.unlink()
    if bad is not None:
        (root / "frame-000001.depth.npy").write_bytes(bad)


def test_npy_depth_in_metres_runs_as_the_png(good, tmp_path):
    root, _ = copy(good, tmp_path)
    npy_depth(root)
    p = cli(root, "scene.options.depth_suffix=depth.npy", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert s["status"] == "ok" and s["predictions_2d"]["miou"] == 100 and not warnings_of(p)
    assert s["coverage_evidence"] > 90


def _npy(arr, shape=None) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, arr)
    data = buf.getvalue()
    if shape is not None:  # the header's shape replaced (both padded to the same length)
        head = io.BytesIO()
        np.lib.format.write_array_header_1_0(head, {**np.lib.format.header_data_from_array_1_0(arr), "shape": shape})
        data = head.getvalue() + data[len(head.getvalue()):]
    return data


@pytest.mark.parametrize("case,needle", [
    ("colour", "depth array of dtype float32 shape (48, 64, 3), expected (H, W) metres"),
    ("lies", "header says shape (480000, 640000) of float32"),
    ("text", "not a .npy file"),
])
def test_bad_npy_depth(good, tmp_path, case, needle):
    root, _ = copy(good, tmp_path)
    bad = {"colour": lambda: _npy(np.ones((H, W, 3), np.float32)),
           "lies": lambda: _npy(np.ones((H, W), np.float32), (480_000, 640_000)),
           "text": lambda: b"0.5 0.5\n"}[case]()
    npy_depth(root, bad)
    one_error(cli(root, "scene.options.depth_suffix=depth.npy", cwd=tmp_path), "frame-000001.depth.npy", needle)


def _feature_maps(tmp_path):
    """A (6, 8, 16) float16 feature map per frame of :func:`good`'s folder, in ``tmp_path / "maps"``."""
    maps = tmp_path / "maps"
    maps.mkdir()
    for i in range(3):
        np.save(maps / f"frame-{i:06d}.npy", np.random.default_rng(i).random((6, 8, 16)).astype(np.float16))
    return maps


@pytest.mark.parametrize("case,needle", [
    ("float64", "features of shape (6, 8, 16) dtype float64, expected float16/float32 (h, w, D) or (D, h, w)"),
    ("lies", "header says shape (6000, 8000, 16) of float16"),
])
def test_bad_feature_maps(good, tmp_path, case, needle):
    """predictions.embeddings=files: a network's (h, w, D) maps read by the one array reader."""
    root, _ = copy(good, tmp_path)
    maps = _feature_maps(tmp_path)
    (maps / "frame-000001.npy").write_bytes(
        _npy(np.ones((6, 8, 16), np.float64)) if case == "float64" else _npy(np.ones((6, 8, 16), np.float16), (6000, 8000, 16)))
    p = cli(root, "predictions.embeddings=files", f"predictions.folder={maps}", cwd=tmp_path, predictions="features")
    one_error(p, "frame-000001.npy", needle)


@pytest.mark.parametrize("case,needle", [
    ("text", "unreadable .npz (BadZipFile: File is not a zip file), expected a .npz query file"),
    ("lies", "q.npz [embeddings]: header says shape (50000, 16) of float32"),
    ("npy", "a single array, expected a .npz query file"),
])
def test_bad_query_file(good, tmp_path, case, needle):
    """predictions.queries: the query set read by the one array reader (data/arrays.py)."""
    root, _ = copy(good, tmp_path)
    maps = _feature_maps(tmp_path)
    q = tmp_path / "q.npz"
    if case == "text":
        q.write_text("names,embeddings\nwall,0.1\n")
    elif case == "npy":
        q.write_bytes(_npy(np.ones((3, 16), np.float32)))
    else:
        import zipfile

        with zipfile.ZipFile(q, "w") as z:
            z.writestr("names.npy", _npy(np.array(["wall", "floor"])))
            z.writestr("embeddings.npy", _npy(np.ones((2, 16), np.float32), (50_000, 16)))
    p = cli(root, "predictions.embeddings=files", f"predictions.folder={maps}", f"predictions.queries={q}",
            cwd=tmp_path, predictions="features")
    one_error(p, "q.npz", needle)
