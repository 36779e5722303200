"""scene=colmap (diffuser_lab.data.sources.colmap): the 7-Scenes frames written as COLMAP writes them
(a sparse model through pycolmap, binary and text; MVS depth maps in COLMAP's own format; images
named in the model) must label the same points as the posed RGB-D folder (tests/captures.py)."""
from __future__ import annotations

import shutil
import struct

import numpy as np
import pytest
from captures import agreement, labels_of, needs_7scenes, seven_frames, write_rgbd_reference
from conftest import run_cli

from diffuser_lab.data.distortion import colmap_lens, focal_scale, undistort_image, undistort_map
from diffuser_lab.data.geometry import scaled_intrinsics
from diffuser_lab.data.sources.colmap import read_depth_map

pycolmap = pytest.importorskip("pycolmap")

STRIDE = ("scene.options.cloud_stride=8",)
N_FRAMES, STEP = 5, 20


# ---------------------------------------------------------------------------------------- the writer

def write_depth_map(path, depth: np.ndarray) -> None:
    """(H, W) float32 -> COLMAP's depth map file: ``width&height&1&`` + float32 row-major (read_write_dense.py)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = depth.shape
    path.write_bytes(f"{w}&{h}&1&".encode() + np.ascontiguousarray(depth, "<f4").tobytes())


def write_model(folder, frames, *, model="PINHOLE", extra=(), text=False, legacy=False, points=None, colors=None,
                suffix=".jpg") -> None:
    """The frames as a COLMAP sparse model in ``folder``: one camera (COLMAP's principal point is
    OpenCV's + 0.5, the top-left pixel's centre being (0.5, 0.5)), world-to-camera poses, points3D."""
    K = frames[0]["K"]
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, model, float(K[0, 0]), 640, 480)
    if model == "SIMPLE_PINHOLE":
        cam.params = [K[0, 0], K[0, 2] + 0.5, K[1, 2] + 0.5]
    else:
        cam.params = [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5, *extra]
    rec.add_camera_with_trivial_rig(cam)
    for i, f in enumerate(frames):  # loop over frames
        R, t = f["c2w"][:3, :3], f["c2w"][:3, 3]
        im = pycolmap.Image(name=f["name"] + suffix, camera_id=1, image_id=10 + 7 * i)  # ids unordered
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(np.c_[R.T, -R.T @ t]))
    if points is not None:
        for p, c in zip(points, colors):  # loop over a test cloud's points (pycolmap's API adds one at a time)
            rec.add_point3D(np.asarray(p, np.float64), pycolmap.Track(), np.asarray(c, np.uint8))
    folder.mkdir(parents=True, exist_ok=True)
    (rec.write_text if text else rec.write_binary)(str(folder))
    if legacy:  # COLMAP < 3.12 wrote no rigs / frames files
        for name in ("rigs", "frames"):
            (folder / f"{name}.{'txt' if text else 'bin'}").unlink()


def write_workspace(root, frames, *, depth=True, sparse="sparse", **model) -> None:
    """A dense workspace (colmap image_undistorter + patch_match_stereo): images/, ``sparse``, stereo/."""
    (root / "images").mkdir(parents=True, exist_ok=True)
    for f in frames:  # loop over frames
        shutil.copy(f["color_path"], root / "images" / f"{f['name']}.jpg")
        if depth:
            write_depth_map(root / "stereo" / "depth_maps" / f"{f['name']}.jpg.geometric.bin", f["depth"])
    write_model(root / sparse, frames, **model)


def as_stored(frames: list[dict]) -> list[dict]:
    """The frames with their poses as a COLMAP model holds them: 7-Scenes' rotations are orthonormal only
    to ~3e-4, a model stores a unit quaternion; both runs use the rotation the quaternion gives."""
    out = []
    for f in frames:  # loop over frames
        R, t = f["c2w"][:3, :3], f["c2w"][:3, 3]
        T_cw = np.eye(4)
        T_cw[:3] = pycolmap.Rigid3d(np.c_[R.T, -R.T @ t]).matrix()
        out.append(dict(f, c2w=np.linalg.inv(T_cw)))
    return out


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The posed RGB-D folder's run on the frames, poses as stored (:func:`as_stored`)."""
    frames = as_stored(seven_frames(N_FRAMES, STEP))
    root = write_rgbd_reference(tmp_path_factory.mktemp("ref"), frames)
    for f in frames:  # loop over frames: the pose files with the stored rotations
        np.savetxt(root / f"{f['name']}.pose.txt", f["c2w"], fmt="%.17g")
    pts, lab, res = labels_of("scene=rgbd_folder", f"scene.options.root={root}", *STRIDE)
    return frames, pts, lab, res


def _colmap(root, *extra):
    return labels_of("scene=colmap", f"scene.options.root={root}", "scene.options.cloud_stride=8", *extra)


# ---------------------------------------------------------------------------------------- against the reference

@needs_7scenes
def test_binary_dense_workspace_matches_reference(tmp_path, reference):
    frames, ref_pts, ref_lab, ref = reference
    some = ref_pts[::50]  # a model has points3D; cloud_from=depth compares the depth maps' cloud
    write_workspace(tmp_path, frames, points=some, colors=np.full((len(some), 3), 200))
    pts, lab, res = _colmap(tmp_path, "scene.options.cloud_from=depth")
    a = agreement(pts, lab, ref_pts, ref_lab)
    print(f"binary model + geometric depth maps: agreement {a:.5f} ({len(pts)} points, reference {len(ref_pts)})")
    assert a >= 0.999
    f0, r0 = res.scene.frames[0], ref.scene.frames[0]
    np.testing.assert_allclose(f0.K, r0.K, atol=1e-9)  # cx_colmap - 0.5 = the reference's cx
    np.testing.assert_allclose(f0.T_cw, r0.T_cw, atol=1e-9)
    assert res.scene.frames.info["depth_maps"] == f"geometric ({N_FRAMES})"


@needs_7scenes
def test_text_model_folder_as_root_matches_reference(tmp_path, reference):
    """A legacy text model (no rigs/frames files) given as root, images and stereo beside it."""
    frames, ref_pts, ref_lab, _ = reference
    write_workspace(tmp_path, frames, text=True, legacy=True, sparse="model")
    pts, lab, res = _colmap(tmp_path / "model", "scene.options.images=../images", "scene.options.stereo=../stereo")
    a = agreement(pts, lab, ref_pts, ref_lab)
    print(f"text model: agreement {a:.5f}")
    assert a >= 0.999
    assert "(txt," in res.scene.frames.info["colmap_model"]
    assert "back-projected" in res.scene.frames.info["cloud"]  # no points3D, no fused.ply: the depth maps


@needs_7scenes
def test_distorted_camera_goes_through_the_undistortion(tmp_path, reference):
    """OPENCV with zero distortion: resampled by the undistortion map (identity here), no half-pixel shift."""
    frames, ref_pts, ref_lab, _ = reference
    write_workspace(tmp_path, frames, model="OPENCV", extra=(0.0, 0.0, 0.0, 0.0))
    pts, lab, res = _colmap(tmp_path)
    a = agreement(pts, lab, ref_pts, ref_lab)
    print(f"OPENCV (zero distortion), undistorted: agreement {a:.5f}")
    assert a >= 0.999
    assert res.scene.frames.info["undistorted_cameras"] == ["OPENCV (camera 1, focal x1)"]


@needs_7scenes
def test_points3D_without_depth_maps_renders_depth_from_the_cloud(tmp_path, reference):
    """A mapper project (images/, sparse/0) without MVS: the reference cloud as points3D, depth rendered."""
    frames, ref_pts, ref_lab, ref = reference
    cols = ref.scene.colors if ref.scene.colors is not None else np.full((len(ref_pts), 3), 128)
    write_workspace(tmp_path, frames, depth=False, sparse="sparse/0", points=ref_pts, colors=cols)
    pts, lab, res = _colmap(tmp_path)
    a = agreement(pts, lab, ref_pts, ref_lab)
    info = res.scene.frames.info
    print(f"points3D cloud, depth rendered from it: agreement {a:.5f} ({info['visibility']})")
    assert len(pts) == len(ref_pts) and a >= 0.9
    assert info["visibility"].startswith("depth rendered from the cloud") and "points3D" in info["cloud"]


# ---------------------------------------------------------------------------------------- readers

def _tiny(tmp_path, model="PINHOLE", extra=(), text=False, n=2, images=True):
    """A synthetic 2-frame model (no 7-Scenes needed): grey images, no depth, one point."""
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    frames = [dict(name=f"im{i}", K=K, c2w=_c2w(i)) for i in range(n)]
    root = tmp_path / "tiny"
    write_model(root / "sparse", frames, model=model, extra=extra, text=text, points=GRID, colors=np.full((25, 3), 9),
                suffix=".png")
    if images:
        from PIL import Image
        (root / "images").mkdir()
        for f in frames:  # loop over frames
            Image.fromarray(np.full((480, 640, 3), 90, np.uint8)).save(root / "images" / f"{f['name']}.png")
    return root


GRID = np.stack(np.meshgrid(np.linspace(-1, 1, 5), np.linspace(-1, 1, 5), [2.0]), -1).reshape(-1, 3)


def _c2w(i: int) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = 0.1 * i
    return T


def _load(root, **keys):
    from diffuser_lab.data.scene import SCANNET20
    from diffuser_lab.data.sources.colmap import ColmapOptions, load

    class Cfg:
        options = ColmapOptions(root=str(root), **keys)

    return load(Cfg, SCANNET20, None)


def test_depth_map_reader_round_trip(tmp_path):
    d = np.arange(12, dtype=np.float32).reshape(3, 4) - 1  # -1, 0 = none
    write_depth_map(tmp_path / "a.bin", d)
    out = read_depth_map(tmp_path / "a.bin")
    np.testing.assert_array_equal(out, np.where(d > 0, d, 0))
    (tmp_path / "b.bin").write_bytes(b"4&3&1&" + b"\0" * 40)
    with pytest.raises(ValueError, match=r"b\.bin: header 4&3&1& with 40 data bytes"):
        read_depth_map(tmp_path / "b.bin")
    (tmp_path / "c.bin").write_bytes(b"PNG....")
    with pytest.raises(ValueError, match=r"c\.bin: no 'width&height&channels&' header"):
        read_depth_map(tmp_path / "c.bin")


def _pinhole(model, params, shape=(240, 320)):
    """(K of the distorted camera, LensModel, K of the pinhole one with colmap's no-blank focal scale)."""
    K, lens = colmap_lens(model, params)
    s = focal_scale(K, shape, lens, "test")
    Ko = K.copy()
    Ko[:2, :2] *= s
    return K, lens, Ko, s


@pytest.mark.parametrize("model,params", [
    ("SIMPLE_RADIAL", [300.0, 160.0, 120.0, -0.1]), ("RADIAL", [300.0, 160.0, 120.0, -0.1, 0.02]),
    ("OPENCV", [300.0, 310.0, 161.0, 119.5, -0.12, 0.03, 0.001, -0.002]),
    ("OPENCV", [300.0, 300.0, 160.0, 120.0, 0.2, 0.0, 0.0, 0.0]),
    ("FULL_OPENCV", [300.0, 310.0, 161.0, 119.5, -0.12, 0.03, 0.001, -0.002, 0.01, 0.02, -0.01, 0.005])])
def test_colmap_models_map_onto_the_one_undistortion(model, params):
    """data/distortion.py's map of a COLMAP camera equals pycolmap's own projection (img_from_cam, the
    former colmap Undistorter's) to 1e-3 px, at the camera's size and at half of it (centres aligned)."""
    cam = pycolmap.Camera.create_from_model_name(1, model, 300.0, 320, 240)
    cam.params = params
    K, lens, Ko, _ = _pinhole(model, params)
    for h, w in ((240, 320), (120, 160)):
        coords, valid = undistort_map(scaled_intrinsics(K, (240, 320), (h, w)), (h, w), lens,
                                      scaled_intrinsics(Ko, (240, 320), (h, w)))
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        U, V = (u.ravel() + 0.5) * 320 / w - 0.5, (v.ravel() + 0.5) * 240 / h - 0.5  # at the camera's size
        rays = np.stack([(U - Ko[0, 2]) / Ko[0, 0], (V - Ko[1, 2]) / Ko[1, 1], np.ones_like(U)], 1)
        uv = np.asarray(cam.img_from_cam(rays), np.float64) - 0.5
        ref = np.stack([((uv[:, 1] + 0.5) * h / 240 - 0.5).reshape(h, w), ((uv[:, 0] + 0.5) * w / 320 - 0.5).reshape(h, w)])
        assert np.abs(coords - ref).max() < 1e-3
        assert valid.all()  # the focal scale leaves no blank pixel


def test_undistortion_inverts_the_camera_model():
    """An image distorted through pycolmap's own OPENCV projection comes back to the pinhole one."""
    cam = pycolmap.Camera.create_from_model_name(1, "OPENCV", 300.0, 320, 240)
    cam.params = [300.0, 310.0, 161.0, 119.5, -0.12, 0.03, 0.001, -0.002]
    K, lens, Ko, s = _pinhole("OPENCV", cam.params)
    assert s == 1.0  # barrel distortion: the pinhole image of the same focal length has no blank pixel
    v, w = np.mgrid[0:240, 0:320].astype(np.float64)
    truth = np.sin(w / 9.0) + np.cos(v / 7.0)  # a smooth pinhole image, pixel centres at integers

    # the distorted image: each distorted pixel (centre + 0.5 in COLMAP's frame) looks up the pinhole image
    xy = cam.cam_from_img(np.stack([w.ravel() + 0.5, v.ravel() + 0.5], 1))
    pu, pv = Ko[0, 0] * xy[:, 0] + Ko[0, 2], Ko[1, 1] * xy[:, 1] + Ko[1, 2]
    distorted = (np.sin(pu / 9.0) + np.cos(pv / 7.0)).reshape(240, 320).astype(np.float32)
    back = undistort_image(distorted, K, lens, order=1, K_out=Ko)
    inner = (slice(20, -20), slice(20, -20))
    assert np.abs(back[inner] - truth[inner]).max() < 0.02
    half = undistort_image(distorted[::2, ::2].copy(), scaled_intrinsics(K, (240, 320), (120, 160)), lens, order=1,
                           K_out=scaled_intrinsics(Ko, (240, 320), (120, 160)))  # another size: centres aligned
    assert np.abs(half[10:-10, 10:-10] - truth[::2, ::2][10:-10, 10:-10]).max() < 0.05
    # pincushion distortion: the focal length grows until no pixel is blank
    assert _pinhole("OPENCV", [300.0, 300.0, 160.0, 120.0, 0.2, 0.0, 0.0, 0.0])[3] > 1.0


def test_labels_template_and_sparse_0(tmp_path):
    from PIL import Image

    root = _tiny(tmp_path)
    (root / "sparse").rename(root / "s0")
    (root / "sparse").mkdir()
    (root / "s0").rename(root / "sparse" / "0")
    (root / "labels").mkdir()
    lab = np.zeros((240, 320), np.uint8)
    lab[:, 160:] = 3
    Image.fromarray(lab).save(root / "labels" / "im1.png")  # im0 has none
    scene = _load(root, labels="labels/{stem}.png", gt_from_frames=False)
    assert scene.frames.names == ["im0", "im1"]
    assert scene.frames[0].gt_labels is None
    gt = scene.frames[1].gt_labels
    assert gt.shape == (480, 640) and set(np.unique(gt)) == {0, 3}
    assert scene.points.shape == (25, 3)  # the model's points3D
    np.testing.assert_allclose(scene.frames[1].K, [[500, 0, 319.5], [0, 500, 239.5], [0, 0, 1]])


# ---------------------------------------------------------------------------------------- bad input

def test_unknown_and_refused_camera_models(tmp_path):
    root = _tiny(tmp_path, text=True)
    cams = root / "sparse" / "cameras.txt"
    cams.write_text(cams.read_text().replace(" PINHOLE ", " FOOBAR "))
    with pytest.raises(ValueError, match=r"cameras\.txt: line \d+: camera 1 has model FOOBAR, not a COLMAP camera"):
        _load(root)

    root = _tiny(tmp_path / "b")  # binary: a model id COLMAP does not have
    cams = root / "sparse" / "cameras.bin"
    data = bytearray(cams.read_bytes())
    data[12:16] = struct.pack("<i", 99)
    cams.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"cameras\.bin: camera 1 has model id 99, not a COLMAP camera model"):
        _load(root)

    root = _tiny(tmp_path / "f", model="OPENCV_FISHEYE", extra=(0.1, 0, 0, 0))
    with pytest.raises(ValueError, match=r"cameras\.bin: camera 1 has model OPENCV_FISHEYE, expected one of"):
        _load(root)

    root = _tiny(tmp_path / "u", model="OPENCV", extra=(0.1, 0, 0, 0))
    with pytest.raises(ValueError, match=r"cameras\.bin: camera 1 has model OPENCV \(distorted\) and "
                                         r"scene\.options\.undistort=false"):
        _load(root, undistort=False)
    assert _load(root).frames.info["undistorted_cameras"][0].startswith("OPENCV (camera 1, focal x")


@pytest.mark.parametrize("cut, field", [(4, "number of images"), (30, "image_id, qvec, tvec"),
                                        (8 + 64 + 3, "name"), (-30, "points2D|num_points2D|image_id")])
def test_truncated_images_bin(tmp_path, cut, field):
    root = _tiny(tmp_path, n=2)
    path = root / "sparse" / "images.bin"
    data = path.read_bytes()
    path.write_bytes(data[:cut])
    with pytest.raises(ValueError, match=rf"images\.bin: truncated at byte {len(data[:cut])}.*field ({field})"):
        _load(root)


def test_every_truncation_of_the_binary_model_is_one_line(tmp_path):
    """Each prefix of cameras.bin / images.bin (and points3D.bin past its header) reads or raises one
    line naming the file: never pycolmap's std::bad_alloc or a crash."""
    from diffuser_lab.data.sources.colmap import read_model

    folder = _tiny(tmp_path) / "sparse"
    for name in ("cameras.bin", "images.bin", "points3D.bin"):  # loop over the files
        data = (folder / name).read_bytes()
        cuts = range(len(data)) if name != "points3D.bin" else [*range(0, len(data), 13), len(data) - 1]
        for cut in cuts:  # loop over truncations: every byte (points3D.bin: every 13th, its records are alike)
            (folder / name).write_bytes(data[:cut])
            with pytest.raises(ValueError) as e:
                read_model(folder, "bin")
            msg = str(e.value)
            assert name in msg and "\n" not in msg, msg
        (folder / name).write_bytes(data)
    read_model(folder, "bin")  # whole again: reads


def test_missing_images_folder_image_and_model(tmp_path):
    root = _tiny(tmp_path, images=False)
    with pytest.raises(FileNotFoundError, match=r"image folder .*tiny/images does not exist \(scene\.options\.images"):
        _load(root)
    (root / "images").mkdir()
    with pytest.raises(FileNotFoundError, match=r"image .*images/im0\.png of the model does not exist \(2 of 2"):
        _load(root)
    with pytest.raises(FileNotFoundError, match=r"no COLMAP sparse model .* \(scene\.options\.root / scene\.options\.sparse\)"):
        _load(root, sparse="nowhere")
    (root / "sparse" / "points3D.bin").unlink()
    with pytest.raises(FileNotFoundError, match=r"COLMAP model file .*sparse/points3D\.bin does not exist"):
        _load(root)


def test_cli_prints_one_error_line(tmp_path):
    root = _tiny(tmp_path)
    path = root / "sparse" / "images.bin"
    path.write_bytes(path.read_bytes()[:40])
    r = run_cli("scene=colmap", f"scene.options.root={root}", "record=off")
    assert r.returncode != 0
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("diffuser-lab: error:")]
    assert len(errors) == 1, r.stderr[-2000:]
    assert "images.bin: truncated at byte 40 in image record 1 of 2, field image_id, qvec, tvec" in errors[0]
    assert "Traceback" not in r.stderr


def write_readme_fixture(root, frames, labels):
    """README's COLMAP_DIR: a dense workspace of ``frames`` (binary model, geometric depth maps) with
    ground-truth label images ``labels/<stem>.png`` (``labels``: frame name -> (H, W) ids)."""
    from PIL import Image

    write_workspace(root, as_stored(frames))
    (root / "labels").mkdir(exist_ok=True)
    for f in frames:  # loop over frames
        Image.fromarray(np.asarray(labels[f["name"]], np.uint8)).save(root / "labels" / f"{f['name']}.png")
    return root


def test_the_cameras_size_against_the_images(tmp_path):
    """Issue 52 item 4: a COLMAP camera's WIDTH HEIGHT (640 x 480) describe its images: half-size images
    take K scaled (and said), images of another aspect are one line naming cameras.bin and the image."""
    from PIL import Image

    root = _tiny(tmp_path, images=False)
    (root / "images").mkdir()
    for size in ((240, 320), (300, 300)):  # loop over the two cases
        for i in range(2):  # loop over frames
            Image.fromarray(np.full((*size, 3), 90, np.uint8)).save(root / "images" / f"im{i}.png")
        if size == (240, 320):
            s = _load(root)
            assert s.frames[0].rgb.shape == (240, 320, 3) and "scaled by 1/2" in s.frames.info["intrinsics"]
            np.testing.assert_allclose(s.frames[0].K[0, 0], 250.0)
        else:
            with pytest.raises(ValueError, match=r"cameras\.bin \(camera 1\): K is stated for 640x480 \(W x H\) "
                                                 r"images, .*images/im0\.png is 300x300"):
                _load(root)
