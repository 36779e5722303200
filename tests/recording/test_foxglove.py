"""run.mcap for Foxglove (and Rerun's MCAP loader): the cameras as foxglove messages, a timeline
ordered by camera and iteration, the label images in the re-logged .rrd, the shipped layout."""
import io
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from google.protobuf import descriptor_pb2
from mcap.reader import make_reader
from PIL import Image

from diffuser_lab.cli.inspect import main as inspect_main
from diffuser_lab.cli.inspect import mcap_to_rrd
from diffuser_lab.config import default_config
from diffuser_lab.recording import make_hooks, schema
from diffuser_lab.recording.mcap_encode import (
    TOPIC_CALIBRATION,
    TOPIC_CAMERA_LABELS,
    TOPIC_LABELS,
    TOPIC_METRICS,
    TOPIC_TF,
    TOPIC_Z,
    UNLABELED_INDEX,
    _quaternion,
    camera_frame_id,
    decode_label_png,
    label_png,
    strided,
)
from diffuser_lab.recording.mcap_write import FOXGLOVE_LAYOUT, ITERATION_STEP_NS, log_time_ns
from diffuser_lab.runs.pipeline import run

FOXGLOVE = {c.DESCRIPTOR.full_name: c for c in (PointCloud, FrameTransform, CameraCalibration, CompressedImage)}
MAX_SIDE = 64  # the demo's 160 x 120 frames are strided by 3 to 54 x 40


@pytest.fixture(scope="module")
def fox_run(small_demo_scene, tmp_path_factory):
    """A small demo run recorded (both formats, images strided to 64 px), with the frames the
    recorders saw: {index: (K, T_cw, (H, W), labels)}."""
    d = tmp_path_factory.mktemp("fox")
    cfg = default_config(**{"solver.max_iter": 30, "record.interval": 10, "record.clouds": "all",
                            "record.max_image_side": MAX_SIDE})
    hooks = make_hooks(cfg, d)
    frames = {}
    on_frame = hooks.on_frame

    def keep(index, frame):
        lab = frame.labels if frame.labels is not None else np.argmax(frame.probs, axis=2)
        frames[index] = (np.array(frame.K), np.array(frame.T_cw), frame.shape, np.array(lab))
        on_frame(index, frame)

    hooks.on_frame = keep
    try:
        run(cfg, scene=small_demo_scene, hooks=hooks)
    finally:
        hooks.close()
    assert not hooks.files().get("errors")
    msgs = []  # (topic, schema, log_time, sequence, data), in file order
    with open(d / "run.mcap", "rb") as fh:
        for sch, ch, m in make_reader(fh).iter_messages(log_time_order=False):
            msgs.append((ch.topic, sch, m.log_time, m.sequence, m.data))
    return SimpleNamespace(dir=d, frames=frames, msgs=msgs, taxonomy=small_demo_scene.taxonomy)


def _by_topic(fox_run, topic):
    return [m for m in fox_run.msgs if m[0] == topic]


def test_every_foxglove_message_decodes_with_the_foxglove_schemas(fox_run):
    names = {sch.name for _, sch, *_ in fox_run.msgs if sch.name.startswith("foxglove.")}
    assert names == set(FOXGLOVE)
    for topic, sch, t, _, data in fox_run.msgs:
        if sch.name not in FOXGLOVE:
            continue
        cls = FOXGLOVE[sch.name]
        # the schema record is foxglove's own file (and its imports), as a FileDescriptorSet
        fds = descriptor_pb2.FileDescriptorSet.FromString(sch.data)
        want = descriptor_pb2.FileDescriptorProto()
        cls.DESCRIPTOR.file.CopyToProto(want)
        assert sch.encoding == "protobuf" and want in list(fds.file), topic
        msg = cls.FromString(data)
        assert msg.timestamp.ToNanoseconds() == t, topic  # the message stamp is its log time


def test_cameras_calibrations_images_and_transforms_match_the_frames(fox_run):
    n = len(fox_run.frames)
    assert n == 12 and sorted(fox_run.frames) == list(range(n))
    tfs = [FrameTransform.FromString(m[4]) for m in _by_topic(fox_run, TOPIC_TF)]
    cals = [CameraCalibration.FromString(m[4]) for m in _by_topic(fox_run, TOPIC_CALIBRATION)]
    imgs = [CompressedImage.FromString(m[4]) for m in _by_topic(fox_run, TOPIC_CAMERA_LABELS)]
    assert len(tfs) == len(cals) == len(imgs) == n
    pal = np.zeros((256, 3), np.uint8)
    pal[:fox_run.taxonomy.num_classes] = fox_run.taxonomy.colors
    pal[UNLABELED_INDEX] = 70
    for i, (tf, cal, img) in enumerate(zip(tfs, cals, imgs)):
        K, T_cw, (h, w), labels = fox_run.frames[i]
        frame = camera_frame_id(i)
        assert tf.parent_frame_id == "world" and tf.child_frame_id == cal.frame_id == img.frame_id == frame
        # the transform is the camera's pose: inv(T_cw)
        from scipy.spatial.transform import Rotation

        T_wc = np.eye(4)
        T_wc[:3, :3] = Rotation.from_quat([tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w]).as_matrix()
        T_wc[:3, 3] = tf.translation.x, tf.translation.y, tf.translation.z
        np.testing.assert_allclose(T_wc @ T_cw, np.eye(4), atol=1e-9)
        # calibration of the stored (strided) image
        s = int(np.ceil(max(h, w) / MAX_SIDE))
        assert s == 3 and (cal.width, cal.height) == (-(-w // s), -(-h // s))
        K_s = np.array(K, float)
        K_s[:2] /= s
        np.testing.assert_allclose(np.reshape(cal.K, (3, 3)), K_s)
        np.testing.assert_allclose(np.reshape(cal.P, (3, 4)), np.hstack([K_s, np.zeros((3, 1))]))
        # the palette PNG: pixels are the frame's class ids strided, the palette the taxonomy's colours
        assert img.format == "png"
        im = Image.open(io.BytesIO(img.data))
        assert im.mode == "P" and im.size == (cal.width, cal.height)
        want = np.where(labels[::s, ::s] < 0, UNLABELED_INDEX, labels[::s, ::s])
        np.testing.assert_array_equal(np.asarray(im), want)
        np.testing.assert_array_equal(np.reshape(im.getpalette()[:768], (256, 3)), pal)
        np.testing.assert_array_equal(decode_label_png(img.data, fox_run.taxonomy.colors), labels[::s, ::s])
    assert len({np.asarray(Image.open(io.BytesIO(im.data))).tobytes() for im in imgs}) > 1  # not one image


def test_log_times_order_the_cameras_then_the_iterations(fox_run):
    first = fox_run.msgs[0][2]
    cams = [(m[3], m[2]) for m in _by_topic(fox_run, TOPIC_CALIBRATION)]  # (camera index, time)
    assert [i for i, _ in cams] == list(range(len(cams)))
    assert all(t == log_time_ns(first, "camera", i) for i, t in cams)
    assert first < cams[0][1] and all(a[1] < b[1] for a, b in zip(cams, cams[1:]))
    per_topic = {topic: [(m[3], m[2]) for m in _by_topic(fox_run, topic)]  # (iteration, time)
                 for topic in (TOPIC_METRICS, TOPIC_LABELS, TOPIC_Z)}
    its = [it for it, _ in per_topic[TOPIC_METRICS]]
    assert its == [1, 10, 20, 30]
    for topic, rows in per_topic.items():
        assert [it for it, _ in rows] == its, topic
        times = [t for _, t in rows]
        assert times == [log_time_ns(first, "iteration", it, len(cams)) for it in its], topic
        assert times[0] > cams[-1][1]
        assert np.all(np.diff(times) == np.diff(its) * ITERATION_STEP_NS)  # 10 ms per iteration
        assert (times[0] - ITERATION_STEP_NS) % 10**9 == 0  # the diffusion starts on a whole second


def test_rerun_mcap_loader_orders_the_iterations_on_message_log_time(fox_run):
    from rerun.chunk import McapReader

    rows, images = [], False
    for ch in McapReader(fox_run.dir / "run.mcap").stream():
        rb = ch.to_record_batch()
        if ch.entity_path == TOPIC_METRICS and "message_log_time" in rb.schema.names:  # not the channel info
            times = rb.column("message_log_time").cast("int64").to_pylist()
            col = next(c for c in rb.schema.names if "IterationMetrics" in c)
            rows += [(t, m[0]["iteration"]) for t, m in zip(times, rb.column(col).to_pylist())]  # one per row
        if ch.entity_path == TOPIC_CAMERA_LABELS and "message_log_time" in rb.schema.names:
            assert "EncodedImage:blob" in rb.schema.names  # Rerun decodes the foxglove images too
            images = True
    rows.sort()
    assert [it for _, it in rows] == [1, 10, 20, 30] and images


def _rrd_cameras(path: Path) -> dict:
    """{(entity, column): values} of /world/cameras/** in an .rrd, read with rerun's reader."""
    from rerun.chunk import RrdReader

    out = {}
    for ch in RrdReader(path).stream():
        if ch.entity_path.startswith("/world/cameras/"):
            rb = ch.to_record_batch()
            for name in rb.schema.names:
                if name.startswith(("Pinhole:", "SegmentationImage:", "Transform3D:")):
                    out[(ch.entity_path, name)] = rb.column(name).to_pylist()
    return out


def test_relogged_rrd_has_the_label_images_of_the_live_one(fox_run, tmp_path):
    from rerun.chunk import RrdReader

    out = tmp_path / "replay.rrd"
    mcap_to_rrd(fox_run.dir / "run.mcap", out)
    live, replay = _rrd_cameras(fox_run.dir / "run.rrd"), _rrd_cameras(out)
    seg = [k for k in live if k[1] == "SegmentationImage:buffer"]
    assert len(seg) == len(fox_run.frames)
    assert live == replay  # label images, pinholes (of the strided images) and poses alike
    fmt = replay[("/world/cameras/0000/labels", "SegmentationImage:format")][0][0]
    assert (fmt["width"], fmt["height"]) == (54, 40)
    names = [r.get("RecordingInfo:name") for ch in RrdReader(out).stream() if ch.entity_path == "/__properties"
             for r in ch.to_record_batch().to_pylist()]
    assert any(n and "re-logged from run.mcap" in n[0] for n in names)


def test_layout_parses_and_names_topics_and_fields_in_the_file(fox_run, tmp_path):
    out = tmp_path / "layout.json"
    assert inspect_main([str(fox_run.dir), "--foxglove-layout", str(out)]) == 0
    assert out.read_bytes() == FOXGLOVE_LAYOUT.read_bytes()
    layout = json.loads(out.read_text())
    assert {"configById", "layout", "globalVariables", "userNodes", "playbackConfig"} <= set(layout)

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    ids = leaves(layout["layout"])
    assert sorted(ids) == sorted(layout["configById"]) and len(set(ids)) == len(ids)
    assert {i.split("!")[0] for i in ids} == {"3D", "Image", "Plot"}
    topics = {m[0] for m in fox_run.msgs}
    named, fields = set(), set()
    for pid, conf in layout["configById"].items():
        named |= set(conf.get("topics", {}))
        named |= {v for k, v in conf.get("imageMode", {}).items() if k.endswith("Topic")}
        named |= {t["cameraInfoTopic"] for t in conf.get("topics", {}).values() if "cameraInfoTopic" in t}
        for p in conf.get("paths", []) + ([conf["xAxisPath"]] if "xAxisPath" in conf else []):
            topic, field = p["value"].split(".")
            named.add(topic)
            fields.add(field)
    assert {TOPIC_LABELS, TOPIC_CALIBRATION, TOPIC_CAMERA_LABELS, TOPIC_METRICS} <= named <= topics
    assert fields <= set(schema.IterationMetrics.DESCRIPTOR.fields_by_name)
    assert {"miou", "n_changed", "residual", "iteration"} <= fields
    three_d = layout["configById"]["3D!diffusion"]
    assert three_d["topics"][TOPIC_LABELS]["visible"] and three_d["followTf"] == "world"


@pytest.mark.parametrize("n_classes", [20, 300])
def test_label_png_gives_the_class_ids_back(n_classes):
    rng = np.random.default_rng(n_classes)
    # distinct colours (the RGB fallback matches colours back to classes)
    colors = np.stack([np.arange(n_classes) % 256, np.arange(n_classes) // 256, np.full(n_classes, 9)], 1)
    labels = rng.integers(-1, n_classes, (37, 53)).astype(np.int16)
    data = label_png(labels, colors.astype(np.uint8))
    im = Image.open(io.BytesIO(data))
    assert im.size == (53, 37) and im.mode == ("P" if n_classes < 255 else "RGB")
    np.testing.assert_array_equal(np.asarray(im.convert("RGB")),
                                  np.vstack([colors, [[70, 70, 70]]]).astype(np.uint8)[labels])
    np.testing.assert_array_equal(decode_label_png(data, colors), labels)


def test_strided_is_run_rrds_stride_and_quaternions_are_scipys():
    from scipy.spatial.transform import Rotation

    from diffuser_lab.recording.rerun_log import RerunRecorder

    K = np.array([[200.0, 0, 159.5], [0, 210.0, 119.5], [0, 0, 1]])
    for side, shape in ((320, (240, 320)), (100, (240, 320)), (64, (120, 160)), (333, (1000, 7))):
        img = np.arange(np.prod(shape)).reshape(shape)
        got = strided(img, K, side)
        want = RerunRecorder._shrink(SimpleNamespace(max_image_side=side), img, K)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_allclose(got[1], want[1])
    R = np.concatenate([Rotation.random(200, random_state=0).as_matrix(),
                        Rotation.from_rotvec(np.pi * np.eye(3)).as_matrix(), np.eye(3)[None]])
    q = np.array([_quaternion(r) for r in R])
    np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), R, atol=1e-12)
    assert (q[:, 3] >= 0).all()


def test_a_camera_at_the_origin_keeps_its_translation():
    # proto3 leaves an all-zero sub-message out, which Rerun's MCAP loader reads as a null translation
    from diffuser_lab.recording.mcap_encode import camera_messages

    K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    msgs = dict(camera_messages(3, K, np.eye(4), (48, 64), None, None, 32, 5))
    tf = FrameTransform.FromString(msgs[TOPIC_TF].SerializeToString())
    assert tf.HasField("translation") and tf.rotation.w == 1.0 and tf.child_frame_id == "camera_0003"
    cal = msgs[TOPIC_CALIBRATION]
    assert (cal.width, cal.height) == (32, 24) and TOPIC_CAMERA_LABELS not in msgs  # no labels: no image
