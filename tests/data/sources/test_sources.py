"""Dataset loaders: ScanNet export layout and posed RGB-D folders (diffuser_lab.data.sources)."""
import time
import warnings

import numpy as np
import pytest
from datasets import (  # noqa: F401
    BAD_POSE,
    CH,
    CW,
    EYES,
    NYU,
    TARGET,
    H,
    W,
    _c2w,
    _save_u16,
    _vertex_nyu,
    _write_mesh,
    make_world,
    write_rgbd,
    write_scannet,
)
from conftest import SHARED as _SHARED
from plyfile import PlyData, PlyElement

from diffuser_lab.data.geometry import backproject, project
from diffuser_lab.data.scene import IGNORE, SCANNET20
from diffuser_lab.data.frames import LazyFrames
from diffuser_lab.data.images import read_depth_png
from diffuser_lab.data.meshes import read_labelled_mesh
from diffuser_lab.data.sources.rgbd_folder import load_rgbd_folder
from diffuser_lab.data.sources.scannet import load_scannet
from diffuser_lab.method.evidence import visible_projection

SHARED = _SHARED / "data"
SCANNET_REAL = SHARED / "scannet" / "scene0470_00"
SEVEN_SCENES = SHARED / "7scenes_sample"


@pytest.fixture(scope="module")
def world():
    """Demo room mesh, its renderer, cameras and the rendered depth/label images."""
    return make_world()


@pytest.fixture
def scannet_dir(tmp_path, world):
    return write_scannet(tmp_path, world)


def _check_round_trip(scene, world, ids):
    """Loaded frames reproduce the rendered geometry: pose, K, depth to 1 mm, pixel to 1 px,
    and points of one view land on the surfaces seen by the next (pose direction is right)."""
    assert isinstance(scene.frames, LazyFrames)
    assert [f.name for f in scene.frames] == [str(i) for i in ids] or \
        [f.name for f in scene.frames] == [f"frame-{i:06d}" for i in ids]
    for k, i in enumerate(ids):  # loop over frames
        f = scene.frames[k]
        depth_true = world["views"][i][0]
        assert f.depth.shape == (H, W) and f.depth.dtype == np.float32 and f.labels is None
        np.testing.assert_allclose(f.K, world["K"], atol=1e-9)
        np.testing.assert_allclose(f.T_cw, world["poses"][i], atol=1e-9)
        assert np.abs(f.depth - depth_true).max() <= 0.0005 + 1e-6  # mm quantisation
        pts, pix = backproject(f.depth, f.K, f.T_cw)
        u, v, z = project(pts, f.K, f.T_cw)
        assert np.abs(u - pix[:, 1]).max() < 1.0 and np.abs(v - pix[:, 0]).max() < 1.0
        assert np.abs(z - depth_true[pix[:, 0], pix[:, 1]]).max() < 0.001
    # Cross-view: frame 0's points pass the 5 cm depth check in frame 1 (an inverted pose gives 0 %;
    # at 80x60 px pixel rounding on oblique floor costs ~6 %).
    a, b = scene.frames[0], scene.frames[1]
    pts, _ = backproject(a.depth, a.K, a.T_cw)
    u, v, _ = project(pts, b.K, b.T_cw)
    inside = np.count_nonzero((np.rint(u) >= 0) & (np.rint(u) < W) & (np.rint(v) >= 0) & (np.rint(v) < H))
    idx, _, _ = visible_projection(pts, b, 0.05)
    assert inside > 0.5 * len(pts) and len(idx) > 0.85 * inside


def test_scannet_layout_round_trip(scannet_dir, world):
    scene = load_scannet(scannet_dir, frame_step=1)
    assert scene.name == "scene0999_00" and scene.taxonomy is SCANNET20
    assert scene.frames.info["n_invalid_pose"] == 1
    _check_round_trip(scene, world, [0, 1, 3])
    # Mesh: points, colours, vertex normals, mapped per-vertex ground truth.
    np.testing.assert_array_equal(scene.points, world["verts"])
    assert (scene.colors == [100, 150, 200]).all()
    np.testing.assert_allclose(np.linalg.norm(scene.normals, axis=1), 1.0, atol=1e-5)
    vlab = np.zeros(len(world["verts"]), np.int16)
    vlab[world["tris"].ravel()] = np.repeat(world["tri_lab"], 3)
    np.testing.assert_array_equal(scene.gt_labels, vlab)
    # label-filt (NYU40 at colour resolution) -> SCANNET20 at depth resolution.
    for k, i in enumerate([0, 1, 3]):
        f = scene.frames[k]
        lab = world["views"][i][1]
        assert f.gt_labels.shape == (H, W) and f.gt_labels.dtype == np.int16
        assert np.mean(f.gt_labels == lab) > 0.95  # nearest resize differs only at edges
        assert f.rgb.shape == (H, W, 3) and f.rgb.dtype == np.uint8
    # Unannotated (NYU40 0) pixels -> IGNORE exactly where nothing was hit.
    assert ((scene.frames[0].gt_labels == IGNORE) == (world["views"][0][0] == 0)).mean() > 0.95


def test_scannet_frame_step_and_missing_folders(scannet_dir):
    s2 = load_scannet(scannet_dir, frame_step=2)  # frames 0, 2 -> 2 has a -inf pose
    assert [f.name for f in s2.frames] == ["0"] and s2.frames.info["n_invalid_pose"] == 1
    s3 = load_scannet(scannet_dir, frame_step=3)
    assert s3.frames.names == ["0", "3"] and s3.frames.info["n_invalid_pose"] == 0
    assert load_scannet(scannet_dir, frame_step=1, max_frames=2).frames.names == ["0", "1"]
    for p in (scannet_dir / "depth").iterdir():
        p.unlink()
    (scannet_dir / "depth").rmdir()
    with pytest.raises(FileNotFoundError, match=r"depth/\{frame\}\.png.*scene\.options\.depth"):
        load_scannet(scannet_dir)
    assert len(load_scannet(scannet_dir, with_frames=False).frames) == 0


def test_read_labelled_mesh_errors(tmp_path):
    v = np.zeros(3, [("x", "f4"), ("y", "f4"), ("z", "f4")])
    PlyData([PlyElement.describe(v, "vertex")]).write(str(tmp_path / "pts.ply"))
    with pytest.raises(ValueError, match="no faces"):
        read_labelled_mesh(tmp_path / "pts.ply")
    with pytest.raises(FileNotFoundError, match="missing.ply"):
        read_labelled_mesh(tmp_path / "missing.ply")


@pytest.mark.skipif(not SCANNET_REAL.is_dir(), reason=f"real ScanNet sample absent ({SCANNET_REAL})")
def test_real_scannet_mesh():
    scene = load_scannet(SCANNET_REAL, with_frames=False)
    assert scene.n_points == 67_465 and scene.points.dtype == np.float32
    present = {scene.taxonomy.names[c] for c in np.unique(scene.gt_labels) if c != IGNORE}
    assert {"wall", "floor", "chair", "table", "door", "window"} <= present
    np.testing.assert_allclose(np.linalg.norm(scene.normals, axis=1), 1.0, atol=1e-4)
    floor = scene.gt_labels == SCANNET20.names.index("floor")
    assert np.median(scene.normals[floor, 2]) > 0.9  # z up: winding-oriented normals face up


@pytest.fixture
def rgbd_dir(tmp_path, world):
    return write_rgbd(tmp_path, world)


def test_rgbd_folder_round_trip_and_fused_cloud(rgbd_dir, world):
    import open3d as o3d

    scene = load_rgbd_folder(rgbd_dir, label_suffix="label.png", mapping="nyu40_to_scannet20",
                             voxel_size=0.05, cloud_stride=2)
    assert scene.name == "seq" and len(scene.frames) == 4 and scene.normals is None
    _check_round_trip(scene, world, [0, 1, 2, 3])
    assert scene.frames[1].gt_labels is None  # no label file for that frame
    assert np.mean(scene.frames[0].gt_labels == world["views"][0][1]) > 0.95
    assert scene.frames[0].rgb.shape == (H, W, 3)
    # Fused cloud: every voxel centroid lies on the mesh (up to corner rounding).
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(world["verts"]), o3d.core.Tensor(world["tris"].astype(np.uint32)))
    dist = rc.compute_distance(o3d.core.Tensor(scene.points)).numpy()
    assert 200 < scene.n_points < 4 * H * W / 4 and np.quantile(dist, 0.95) < 0.01 and dist.max() < 0.05
    assert scene.colors.shape == (scene.n_points, 3) and scene.colors.dtype == np.uint8
    # Frames are lazy: a changed file shows on the next access.
    _save_u16(rgbd_dir / "frame-000000.depth.png", np.full((H, W), 1234))
    assert np.allclose(scene.frames[0].depth, 1.234)
    # frame_step / max_frames.
    s = load_rgbd_folder(rgbd_dir, frame_step=2, max_frames=1, voxel_size=0.1)
    assert s.frames.names == ["frame-000000"]


def test_rgbd_folder_cloud_from_ply(rgbd_dir, world):
    _write_mesh(rgbd_dir / "cloud.ply", world["verts"], world["tris"], _vertex_nyu(world))
    s = load_rgbd_folder(rgbd_dir, cloud=rgbd_dir / "cloud.ply", mapping="nyu40_to_scannet20")
    np.testing.assert_array_equal(s.points, world["verts"])
    assert s.gt_labels.dtype == np.int16 and (s.gt_labels >= 0).all() and s.normals is None


def test_rgbd_folder_validation(rgbd_dir):
    (rgbd_dir / "frame-000003.pose.txt").unlink()
    with pytest.raises(ValueError, match=r"4 depth\.png, 3 pose\.txt and 4 color\.jpg files"):
        load_rgbd_folder(rgbd_dir)
    T = np.eye(4)
    T[:3, :3] *= 1.1  # scaled, not rigid
    np.savetxt(rgbd_dir / "frame-000003.pose.txt", T)
    with pytest.raises(ValueError, match=r"frame-000003\.pose\.txt.*not a rigid"):
        load_rgbd_folder(rgbd_dir)
    np.savetxt(rgbd_dir / "frame-000003.pose.txt", np.eye(4))
    with pytest.warns(UserWarning, match="depth_scale=1.0"):  # metres read as millimetres
        load_rgbd_folder(rgbd_dir, depth_scale=1.0, voxel_size=50.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_rgbd_folder(rgbd_dir, voxel_size=0.2)
    np.savetxt(rgbd_dir / "camera-intrinsics.txt", np.diag([-500.0, 500.0, 1.0]))
    with pytest.raises(ValueError, match="camera-intrinsics.txt.*positive focal"):
        load_rgbd_folder(rgbd_dir)


def test_depth_bit_shift(tmp_path):
    d = np.array([[0, 1, 1500, 4000, 9000, 20000]], np.uint32)  # >= 8192: top bits wrap around
    stored = ((d << 3) | (d >> 13)) & 0xFFFF  # SUN3D: rotate left by 3
    _save_u16(tmp_path / "d.png", stored)
    np.testing.assert_allclose(read_depth_png(tmp_path / "d.png", 1000.0, bit_shift=3), d / 1000.0)
    raw = read_depth_png(tmp_path / "d.png", 1000.0)
    assert raw[0, 2] == pytest.approx(12.0)  # unshifted value is 8x too far: what the warning catches


@pytest.mark.skipif(not SEVEN_SCENES.is_dir(), reason=f"real 7-Scenes sample absent ({SEVEN_SCENES})")
def test_real_7scenes_neighbouring_frames_agree_and_fused_cloud():
    t0 = time.perf_counter()
    scene = load_rgbd_folder(SEVEN_SCENES)  # cloud=None: fuse 100 frames, stride 4, 2 cm voxels
    seconds = time.perf_counter() - t0
    assert len(scene.frames) == 100
    a, b = scene.frames[0], scene.frames[1]
    assert a.depth.shape == (480, 640) and 0.5 < np.median(a.depth[a.depth > 0]) < 5.0
    pts, _ = backproject(a.depth, a.K, a.T_cw, stride=4)
    u, v, _ = project(pts, b.K, b.T_cw)
    cols, rows = np.rint(u), np.rint(v)
    inside = np.count_nonzero((cols >= 0) & (cols < 640) & (rows >= 0) & (rows < 480))
    idx, _, _ = visible_projection(pts, b, 0.05)
    share = len(idx) / inside
    print(f"7-Scenes frames 0->1: {share:.1%} of {inside} projecting points pass the 5 cm check; "
          f"fused cloud {scene.n_points} points in {seconds:.2f} s")
    assert inside > 0.5 * len(pts) and share > 0.7
    # A room-sized scan at 2 cm: 10^4..10^6 points, a few metres across.
    assert 20_000 < scene.n_points < 1_000_000
    extent = scene.points.max(0) - scene.points.min(0)
    assert (extent < 15).all() and extent.max() > 1.0
    assert seconds < 30.0
