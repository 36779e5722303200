"""nerfstudio's transforms.json (issue 27, item 1): the 7-Scenes frames written as nerfstudio lays
them out (OpenGL camera-to-world, cx/cy with nerfstudio's half-pixel, depth PNGs in mm) label the
same points as the posed RGB-D folder; distortion, applied_transform, ply_file_path, downscaled
images, masks, label templates and malformed files."""
import json
import shutil

import numpy as np
import pytest
from captures import agreement, labels_of, needs_7scenes, reference_labels, seven_frames
from conftest import compose, run_cli
from PIL import Image
from plyfile import PlyData, PlyElement

from diffuser_lab.data.distortion import FISHEYE, PERSPECTIVE, LensModel, distort_points, undistort_image, \
    undistort_points
from diffuser_lab.data.capture import to_taxonomy
from diffuser_lab.data.geometry import scaled_intrinsics
from diffuser_lab.data.mapping import load_mapping
from diffuser_lab.data.scene import IGNORE, SCANNET20
from diffuser_lab.data.sources.nerfstudio import OPENGL_TO_OPENCV
from diffuser_lab.data.images import read_rgb
from diffuser_lab.data.poses import rigid_inverse
from diffuser_lab.runs.pipeline import load_scene

STRIDE = ["scene.options.cloud_stride=8"]
REF_STRIDE = ["scene.options.cloud_stride=8"]
# a saved frame as ns-process-data's COLMAP one (axes permuted, y <-> z with a sign) plus a shift
APPLIED = np.array([[1.0, 0, 0, 0.3], [0, 0, 1, -0.2], [0, -1, 0, 1.5], [0, 0, 0, 1]])


def _save_u16(path, arr):
    Image.fromarray(np.asarray(arr, np.uint16)).save(path)


def _distorted(img, K, lens, order, fill=0):
    """The image a camera with ``lens`` (and the same K) would see: each distorted pixel samples the
    pinhole image at its undistorted position (the iterative inverse)."""
    from scipy.ndimage import map_coordinates

    h, w = img.shape[:2]
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = undistort_points((cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], lens)
    c, r = K[0, 0] * x + K[0, 2], K[1, 1] * y + K[1, 2]
    ok = (c >= -0.5) & (c <= w - 0.5) & (r >= -0.5) & (r <= h - 0.5)
    planes = img[..., None] if img.ndim == 2 else img
    out = np.stack([map_coordinates(planes[..., k].astype(np.float64), [r, c], order=order, mode="nearest")
                    for k in range(planes.shape[2])], -1)
    out[~ok] = fill
    out = np.rint(out).astype(img.dtype) if img.dtype.kind in "ui" else out.astype(img.dtype)
    return out[..., 0] if img.ndim == 2 else out


def write_nerfstudio(parent, frames, *, per_frame=False, camera_model="OPENCV", lens=None, applied=None,
                     ply=None, depth=True, labels=None, downscale=None, mask_half=False, extra=None):
    """The frames as ns-process-data lays them out: images/<name>.jpg (the 7-Scenes colour),
    depth/<name>.png (uint16 mm), transforms.json (OpenGL camera-to-world; poses in the frame
    ``applied`` maps the original world to, when given). ``lens``: distort images and depth with it
    and write its coefficients; ``ply``: (points, colours) in the original world, written in the
    saved one; ``labels``: name -> label image written as labels/<name>.png; ``downscale``: also
    images_<d>/ at 1/d size; ``mask_half``: masks/<name>.png with the left half 0."""
    root = parent / "ns"
    (root / "images").mkdir(parents=True, exist_ok=True)
    (root / "depth").mkdir(exist_ok=True)
    A = np.eye(4) if applied is None else applied
    K = frames[0]["K"]
    cam = {"fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2] + 0.5, "cy": K[1, 2] + 0.5, "w": 640, "h": 480}
    if lens is not None:
        cam.update({k: getattr(lens, k) for k in ("k1", "k2", "k3", "k4", "p1", "p2") if getattr(lens, k)})
    meta = {"camera_model": camera_model} if camera_model else {}
    if not per_frame:
        meta.update(cam)
    out = []
    for f in frames:  # loop over frames
        name = f["name"]
        rec = {"file_path": f"images/{name}.jpg",
               "transform_matrix": (A @ f["c2w"] @ OPENGL_TO_OPENCV).tolist()}
        if lens is None:
            shutil.copy(f["color_path"], root / "images" / f"{name}.jpg")
        else:  # PNG so the colour is not recompressed
            rec["file_path"] = f"images/{name}.png"
            Image.fromarray(_distorted(read_rgb(f["color_path"]), K, lens, 1)).save(root / "images" / f"{name}.png")
        if depth:
            mm = np.rint(f["depth"] * 1000.0)
            if lens is not None:
                mm = _distorted(mm, K, lens, 0)
            _save_u16(root / "depth" / f"{name}.png", mm)
            rec["depth_file_path"] = f"depth/{name}.png"
        if per_frame:
            rec.update(cam)
        if labels is not None:
            (root / "labels").mkdir(exist_ok=True)
            Image.fromarray(labels[name].astype(np.uint8)).save(root / "labels" / f"{name}.png")
        if downscale:
            (root / f"images_{downscale}").mkdir(exist_ok=True)
            im = Image.open(root / rec["file_path"])
            im.resize((640 // downscale, 480 // downscale), Image.BILINEAR).save(
                root / f"images_{downscale}" / f"{name}.jpg")
        if mask_half:
            (root / "masks").mkdir(exist_ok=True)
            m = np.full((480, 640), 255, np.uint8)
            m[:, :320] = 0
            Image.fromarray(m).save(root / "masks" / f"{name}.png")
            rec["mask_path"] = f"masks/{name}.png"
        out.append(rec)
    meta["frames"] = out[::-1]  # nerfstudio sorts by file_path: the loader must too
    if applied is not None:
        meta["applied_transform"] = applied[:3].tolist()
    if ply is not None:
        pts, cols = ply
        p = pts.astype(np.float64) @ A[:3, :3].T + A[:3, 3]
        v = np.zeros(len(p), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"),
                                    ("blue", "u1")])
        v["x"], v["y"], v["z"] = p[:, 0], p[:, 1], p[:, 2]
        v["red"], v["green"], v["blue"] = cols[:, 0], cols[:, 1], cols[:, 2]
        PlyData([PlyElement.describe(v, "vertex")]).write(str(root / "sparse_pc.ply"))
        meta["ply_file_path"] = "sparse_pc.ply"
    meta.update(extra or {})
    (root / "transforms.json").write_text(json.dumps(meta, indent=1))
    return root


@pytest.fixture(scope="module")
def seven():
    return seven_frames(5, 20)


@pytest.fixture(scope="module")
def reference(tmp_path_factory, seven):
    """The posed RGB-D folder's run on the frames: (points, labels, result)."""
    return reference_labels(tmp_path_factory.mktemp("ref"), seven, *REF_STRIDE)


def _run(root, *extra):
    return labels_of("scene=nerfstudio", f"scene.options.root={root}", *STRIDE, *extra)


@needs_7scenes
def test_shared_intrinsics_opencv_zero_distortion_agrees(tmp_path, seven, reference):
    root = write_nerfstudio(tmp_path, seven, camera_model="OPENCV",
                            extra={"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0})
    pts, lab, res = _run(root)
    ref_pts, ref_lab, _ = reference
    assert agreement(ref_pts, ref_lab, pts, lab) >= 0.999 and agreement(pts, lab, ref_pts, ref_lab) >= 0.999
    assert res.scene.frames.names == [f["name"] for f in seven]  # sorted by file_path, named by stem
    assert "undistorted" not in res.scene.frames.info  # zero coefficients: no resampling
    f = res.scene.frames[0]
    np.testing.assert_allclose(f.K, seven[0]["K"], atol=1e-12)
    np.testing.assert_allclose(f.T_cw, rigid_inverse(seven[0]["c2w"]), atol=1e-9)


@needs_7scenes
def test_per_frame_intrinsics_applied_transform_back_to_original(tmp_path, seven, reference):
    root = write_nerfstudio(tmp_path, seven, per_frame=True, camera_model=None, applied=APPLIED)
    pts, lab, res = _run(root, "scene.options.world=original")
    ref_pts, ref_lab, _ = reference
    assert agreement(ref_pts, ref_lab, pts, lab) >= 0.999
    # world=saved (the default) keeps the json's frame: the same cameras moved by applied_transform
    saved = load_scene(compose("scene=nerfstudio", f"scene.options.root={root}", *STRIDE).scene)
    for k, f in enumerate(seven):  # loop over frames
        np.testing.assert_allclose(saved.frames[k].T_cw, rigid_inverse(APPLIED @ f["c2w"]), atol=1e-9)


@needs_7scenes
def test_ply_file_path_is_the_cloud_in_either_frame(tmp_path, seven, reference):
    ref_pts, ref_lab, ref_res = reference
    cols = ref_res.scene.colors
    root = write_nerfstudio(tmp_path, seven, applied=APPLIED, ply=(ref_pts, cols))
    pts, lab, res = _run(root, "scene.options.world=original")  # PLY saved -> original with the poses
    assert len(pts) == len(ref_pts) and "sparse_pc.ply (ply_file_path)" in res.scene.frames.info["cloud"]
    assert agreement(ref_pts, ref_lab, pts, lab) >= 0.999
    # a PLY of nerfstudio < 1.0 (still in the original frame) read as such in the saved world
    p = PlyData.read(str(root / "sparse_pc.ply"))
    v = np.array(p["vertex"].data)  # a copy: plyfile maps the file
    orig = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64) - APPLIED[:3, 3]
    orig = orig @ APPLIED[:3, :3]  # A^-1 applied: back to the original frame
    v["x"], v["y"], v["z"] = orig[:, 0], orig[:, 1], orig[:, 2]
    PlyData([PlyElement.describe(v, "vertex")]).write(str(root / "sparse_pc.ply"))
    old = load_scene(compose("scene=nerfstudio", f"scene.options.root={root}", "scene.options.ply_world=original").scene)
    np.testing.assert_allclose(old.points, ref_pts @ APPLIED[:3, :3].T.astype(np.float32) + APPLIED[:3, 3], atol=1e-4)


@pytest.mark.parametrize("lens", [LensModel(PERSPECTIVE, k1=-0.12, k2=0.03, p1=0.002, p2=-0.001),
                                  LensModel(PERSPECTIVE, k1=0.08),  # pincushion: corners have no source
                                  LensModel(FISHEYE, k1=0.04, k2=-0.01, k3=0.003)])
def test_undistortion_reproduces_the_pinhole_image(lens):
    """An image of a smooth pattern, distorted analytically, resamples back to the pinhole image."""
    K = np.array([[500.0, 0, 319.5], [0, 480.0, 241.0], [0, 0, 1]])
    h, w = 480, 640

    def pattern(x, y):  # a smooth function of the ray direction
        return 120 + 60 * np.sin(6 * x) * np.cos(5 * y) + 40 * x

    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    xu, yu = undistort_points((cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], lens)
    seen = pattern(xu, yu)  # what the distorted camera's pixel sees
    out = undistort_image(seen, K, lens, order=1, fill=np.nan)
    truth = pattern((cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1])
    ok = np.isfinite(out)
    assert ok.mean() > (0.9 if lens.k1 > 0 else 0.999)
    assert np.abs(out[ok] - truth[ok]).max() < 0.5  # bilinear error of a smooth pattern, grey levels
    # the map is the forward model: the distorted position of each pinhole pixel
    xd, yd = distort_points(xu, yu, lens)
    assert np.abs(xd - (cols - K[0, 2]) / K[0, 0]).max() < 1e-9
    # labels: nearest, -1 where there is no source, which a mapping leaves IGNORE (capture's rule)
    ids = undistort_image(np.full((h, w), 5, np.int64), K, lens, order=0, fill=IGNORE)
    mapped = to_taxonomy(ids, load_mapping("nyu40_to_scannet20", SCANNET20), SCANNET20, "labels")
    assert ((mapped == IGNORE) == ~ok).all() and (mapped[ok] == mapped[ok][0]).all() and mapped[ok][0] >= 0


def _against_pinhole(scene, frames):
    """Per frame: the share of valid depth pixels within 1 cm of the pinhole original's, and the
    median grey-level difference of the colour."""
    same_depth, grey_err = [], []
    for k, f in enumerate(frames):  # loop over frames: undistorted frames vs the pinhole originals
        fr = scene.frames[k]
        valid = (fr.depth > 0) & (f["depth"] > 0)
        same_depth.append(np.mean(np.abs(fr.depth[valid] - f["depth"][valid]) < 0.01))
        grey = fr.rgb.astype(np.float32).mean(2) - read_rgb(f["color_path"]).astype(np.float32).mean(2)
        grey_err.append(np.median(np.abs(grey)))
    return min(same_depth), max(grey_err)


@needs_7scenes
def test_distorted_capture_is_undistorted(tmp_path, seven, reference):
    """Frames distorted with known coefficients (iterative inverse, resampled) come back as the
    pinhole frames: the undistortion itself is exact (test above), what differs is the round
    trip's double resampling (nearest depth, bilinear colour) at depth and colour edges."""
    lens = LensModel(PERSPECTIVE, k1=-0.15, k2=0.04, p1=0.001)
    root = write_nerfstudio(tmp_path, seven, lens=lens)
    scene = load_scene(compose("scene=nerfstudio", f"scene.options.root={root}", *STRIDE).scene)
    assert scene.frames.info["undistorted"] == {lens.text(): len(seven)}
    depth_ok, grey_err = _against_pinhole(scene, seven)
    assert depth_ok > 0.98 and grey_err < 4
    # the toy network's labels on the points: the double resampling moves points by < 2 cm
    pts, lab, _ = _run(root)
    ref_pts, ref_lab, _ = reference
    assert agreement(ref_pts, ref_lab, pts, lab, tol=0.02) >= 0.98
    # undistort=false refuses the distorted camera, naming the file, the frame and the model
    with pytest.raises(ValueError, match=r"transforms\.json: frame images/frame-\d+\.png: camera_model OPENCV "
                                         r"\(perspective k1=-0\.15.*undistort=false refuses"):
        load_scene(compose("scene=nerfstudio", f"scene.options.root={root}", "scene.options.undistort=false").scene)
    # OPENCV_FISHEYE
    fish = LensModel(FISHEYE, k1=0.04, k2=-0.01)
    root = write_nerfstudio(tmp_path / "fisheye", seven[:2], lens=fish, camera_model="OPENCV_FISHEYE")
    scene = load_scene(compose("scene=nerfstudio", f"scene.options.root={root}", *STRIDE).scene)
    depth_ok, grey_err = _against_pinhole(scene, seven[:2])
    assert depth_ok > 0.97 and grey_err < 4


@needs_7scenes
def test_downscale_masks_labels_and_depth_unit(tmp_path, seven):
    few = seven[:2]
    labels = {f["name"]: (read_rgb(f["color_path"]).mean(2) > 100).astype(np.uint8) for f in few}
    pts = (few[0]["c2w"][:3, :3] @ np.random.default_rng(0).uniform([-1, -1, 1], [1, 1, 3], (500, 3)).T).T \
        + few[0]["c2w"][:3, 3]  # points in front of the first camera
    root = write_nerfstudio(tmp_path, few, depth=False, downscale=2, labels=labels,
                            ply=(pts.astype(np.float32), np.zeros((500, 3), np.uint8)))
    s = load_scene(compose("scene=nerfstudio", f"scene.options.root={root}", "scene.options.downscale=2",
                           "scene.options.labels='labels/{stem}.png'", "scene.options.gt_from_frames=false").scene)
    f = s.frames[0]  # no depth: the frame takes images_2/'s size, K scaled from the json's (h, w)
    assert f.rgb.shape == (240, 320, 3)
    np.testing.assert_allclose(f.K, scaled_intrinsics(few[0]["K"], (480, 640), (240, 320)), atol=1e-12)
    assert f.gt_labels.shape == (240, 320) and set(np.unique(f.gt_labels)) <= {0, 1}
    with pytest.raises(FileNotFoundError, match=r"images_4/frame-\d+\.jpg does not exist.*downscale=4"):
        load_scene(compose("scene=nerfstudio", f"scene.options.root={root}", "scene.options.downscale=4").scene)
    # masks zero the depth; depth_unit_scale reads the PNGs in another unit
    root2 = write_nerfstudio(tmp_path / "m", few, mask_half=True)
    s = load_scene(compose("scene=nerfstudio", f"scene.options.root={root2}/transforms.json",
                           "scene.options.depth_unit_scale=0.002").scene)
    d = s.frames[0].depth
    assert (d[:, :320] == 0).all() and (d[:, 320:] > 0).mean() > 0.5
    valid = (d > 0) & (few[0]["depth"] > 0)
    np.testing.assert_allclose(d[valid], 2 * few[0]["depth"][valid], atol=1e-5)
    s = load_scene(compose("scene=nerfstudio", f"scene.options.root={root2}", "scene.options.masks=false").scene)
    assert (s.frames[0].depth[:, :320] > 0).mean() > 0.5


@pytest.fixture
def tiny(tmp_path):
    """A two-frame transforms.json with a grey image and a depth PNG (no 7-Scenes needed)."""
    root = tmp_path / "tiny"
    (root / "images").mkdir(parents=True)
    for n in ("a", "b"):  # loop over frames
        Image.fromarray(np.full((24, 32, 3), 128, np.uint8)).save(root / "images" / f"{n}.png")
        _save_u16(root / f"{n}.depth.png", np.full((24, 32), 1500))
    meta = {"camera_model": "OPENCV", "fl_x": 30.0, "fl_y": 30.0, "cx": 16.0, "cy": 12.0, "w": 32, "h": 24,
            "frames": [{"file_path": f"images/{n}.png", "depth_file_path": f"{n}.depth.png",
                        "transform_matrix": np.eye(4).tolist()} for n in ("a", "b")]}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root, meta


def _load(root, *extra):
    return load_scene(compose("scene=nerfstudio", f"scene.options.root={root}", *extra).scene)


def test_malformed_transforms(tiny):
    root, meta = tiny
    src = root / "transforms.json"
    s = _load(root)
    assert len(s.frames) == 2 and abs(float(np.median(s.frames[0].depth)) - 1.5) < 1e-6
    cases = [
        ({**meta, "camera_model": "EQUIRECTANGULAR"},
         r"transforms\.json: frame images/a\.png: camera_model 'EQUIRECTANGULAR' is not supported \(expected OPENCV"),
        ({**meta, "frames": [{**meta["frames"][0], "camera_model": "FISHEYE624"}]},
         r"frame images/a\.png: camera_model 'FISHEYE624' is not supported"),
        ({**meta, "frames": [{**meta["frames"][0], "transform_matrix": (2 * np.eye(4)).tolist()}]},
         r"transforms\.json: frame images/a\.png transform_matrix: pose is not a rigid transform"),
        ({**meta, "frames": [{**meta["frames"][0], "transform_matrix": [[1, 0, 0], [0, 1, 0]]}]},
         r"frame images/a\.png: transform_matrix is not a finite 4x4 or 3x4 matrix"),
        ({k: v for k, v in meta.items() if k != "fl_y"},
         r"frame images/a\.png: no fl_y \(neither in the frame nor at the top level\)"),
        ({**meta, "cx": "16"}, r"frame images/a\.png: cx='16', expected a finite number"),
        ({**meta, "frames": [{"file_path": "images/a.png"}]}, r"transforms\.json: frames\[0\] lacks file_path or transform_matrix"),
        ({"frames": {}}, r"transforms\.json: no 'frames' list, expected nerfstudio's transforms\.json"),
        ({**meta, "frames": [meta["frames"][0], {**meta["frames"][1], "file_path": "other/a.png"}]},
         r"frames images/a\.png and other/a\.png share the name a"),
    ]
    for bad, pattern in cases:  # loop over malformed files
        src.write_text(json.dumps(bad))
        with pytest.raises(ValueError, match=pattern):
            _load(root)
    src.write_text(json.dumps(meta)[:-40])  # truncated
    with pytest.raises(ValueError, match=r"transforms\.json: not valid JSON \(.* at line 1 column \d+\)"):
        _load(root)
    src.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"no applied_transform, so scene\.options\.world=original"):
        _load(root, "scene.options.world=original")
    with pytest.raises(FileNotFoundError, match=r"transforms file .*nope\.json does not exist"):
        _load(root, "scene.options.transforms=nope.json")
    with pytest.raises(ValueError, match=r"scene\.options\.downscale=3: expected 1, 2, 4 or 8"):
        _load(root, "scene.options.downscale=3")


def test_bad_transforms_is_one_cli_line(tiny, tmp_path):
    root, meta = tiny
    (root / "transforms.json").write_text(json.dumps({**meta, "camera_model": "VR180_L"}))
    r = run_cli("scene=nerfstudio", f"scene.options.root={root}", "record=off", f"hydra.run.dir={tmp_path / 'out'}")
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("diffuser-lab: error:")]
    assert r.returncode != 0 and len(lines) == 1, r.stderr[-2000:]
    assert "transforms.json: frame images/a.png: camera_model 'VR180_L' is not supported" in lines[0]
    assert "Traceback" not in r.stderr


def test_the_stated_size_against_the_images(tiny, tmp_path):
    """Issue 52 item 4: transforms.json's w h describe its images: equal, or images that are a downscale
    of them keeping the aspect (K scaled and said); w = h = 1,000,000 over 32 x 24 images is one line
    naming both files (it ran to the end with K scaled by 32e-6 x 24e-6)."""
    root, meta = tiny
    src = root / "transforms.json"
    src.write_text(json.dumps({**meta, "w": 64, "h": 48, "fl_x": 60.0, "fl_y": 60.0, "cx": 32.0, "cy": 24.0}))
    s = _load(root)
    assert s.frames[0].K[0, 0] == 30.0 and "scaled by 1/2 to the 32x24 images" in s.frames.info["intrinsics"]
    for w, h in ((1_000_000, 1_000_000), (64, 24), (16, 12)):  # a lie, another aspect, an upscale
        src.write_text(json.dumps({**meta, "w": w, "h": h}))
        with pytest.raises(ValueError, match=rf"transforms\.json \(frame images/a\.png: w h\): K is stated for {w}x{h} "
                                             rf"\(W x H\) images, .*images/a\.png is 32x24: expected that size or a "
                                             rf"downscale of it"):
            _load(root)
    src.write_text(json.dumps({**meta, "w": 1_000_000, "h": 1_000_000}))
    r = run_cli("scene=nerfstudio", f"scene.options.root={root}", "record=off", f"hydra.run.dir={tmp_path / 'out'}")
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode != 0 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert lines[0].startswith("diffuser-lab: error: ") and "transforms.json" in lines[0] and "images/a.png" in lines[0]
