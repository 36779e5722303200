"""scene.source=rosbag (diffuser_lab/data/sources/rosbag.py): the 7-Scenes frames written as bags with
rosbags' own writers label the same points as the posed RGB-D folder; the labelled cloud written as a
PointCloud2 MCAP bag reads back; bad bags fail with one line."""
import shutil
import struct

import numpy as np
import pytest
from captures import agreement, labels_of, needs_7scenes, seven_frames, write_rgbd_reference
from conftest import compose, run_cli

from diffuser_lab.data.scene import IGNORE, SCANNET20
from diffuser_lab.data.clouds import read_pointcloud2_bag, write_pointcloud2_bag
from diffuser_lab.data.sources.rosbag import RosbagOptions, load_rosbag
from diffuser_lab.data.poses import rigid_inverse

T0 = 1_700_000_000 * 10**9  # the first frame's stamp, ns
DT = 500_000_000  # frames 0.5 s apart (every 15th frame at 30 Hz)
# base_link -> camera_optical (static): the REP 103 body (x forward, z up) to optical (z forward) rotation, offset
T_BC = np.array([[0, 0, 1, 0.10], [-1, 0, 0, 0.02], [0, -1, 0, 0.30], [0, 0, 0, 1]], np.float64)
Q_BC = (-0.5, 0.5, -0.5, 0.5)  # qx qy qz qw of T_BC's rotation
STRIDE = "scene.options.cloud_stride=8"


def _quat(R):
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat()


def _msgs(ts, ros1: bool):
    """Message constructors of a typestore (ROS 1 headers carry a seq)."""
    T = ts.types

    def header(stamp, frame):
        kw = dict(stamp=T["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id=frame)
        return T["std_msgs/msg/Header"](seq=0, **kw) if ros1 else T["std_msgs/msg/Header"](**kw)

    def image(stamp, frame, a, enc):
        a = np.ascontiguousarray(a)
        h, w = a.shape[:2]
        return T["sensor_msgs/msg/Image"](header=header(stamp, frame), height=h, width=w, encoding=enc, is_bigendian=0,
                                          step=a.strides[0], data=a.view(np.uint8).reshape(-1))

    def info(stamp, frame, K, h, w, D=np.zeros(5)):
        RoI = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        P = np.hstack([K, np.zeros((3, 1))]).ravel()
        D = np.asarray(D, np.float64)
        kd = dict(D=D, K=K.ravel(), R=np.eye(3).ravel(), P=P) if ros1 else \
            dict(d=D, k=K.ravel(), r=np.eye(3).ravel(), p=P)
        return T["sensor_msgs/msg/CameraInfo"](header=header(stamp, frame), height=h, width=w,
                                               distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=RoI, **kd)

    def transform(stamp, parent, child, Tm, scale=1.0):
        V, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
        q = _quat(Tm[:3, :3]) * scale
        return T["geometry_msgs/msg/TransformStamped"](
            header=header(stamp, parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](translation=V(x=Tm[0, 3], y=Tm[1, 3], z=Tm[2, 3]),
                                                       rotation=Q(x=q[0], y=q[1], z=q[2], w=q[3])))

    def pose(stamp, frame, Tm, q=None):
        q = _quat(Tm[:3, :3]) if q is None else q
        P = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=Tm[0, 3], y=Tm[1, 3], z=Tm[2, 3]),
                                        orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
        return T["geometry_msgs/msg/PoseStamped"](header=header(stamp, frame), pose=P)

    return header, image, info, transform, pose


def _distort(depth, K, lens):
    """A pinhole depth image as the distorted camera of the same K would see it (nearest)."""
    from diffuser_lab.data.distortion import undistort_points

    h, w = depth.shape
    v, u = np.mgrid[:h, :w].astype(np.float64)
    x, y = undistort_points((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], lens)
    cu, cv = np.rint(K[0, 0] * x + K[0, 2]).astype(int), np.rint(K[1, 1] * y + K[1, 2]).astype(int)
    inside = (cu >= 0) & (cu < w) & (cv >= 0) & (cv < h)
    return np.where(inside, depth[np.clip(cv, 0, h - 1), np.clip(cu, 0, w - 1)], 0)


def write_ros2_bag(path, frames, storage="mcap", extra_depth=True, rigid=True, D=None, info_size=None):
    """The frames as a ROS 2 bag: depth Image 16UC1 (mm), colour CompressedImage (the JPEG files' bytes),
    label images mono16 at half size (the toy network's grey-level classes), CameraInfo (``D``: plumb_bob
    coefficients, the depth images distorted by them), /tf world -> base_link
    per frame (samples 10 ms before and after each stamp), /tf_static
    base_link -> camera_optical; colour stamped 5 ms after depth. ``extra_depth``: one more depth image
    with no colour near it (skipped). ``info_size``: the (height, width) CameraInfo states (default: the depth's).
    """
    from PIL import Image as PILImage
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    header, image, info, transform, _ = _msgs(ts, False)
    T = ts.types
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    msgs = []  # (record time, topic, message)
    K = frames[0]["K"]
    msgs.append((T0 - DT, "/tf_static", T["tf2_msgs/msg/TFMessage"](
        transforms=[transform(T0 - DT, "base_link", "camera_optical", T_BC)])))
    for i, f in enumerate(frames):  # loop over frames
        t = T0 + i * DT
        T_wb = f["c2w"] @ rigid_inverse(T_BC)
        for dt in (-10_000_000, 10_000_000):  # bracketing samples of the same pose
            msgs.append((t + dt, "/tf", T["tf2_msgs/msg/TFMessage"](transforms=[transform(
                t + dt, "world", "base_link", T_wb, 1.0 if rigid or i != 1 else 2.0)])))  # frame 1: not rigid
        depth = np.rint(f["depth"] * 1000).astype(np.uint16)
        if D is not None:
            from diffuser_lab.data.distortion import ros_lens

            depth = _distort(depth, K, ros_lens("plumb_bob", D, "test"))
        msgs.append((t, "/camera/depth/image_rect_raw", image(t, "camera_optical", depth, "16UC1")))
        msgs.append((t, "/camera/depth/camera_info", info(t, "camera_optical", K, *(info_size or depth.shape),
                                                          *(() if D is None else (D,)))))
        jpeg = np.frombuffer(f["color_path"].read_bytes(), np.uint8)
        grey = np.asarray(PILImage.open(f["color_path"]).convert("RGB"))[::2, ::2].mean(axis=2)
        labels = np.digitize(grey, (60, 120, 180)).astype(np.uint16)  # the toy network's classes, half size
        msgs.append((t + 3_000_000, "/camera/labels", image(t + 3_000_000, "camera_optical", labels, "mono16")))
        msgs.append((t + 5_000_000, "/camera/color/image_raw/compressed", T["sensor_msgs/msg/CompressedImage"](
            header=header(t + 5_000_000, "camera_optical"), format="rgb8; jpeg compressed bgr8", data=jpeg)))
    if extra_depth:
        t = T0 + (len(frames) + 4) * DT
        msgs.append((t, "/camera/depth/image_rect_raw", image(t, "camera_optical", depth, "16UC1")))
    types = {"/tf_static": "tf2_msgs/msg/TFMessage", "/tf": "tf2_msgs/msg/TFMessage",
             "/camera/depth/image_rect_raw": "sensor_msgs/msg/Image",
             "/camera/depth/camera_info": "sensor_msgs/msg/CameraInfo", "/camera/labels": "sensor_msgs/msg/Image",
             "/camera/color/image_raw/compressed": "sensor_msgs/msg/CompressedImage"}
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conns = {topic: w.add_connection(topic, typ, typestore=ts) for topic, typ in types.items()}
        for t, topic, m in sorted(msgs, key=lambda x: x[0]):  # loop over messages
            w.write(conns[topic], t, ts.serialize_cdr(m, types[topic]))
    return path


def write_ros1_bag(path, frames, bad_quat=False):
    """The frames as a ROS 1 bag: depth Image 32FC1 (metres), colour Image bgr8, CameraInfo, and the body
    pose as PoseStamped on /body/pose (frame odom); the camera sits at T_BC in the body."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore
    from PIL import Image

    ts = get_typestore(Stores.ROS1_NOETIC)
    _, image, info, _, pose = _msgs(ts, True)
    types = {"/camera/depth/image": "sensor_msgs/msg/Image", "/camera/depth/camera_info": "sensor_msgs/msg/CameraInfo",
             "/camera/rgb/image_color": "sensor_msgs/msg/Image", "/body/pose": "geometry_msgs/msg/PoseStamped"}
    with Writer(path) as w:
        conns = {topic: w.add_connection(topic, typ, typestore=ts) for topic, typ in types.items()}
        for i, f in enumerate(frames):  # loop over frames
            t = T0 + i * DT
            bgr = np.asarray(Image.open(f["color_path"]).convert("RGB"))[..., ::-1]
            q = (0.0, 0.0, 0.0, 2.0) if bad_quat and i == 2 else None
            for topic, m in (("/body/pose", pose(t, "odom", f["c2w"] @ rigid_inverse(T_BC), q)),
                             ("/camera/depth/image", image(t, "camera", f["depth"].astype(np.float32), "32FC1")),
                             ("/camera/depth/camera_info", info(t, "camera", f["K"], *f["depth"].shape)),
                             ("/camera/rgb/image_color", image(t, "camera", bgr, "bgr8"))):
                w.write(conns[topic], t, ts.serialize_ros1(m, types[topic]))
    return path


@pytest.fixture(scope="module")
def seven():
    """5 frames, their poses made rigid: 7-Scenes' rotation matrices are orthonormal to only ~2e-4, and a
    bag stores rotations as unit quaternions (the difference moves points by up to ~0.5 mm)."""
    from scipy.spatial.transform import Rotation

    frames = seven_frames(5, 15)
    for f in frames:  # loop over frames
        f["c2w"] = f["c2w"].copy()
        f["c2w"][:3, :3] = Rotation.from_matrix(f["c2w"][:3, :3]).as_matrix()
    return frames


@pytest.fixture(scope="module")
def reference(tmp_path_factory, seven):
    """The posed RGB-D folder's run on the same frames with the same (rigid) poses."""
    root = write_rgbd_reference(tmp_path_factory.mktemp("ref"), seven)
    for f in seven:  # loop over frames: the rigid pose files
        np.savetxt(root / f["pose_path"].name, f["c2w"])
    pts, lab, _ = labels_of("scene=rgbd_folder", f"scene.options.root={root}", "scene.options.cloud_stride=8")
    return pts, lab


@pytest.fixture(scope="module")
def ros2_bag(tmp_path_factory, seven):
    return write_ros2_bag(tmp_path_factory.mktemp("bag2") / "rec", seven)


@needs_7scenes
def test_ros2_bag_labels_as_the_rgbd_folder(ros2_bag, reference, seven):
    pts, lab, res = labels_of("scene=rosbag", f"scene.options.path={ros2_bag}", STRIDE,
                              "scene.options.world_frame=world",
                              "scene.options.labels_topic=/camera/labels")
    a = agreement(pts, lab, *reference)
    assert a >= 0.999 and agreement(*reference, pts, lab) >= 0.999, a
    info = res.scene.frames.info
    assert info["n_frames_found"] == 6 and info["n_no_color"] == 1 and info["n_no_pose"] == 0  # the extra depth
    assert info["camera_frame"] == "camera_optical" and info["world_frame"] == "world" and info["n_no_labels"] == 0
    gt = res.scene.gt_labels  # carried from the label images: the toy network's classes: most points agree
    assert (gt != IGNORE).mean() > 0.9 and (gt == lab).mean() > 0.5, ((gt != IGNORE).mean(), (gt == lab).mean())
    f = res.scene.frames[2]
    np.testing.assert_allclose(f.T_cw, rigid_inverse(seven[2]["c2w"]), atol=1e-6)
    np.testing.assert_array_equal(f.depth, seven[2]["depth"])


@needs_7scenes
def test_ros1_bag_with_a_pose_topic(tmp_path, reference, seven):
    bag = write_ros1_bag(tmp_path / "rec.bag", seven)
    q = ",".join(f"{v:.12g}" for v in (*T_BC[:3, 3], *Q_BC))
    pts, lab, res = labels_of("scene=rosbag", f"scene.options.path={bag}", STRIDE,
                              "scene.options.pose_topic=/body/pose",
                              f"scene.options.camera_in_body=[{q}]")
    assert agreement(pts, lab, *reference) >= 0.999 and agreement(*reference, pts, lab) >= 0.999
    assert res.scene.frames.info["world_frame"] == "odom" and res.scene.frames.info["n_no_pose"] == 0


@needs_7scenes
def test_db3_storage_reads_the_same_frames(tmp_path, ros2_bag, seven):
    db3 = write_ros2_bag(tmp_path / "rec", seven[:2], storage="sqlite3", extra_depth=False)
    o = dict(world_frame="world", cloud_stride=16, max_frames=2)
    a = load_rosbag(RosbagOptions(path=str(next(db3.glob("*.db3"))), **o), SCANNET20)
    b = load_rosbag(RosbagOptions(path=str(next(ros2_bag.glob("*.mcap"))), **o), SCANNET20)  # the .mcap file itself
    assert a.frames.names == b.frames.names == ["1700000000.000000000", "1700000000.500000000"]
    for fa, fb in zip(a.frames, b.frames):  # loop over two frames
        np.testing.assert_array_equal(fa.depth, fb.depth), np.testing.assert_array_equal(fa.rgb, fb.rgb)
        np.testing.assert_allclose(fa.T_cw, fb.T_cw, atol=1e-12), np.testing.assert_allclose(fa.K, fb.K)


@needs_7scenes
def test_online_run_consumes_the_frames_in_stamp_order(ros2_bag):
    from captures import NETWORK

    from diffuser_lab.hooks import RunHooks
    from diffuser_lab.runs.online import online

    seen = []

    class Names(RunHooks):
        def on_frame(self, i, f):
            seen.append(f.name)

    cfg = compose("scene=rosbag", f"scene.options.path={ros2_bag}", "scene.options.world_frame=world",
                  "scene.options.cloud_stride=16", "scene.options.max_frames=4", "protocol=online", *NETWORK)
    res = online(cfg, hooks=Names())
    t = [T0 + k * DT for k in range(4)]
    assert seen == [f"{s // 10**9}.{s % 10**9:09d}" for s in t]
    assert len(res.labels) > 1000 and (res.labels != IGNORE).mean() > 0.5


# ------------------------------------------------------------------------------------ bad input


@needs_7scenes
def test_bad_bags_fail_with_one_line(tmp_path, ros2_bag, seven):
    def opts(path, **kw):
        return RosbagOptions(path=str(path), **{"world_frame": "world", "cloud_stride": 16, **kw})

    with pytest.raises(ValueError, match=r"rec: no topic /camera/depth/image_raw \(scene.options.depth_topic\); "
                                         r"topics present: .*/camera/depth/image_rect_raw \(sensor_msgs/msg/Image\)"):
        load_rosbag(opts(ros2_bag, depth_topic="/camera/depth/image_raw"), SCANNET20)
    with pytest.raises(ValueError, match=r"frame 'earth' \(scene.options.world_frame\) is not in /tf or /tf_static; "
                                         r"frames there: base_link, camera_optical, world"):
        load_rosbag(opts(ros2_bag, world_frame="earth"), SCANNET20)
    bent = write_ros2_bag(tmp_path / "bent", seven[:3], extra_depth=False, rigid=False)
    with pytest.raises(ValueError, match=r"bent: /tf world -> base_link: sample 2 has quaternion norm .*a rigid"):
        load_rosbag(opts(bent), SCANNET20)
    ros1 = write_ros1_bag(tmp_path / "bad.bag", seven[:3], bad_quat=True)
    with pytest.raises(ValueError, match=r"bad\.bag: /body/pose: sample 2 has quaternion norm 2"):
        load_rosbag(opts(ros1, pose_topic="/body/pose"), SCANNET20)
    mcap = next(ros2_bag.glob("*.mcap"))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    with pytest.raises(ValueError, match=r"cut\.mcap: not an MCAP file .*mcap recover"):
        load_rosbag(opts(cut), SCANNET20)
    cut1 = tmp_path / "cut.bag"
    cut1.write_bytes(ros1.read_bytes()[: ros1.stat().st_size // 2])
    with pytest.raises(ValueError, match=r"cut\.bag: not a readable ROS bag"):
        load_rosbag(opts(cut1, pose_topic="/body/pose"), SCANNET20)
    r = run_cli("scene=rosbag", f"scene.options.path={ros2_bag}", "scene.options.depth_topic=/depth", "record=off")
    errors = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode != 0 and len(errors) == 1, r.stderr
    assert errors[0].startswith("diffuser-lab: error: ") and "no topic /depth" in errors[0] and "rec" in errors[0]


# ------------------------------------------------------------------------------------ output


def test_pointcloud2_bag_reads_back(tmp_path):
    from mcap.reader import make_reader

    rng = np.random.default_rng(0)
    pts = rng.normal(size=(500, 3)).astype(np.float32)
    lab = rng.integers(-1, SCANNET20.num_classes, 500).astype(np.int16)
    mcap = write_pointcloud2_bag(tmp_path / "labels", pts, lab, SCANNET20, frame_id="world", stamp_ns=T0)
    p, lb, cols, frame = read_pointcloud2_bag(tmp_path / "labels")
    np.testing.assert_array_equal(p, pts), np.testing.assert_array_equal(lb, lab)
    np.testing.assert_array_equal(cols, SCANNET20.colorize(lab, (128, 128, 128)))
    assert frame == "world"
    with open(mcap, "rb") as fh:  # what Foxglove / rviz2 see: the schema by name, CDR
        (schema, channel, message), = list(make_reader(fh).iter_messages())
    assert schema.name == "sensor_msgs/msg/PointCloud2" and schema.encoding == "ros2msg"
    assert channel.topic == "/diffuser_lab/labels" and channel.message_encoding == "cdr"
    assert message.log_time == T0 and len(message.data) > 500 * 20
    raw = mcap.read_bytes()
    with pytest.raises(FileExistsError, match="labels"):
        write_pointcloud2_bag(tmp_path / "labels", pts, lab, SCANNET20)
    shutil.rmtree(tmp_path / "labels")
    # a width that lies (5,000 points declared, 500 stored): one line before any array is made
    assert raw.count(struct.pack("<II", 1, 500)) == 1
    write_pointcloud2_bag(tmp_path / "lies", pts, lab, SCANNET20, stamp_ns=T0)
    lied = next((tmp_path / "lies").glob("*.mcap"))
    lied.write_bytes(raw.replace(struct.pack("<II", 1, 500), struct.pack("<II", 1, 5000)))
    with pytest.raises(ValueError, match=r"lies: /diffuser_lab/labels declares 5000 x 1 points of 20 bytes"):
        read_pointcloud2_bag(tmp_path / "lies")


def test_image_encodings_and_a_distorted_camera_info():
    from types import SimpleNamespace as NS

    from diffuser_lab.data.sources.rosbag import _intrinsics, _to_depth, _to_rgb, decode_image

    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    pad = np.zeros((2, 12), np.uint8)  # rows padded to a step of 12 bytes
    pad[:, :9] = rgb[..., ::-1].reshape(2, 9)
    a, enc = decode_image(NS(encoding="bgr8", height=2, width=3, step=12, is_bigendian=0, data=pad.ravel()), "m")
    np.testing.assert_array_equal(_to_rgb(a, enc, "m"), rgb)
    bgra = np.concatenate([rgb[..., ::-1], np.full((2, 3, 1), 255, np.uint8)], 2)
    a, enc = decode_image(NS(encoding="bgra8", height=2, width=3, step=12, is_bigendian=0, data=bgra.ravel()), "m")
    np.testing.assert_array_equal(_to_rgb(a, enc, "m"), rgb)
    mm = np.array([[0, 1000, 2500]], ">u2")  # big-endian millimetres
    a, enc = decode_image(NS(encoding="16UC1", height=1, width=3, step=6, is_bigendian=1,
                             data=mm.view(np.uint8).ravel()), "m")
    np.testing.assert_allclose(_to_depth(a, enc, 1000.0, "m"), [[0, 1, 2.5]])
    f = np.array([[np.nan, 1.5, -1]], np.float32)
    msg = NS(encoding="32FC1", height=1, width=3, step=12, is_bigendian=0, data=f.view(np.uint8).ravel())
    a, enc = decode_image(msg, "m")
    np.testing.assert_allclose(_to_depth(a, enc, 1000.0, "m"), [[0, 1.5, 0]])
    import io
    import struct

    from PIL import Image

    png = io.BytesIO()
    Image.fromarray(np.array([[0, 1000, 2500]], np.uint16)).save(png, format="PNG")
    cd = NS(format="16UC1; compressedDepth png",
            data=np.frombuffer(struct.pack("<iff", 0, 0, 0) + png.getvalue(), np.uint8))
    np.testing.assert_allclose(_to_depth(*decode_image(cd, "m"), 1000.0, "m"), [[0, 1, 2.5]])
    with pytest.raises(ValueError, match=r"m: rgb8 image 3x2 with step 9 and 10 bytes, expected step >= 9"):
        decode_image(NS(encoding="rgb8", height=2, width=3, step=9, is_bigendian=0, data=np.zeros(10, np.uint8)), "m")
    with pytest.raises(ValueError, match=r"m: image encoding 'yuv422', expected one of rgb8"):
        decode_image(NS(encoding="yuv422", height=2, width=3, step=9, is_bigendian=0, data=np.zeros(18, np.uint8)), "m")
    info = NS(k=np.array([585.0, 0, 320, 0, 585, 240, 0, 0, 1]), d=np.array([0.1, -0.2, 0, 0, 0]),
              distortion_model="kannala", height=480, width=640)
    with pytest.raises(ValueError, match=r"b\.bag: /cam/camera_info: distortion_model 'kannala' with D = \[0\.1.*"
                                         r"expected plumb_bob, rational_polynomial, equidistant"):
        _intrinsics(info, "b.bag", "/cam/camera_info")
    info.distortion_model = "plumb_bob"
    K, size, lens = _intrinsics(info, "b.bag", "/cam/camera_info")
    assert (lens.kind, lens.k1, lens.k2) == ("perspective", 0.1, -0.2)
    info.d = np.zeros(5)
    K, size, lens = _intrinsics(info, "b.bag", "/cam/camera_info")
    assert size == (480, 640) and K[0, 2] == 320 and lens is None


@needs_7scenes
def test_a_distorted_camera_info_undistorts_the_frames(tmp_path, seven):
    """Depth images of a plumb_bob camera (an Azure Kinect's raw topics) come back as the pinhole
    camera's: the one undistortion (data/distortion.py) inverts the distortion the bag was written with."""
    D = (0.12, -0.25, 0.001, -0.0005, 0.08)
    bag = write_ros2_bag(tmp_path / "rec", seven[:1], extra_depth=False, D=D)
    s = load_rosbag(RosbagOptions(path=str(bag), world_frame="world", cloud_stride=16), SCANNET20)
    assert s.frames.info["undistorted"].startswith("perspective k1=0.12 k2=-0.25")
    got, want = s.frames[0].depth, seven[0]["depth"]
    both = (got > 0) & (want > 0)
    assert both.mean() > 0.8  # the corners the distorted image did not see stay without depth
    close = np.abs(got[both] - want[both]) < 0.002  # nearest twice: one pixel off at depth edges
    assert close.mean() > 0.97, close.mean()
    from diffuser_lab.data.distortion import ros_lens

    # the images as the bag holds them (read as if rectified) are far from the pinhole ones
    raw = _distort(np.rint(want * 1000).astype(np.uint16), seven[0]["K"], ros_lens("plumb_bob", D, "t")) / 1000
    assert (np.abs(raw[both] - want[both]) < 0.002).mean() < close.mean() - 0.05


@needs_7scenes
def test_a_camera_info_size_that_lies_is_one_line(tmp_path, seven):
    """Issue 52 item 4: CameraInfo's width x height describe the depth images (640 x 480): twice that
    takes K scaled (and said); a size no downscale of them can be is one line naming the bag and topic."""
    opts = dict(world_frame="world", cloud_stride=16)
    big = write_ros2_bag(tmp_path / "big", seven[:2], extra_depth=False, info_size=(960, 1280))
    s = load_rosbag(RosbagOptions(path=str(big), **opts), SCANNET20)
    assert "scaled by 1/2 to the 640x480 images" in s.frames.info["intrinsics"]
    np.testing.assert_allclose(s.frames[0].K[0, 0], seven[0]["K"][0, 0] / 2)
    lie = write_ros2_bag(tmp_path / "lie", seven[:2], extra_depth=False, info_size=(1_000_000, 1_000_000))
    with pytest.raises(ValueError, match=r"lie.*: /camera/depth/camera_info \(width x height\): K is stated for "
                                         r"1000000x1000000 \(W x H\) images, frame .*'s depth image is 640x480"):
        load_rosbag(RosbagOptions(path=str(lie), **opts), SCANNET20)
