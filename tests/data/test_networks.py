"""A network in the loop: predictions=model (a Python callable through Hydra) and predictions=onnx
(onnxruntime on the CPU), on the real 7-Scenes frames of ../shared/data; outputs mapped, resized
and cached on disk (a second run does not call the network).

The tiny models live in tests/toy_networks.py, a module the command line can name
(``predictions.model._target_=tests.toy_networks.grey_levels``).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import SHARED, compose
from toy_networks import CALLS, GREY_TO_SCANNET20, GreyWithDepth, soft_grey
from diffuser_lab.data.scene import IGNORE, SCANNET20

SEVEN = SHARED / "data" / "7scenes_sample"
needs_7scenes = pytest.mark.skipif(not (SEVEN / "camera-intrinsics.txt").is_file(),
                                   reason=f"real 7-Scenes sample absent: {SEVEN} not found")

# ------------------------------------------------------------------------------------ helpers

def scene_overrides(n_frames=5):
    return ["scene=rgbd_folder", f"scene.options.root={SEVEN}", f"scene.options.max_frames={n_frames}",
            "scene.options.cloud_voxel=0.05", "solver.max_iter=30"]


@pytest.fixture(scope="module")
def scene():
    from diffuser_lab.runs.pipeline import load_scene

    return load_scene(compose(*scene_overrides()).scene)


@pytest.fixture
def mapping_csv(tmp_path):
    p = tmp_path / "grey_to_scannet20.csv"
    p.write_text(GREY_TO_SCANNET20)
    return p


def frames_of(scene, *overrides):
    """The scene's frames with the configured predictions attached, and their stats."""
    from diffuser_lab.data.predictions import with_predictions

    cfg = compose(*scene_overrides(), *overrides)
    fr = with_predictions(scene.frames, cfg.predictions, scene.taxonomy, scene_name=scene.name)
    return [fr[i] for i in range(len(fr))], fr.stats


def npz_files(cache: Path) -> dict:
    return {p: p.stat().st_mtime_ns for p in sorted(cache.rglob("*.npz"))}


def tiny_onnx(path, weight, bias, *, head="softmax", hw=("H", "W"), nhwc=False):
    """A 1x1 Conv (3 -> C channels) segmentation network, NCHW float input of size ``hw``
    (symbolic = any), with ``head``: softmax (probabilities), none (logits) or argmax (ids);
    ``nhwc``: input and output (1, H, W, channels) instead (TensorFlow's layout)."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper, numpy_helper

    C = weight.shape[0]
    first = "image"
    nodes = []
    if nhwc:
        nodes.append(helper.make_node("Transpose", ["image"], ["nchw"], perm=[0, 3, 1, 2]))
        first = "nchw"
    nodes.append(helper.make_node("Conv", [first, "w", "b"], ["logits"], kernel_shape=[1, 1]))
    out, kind = "logits", TensorProto.FLOAT
    if head == "softmax":
        nodes.append(helper.make_node("Softmax", ["logits"], ["probs"], axis=1))
        out = "probs"
    elif head == "argmax":
        nodes.append(helper.make_node("ArgMax", ["logits"], ["ids"], axis=1, keepdims=0))
        out, kind = "ids", TensorProto.INT64
    shape_out = [1, *hw] if head == "argmax" else [1, C, *hw]
    if nhwc and head != "argmax":
        nodes.append(helper.make_node("Transpose", [out], ["out_nhwc"], perm=[0, 2, 3, 1]))
        out, shape_out = "out_nhwc", [1, *hw, C]
    graph = helper.make_graph(
        nodes, "tiny_seg", [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, *hw, 3] if nhwc else [1, 3, *hw])],
        [helper.make_tensor_value_info(out, kind, shape_out)],
        [numpy_helper.from_array(weight.reshape(C, 3, 1, 1).astype(np.float32), "w"),
         numpy_helper.from_array(bias.astype(np.float32), "b")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8  # readable by every onnxruntime of the last years
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


W4 = np.array([[3.0, -1.0, -1.0], [-1.0, 3.0, -1.0], [-1.0, -1.0, 3.0], [1.0, 1.0, 1.0]], np.float32)
B4 = np.array([0.0, 0.2, -0.1, 0.5], np.float32)
MEAN, STD = np.array([0.485, 0.456, 0.406], np.float32), np.array([0.229, 0.224, 0.225], np.float32)


def numpy_net(rgb, mean=MEAN, std=STD):
    """What tiny_onnx(W4, B4) computes: (H, W, 4) softmax probabilities."""
    x = (rgb.astype(np.float32) / 255.0 - mean) / std
    z = x @ W4.T + B4
    e = np.exp(z - z.max(axis=2, keepdims=True))
    return e / e.sum(axis=2, keepdims=True)


def map_columns(p):
    """Sum the 4 source columns into ScanNet-20 classes as GREY_TO_SCANNET20 says."""
    out = np.zeros(p.shape[:2] + (SCANNET20.num_classes,), np.float32)
    for src, name in enumerate(["chair", "wall", "floor"]):
        out[..., SCANNET20.names.index(name)] += p[..., src]
    return out


# ------------------------------------------------------------------------------- no data needed

def test_build_callable_kinds():
    from diffuser_lab.data.networks import build_callable

    rgb = np.full((4, 6, 3), 200, np.uint8)
    me = "toy_networks"
    fn = build_callable({"_target_": f"{me}.grey_levels", "cuts": [10, 20, 250]})  # bound, called per frame
    assert (fn(rgb) == 2).all()
    assert (build_callable({"_target_": f"{me}.make_grey", "cuts": [10, 20, 30]})(rgb) == 3).all()  # factory
    obj = build_callable({"_target_": f"{me}.GreyWithDepth", "near": 2.5})  # class: an instance
    assert isinstance(obj, GreyWithDepth) and obj.near == 2.5
    with pytest.raises(ValueError, match=r"predictions.model._target_=.*cannot import.*no attribute 'nothing'"):
        build_callable({"_target_": f"{me}.nothing"})
    with pytest.raises(ValueError, match=r"predictions.model._target_=no_such_pkg.fn: cannot import"):
        build_callable({"_target_": "no_such_pkg.fn"})
    with pytest.raises(ValueError, match="gave a float, expected a callable"):
        build_callable({"_target_": "builtins.float", "_args_": ["2"]})


def test_translate_ids_probs_and_errors(tmp_path):
    from diffuser_lab.data.mapping import load_mapping
    from diffuser_lab.data.networks import as_output, translate

    (tmp_path / "m.csv").write_text(GREY_TO_SCANNET20)
    m = load_mapping(tmp_path / "m.csv", SCANNET20)
    ids = np.array([[0, 1], [2, 3]], np.uint8)
    labels, probs, n_un = translate(as_output(ids, "t"), m, SCANNET20, (4, 4), "t")
    names = SCANNET20.names
    assert probs is None and labels.shape == (4, 4) and labels.dtype == np.int16 and n_un == 4
    assert labels[0, 0] == names.index("chair") and labels[0, 3] == names.index("wall")
    assert labels[3, 0] == names.index("floor") and labels[3, 3] == IGNORE
    p = as_output(np.random.default_rng(0).dirichlet(np.ones(4), size=(3, 5)).astype(np.float32), "t")
    _, mp, n_un = translate(p, m, SCANNET20, (3, 5), "t")
    np.testing.assert_allclose(mp, map_columns(p), atol=1e-6)  # columns summed, 'bright' dropped
    assert n_un == int((np.argmax(p, axis=2) == 3).sum())
    with pytest.raises(ValueError, match=r"label ids in \[0, 25\], expected scannet20 ids 0..19; pass predictions.mapping"):
        translate(as_output(np.array([[0, 25]]), "t"), None, SCANNET20, (1, 2), "t")
    with pytest.raises(ValueError, match="4 class scores per pixel, expected 20"):
        translate(p, None, SCANNET20, (3, 5), "t")
    with pytest.raises(ValueError, match="6 class scores per pixel, but mapping .* does not list source ids 4, 5"):
        translate(as_output(np.ones((2, 2, 6), np.float32), "t"), m, SCANNET20, (2, 2), "t")
    with pytest.raises(ValueError, match="negative values.*softmax"):
        as_output(-np.ones((2, 2, 4), np.float32), "t")
    with pytest.raises(ValueError, match=r"shape \(2, 2, 4\) dtype int64, expected \(H, W\) integer"):
        as_output(np.ones((2, 2, 4), np.int64), "t")


def test_resize_bilinear_matches_pillow():
    from PIL import Image

    from diffuser_lab.data.images import resize_bilinear

    a = np.random.default_rng(1).random((7, 9, 2)).astype(np.float32)
    r = resize_bilinear(a, (21, 27))
    for c in range(2):
        ref = np.asarray(Image.fromarray(a[..., c], "F").resize((27, 21), Image.BILINEAR))
        np.testing.assert_allclose(r[..., c], ref, atol=1e-5)
    assert resize_bilinear(a, (7, 9)) is a


def test_onnx_bad_files(tmp_path):
    from diffuser_lab.config import OnnxConfig
    from diffuser_lab.data.networks import OnnxModel, onnx_key

    with pytest.raises(FileNotFoundError, match=r"predictions.onnx.path=.*nothing.onnx does not exist"):
        onnx_key(OnnxConfig(path=str(tmp_path / "nothing.onnx")))
    pytest.importorskip("onnxruntime")
    (tmp_path / "junk.onnx").write_bytes(b"not a graph")
    with pytest.raises(ValueError, match=r"predictions.onnx.path=.*junk.onnx: not a loadable ONNX model"):
        OnnxModel(OnnxConfig(path=str(tmp_path / "junk.onnx")))
    net = tiny_onnx(tmp_path / "fixed.onnx", W4, B4, hw=(12, 16))
    with pytest.raises(ValueError, match=r"predictions.onnx.input_size=\[10, 10\]: .* fixed at \[1, 3, 12, 16\]"):
        OnnxModel(OnnxConfig(path=str(net), input_size=[10, 10]))
    with pytest.raises(ValueError, match="predictions.onnx.output_name=nope: the graph's outputs are probs"):
        OnnxModel(OnnxConfig(path=str(net), output_name="nope"))


def test_cache_keys():
    from diffuser_lab.data.networks import model_key

    k = model_key({"_target_": "a.b", "x": 1}, False)[0]
    assert k == model_key({"x": 1, "_target_": "a.b"}, False)[0]  # the order of kwargs does not matter
    assert len({k, model_key({"_target_": "a.b", "x": 2}, False)[0], model_key({"_target_": "a.b", "x": 1}, True)[0],
                model_key({"_target_": "a.c", "x": 1}, False)[0]}) == 4


def test_the_cache_reads_back_bit_for_bit_and_a_damaged_file_is_computed_again(tmp_path):
    """The network cache through the one array reader (data/arrays.py): ids, probabilities and a feature
    map come back as they were saved; a torn, foreign or lying file reads as absent (computed again and
    replaced), never a traceback or a header's allocation."""
    import io
    import zipfile

    from diffuser_lab.data.networks import _DiskCache

    cache = _DiskCache(str(tmp_path), "k", {"source": "test"})
    rng = np.random.default_rng(0)
    outs = {"ids": rng.integers(-1, 300, (6, 8)), "probs": rng.random((6, 8, 4)).astype(np.float32),
            "features": rng.random((3, 4, 16)).astype(np.float16)}
    for name, out in outs.items():
        p = cache.path("scene", name, "0" * 16)
        cache.save(p, out)
        got = cache.load(p)
        want = out.astype(np.float16).astype(np.float32) if name == "probs" else out
        assert got.dtype == want.dtype and np.array_equal(got, want), name
    p = cache.path("scene", "ids", "0" * 16)
    good = p.read_bytes()
    buf = io.BytesIO()
    head = np.lib.format.header_data_from_array_1_0(np.zeros((6, 8), np.int16))
    np.lib.format.write_array_header_1_0(buf, {**head, "shape": (60_000, 80_000)})
    for bad in (good[: len(good) // 2], b"not a zip", np.zeros(3).tobytes()):
        p.write_bytes(bad)
        assert cache.load(p) is None
    with zipfile.ZipFile(p, "w") as z:  # a member whose header says 4.8e9 int16 in 96 bytes
        z.writestr("ids.npy", buf.getvalue() + b"\0" * 96)
    assert cache.load(p) is None
    np.savez(p, ids=np.zeros((2, 3, 4), np.int16))  # another shape: 2-d ids expected
    assert cache.load(p) is None


@pytest.mark.parametrize("args,needle", [
    (["predictions=model"], "predictions.model._target_ is required"),
    (["predictions=onnx"], "predictions.onnx.path is required"),
    (["predictions=onnx", "predictions.onnx.path=x.onnx", "predictions.onnx.std=[1,0,1]"], "predictions.onnx.std"),
    (["predictions=onnx", "predictions.onnx.path=x.onnx", "predictions.onnx.layout=nhcw"], "predictions.onnx.layout"),
])
def test_config_errors_at_start_up(args, needle):
    from conftest import run_cli

    p = run_cli(*args)
    assert p.returncode == 2 and needle in p.stderr and p.stderr.count("\n") == 1, p.stderr


# -------------------------------------------------------------------------- real 7-Scenes frames

@pytest.mark.slow
@needs_7scenes
def test_model_ids_run_cached_and_reused(scene, mapping_csv, tmp_path):
    from diffuser_lab.runs.pipeline import run

    cache = tmp_path / "cache"
    ov = [*scene_overrides(), "predictions=model", "predictions.model._target_=toy_networks.grey_levels",
          f"predictions.mapping={mapping_csv}", f"predictions.cache_dir={cache}"]
    n0 = CALLS["n"]
    first = run(compose(*ov), scene=scene)
    assert CALLS["n"] - n0 == 5 and first.predictions_stats["model_calls"] == 5
    assert first.metrics is None and first.predictions_2d is None  # 7-Scenes has no labels: nothing to score
    files = npz_files(cache)
    assert len(files) == 5 and all(p.parent.name == scene.name for p in files)
    ident = json.loads(next(cache.glob("*/model.json")).read_text())
    assert ident["model"]["_target_"].endswith(".grey_levels")
    labelled = first.labels[first.labels != IGNORE]
    assert labelled.size > 0.9 * scene.n_points
    assert set(np.unique(labelled)) <= {SCANNET20.names.index(n) for n in ("chair", "wall", "floor")}

    again = run(compose(*ov, "graph.k=12"), scene=scene)  # a sweep over graph parameters: the network once
    assert CALLS["n"] - n0 == 5 and again.predictions_stats["cached_frames"] == 5
    assert npz_files(cache) == files  # read, not rewritten
    np.testing.assert_array_equal(run(compose(*ov), scene=scene).labels, first.labels)  # cached = fresh

    _, st = frames_of(scene, *ov[len(scene_overrides()):], "+predictions.model.cuts=[50,100,200]")
    assert st["model_calls"] == 5 and CALLS["n"] - n0 == 10  # new kwargs: a new cache entry
    assert len(list(cache.glob("*/model.json"))) == 2
    _, st = frames_of(scene, *ov[len(scene_overrides()):-1], "predictions.cache_dir=null")
    _, st = frames_of(scene, *ov[len(scene_overrides()):-1], "predictions.cache_dir=null")
    assert st["model_calls"] == 5 and st["cache"] is None and CALLS["n"] - n0 == 20  # cache off: runs each time


@needs_7scenes
def test_model_probabilities_resized_and_mapped(scene, mapping_csv, tmp_path):
    from diffuser_lab.data.images import resize_bilinear

    ov = ["predictions=model", "predictions.model._target_=toy_networks.soft_grey",
          f"predictions.mapping={mapping_csv}", f"predictions.cache_dir={tmp_path / 'c'}"]
    frames, st = frames_of(scene, *ov)
    assert st["probability_frames"] == 5 and st["model_calls"] == 5
    f = frames[2]
    assert f.labels is None and f.probs.shape == f.shape + (SCANNET20.num_classes,) and f.probs.dtype == np.float32
    raw = soft_grey(f.rgb).astype(np.float16).astype(np.float32)  # the cache keeps float16: so does the run
    np.testing.assert_allclose(f.probs, resize_bilinear(map_columns(raw), f.shape), atol=1e-6)
    cached, st = frames_of(scene, *ov)
    assert st["cached_frames"] == 5 and st["model_calls"] == 0
    np.testing.assert_array_equal(cached[2].probs, f.probs)


@needs_7scenes
def test_model_class_with_depth(scene, tmp_path):
    from diffuser_lab.data.networks import build_callable
    from diffuser_lab.data.predictions import with_predictions

    cfg = compose(*scene_overrides(), "predictions=model", "predictions.model._target_=toy_networks.GreyWithDepth",
                  "+predictions.model.near=1.2", "predictions.pass_depth=true", f"predictions.cache_dir={tmp_path}")
    fr = with_predictions(scene.frames, cfg.predictions, scene.taxonomy, scene_name=scene.name)
    f = fr[1]
    model = fr.fn._model  # built at the first frame, kept for the next ones
    assert isinstance(model, GreyWithDepth) and model.near == 1.2
    np.testing.assert_array_equal(model.depths[0], scene.frames[1].depth)
    near = (f.depth > 0) & (f.depth < 1.2)
    assert near.any() and (f.labels[near] == 3).all()  # no mapping: the model's ids are ScanNet-20 ids
    assert isinstance(build_callable(dict(cfg.predictions.model)), GreyWithDepth)


@pytest.mark.slow
@needs_7scenes
def test_onnx_probabilities_cached_and_keyed(scene, mapping_csv, tmp_path):
    pytest.importorskip("onnxruntime")
    net = tiny_onnx(tmp_path / "tiny.onnx", W4, B4)
    cache = tmp_path / "cache"
    ov = ["predictions=onnx", f"predictions.onnx.path={net}", "predictions.onnx.output=probs",
          f"predictions.mapping={mapping_csv}", f"predictions.cache_dir={cache}"]
    frames, st = frames_of(scene, *ov)
    assert st["model_calls"] == 5 and st["probability_frames"] == 5
    for f in frames[:2]:
        np.testing.assert_allclose(f.probs, map_columns(numpy_net(f.rgb)), atol=2e-3)  # float16-rounded
    files = npz_files(cache)
    assert len(files) == 5
    again, st = frames_of(scene, *ov)
    assert st["model_calls"] == 0 and st["cached_frames"] == 5 and npz_files(cache) == files
    np.testing.assert_array_equal(again[0].probs, frames[0].probs)
    _, st = frames_of(scene, *ov, "predictions.onnx.mean=[0.5,0.5,0.5]")  # preprocessing is in the key
    assert st["model_calls"] == 5 and len(npz_files(cache)) == 10
    tiny_onnx(net, W4, B4 * 0.5)  # so is the file's content
    _, st = frames_of(scene, *ov)
    assert st["model_calls"] == 5 and len(npz_files(cache)) == 15


@needs_7scenes
def test_onnx_fixed_size_logits_ids_and_a_run(scene, mapping_csv, tmp_path):
    pytest.importorskip("onnxruntime")
    from diffuser_lab.runs.pipeline import run

    common = [f"predictions.mapping={mapping_csv}", f"predictions.cache_dir={tmp_path / 'c'}"]
    soft = tiny_onnx(tmp_path / "soft.onnx", W4, B4, hw=(120, 160))
    logits = tiny_onnx(tmp_path / "logits.onnx", W4, B4, head="none", hw=(120, 160))
    ids = tiny_onnx(tmp_path / "ids.onnx", W4, B4, head="argmax", hw=(120, 160))
    fp, _ = frames_of(scene, "predictions=onnx", f"predictions.onnx.path={soft}", "predictions.onnx.output=probs", *common)
    fl, _ = frames_of(scene, "predictions=onnx", f"predictions.onnx.path={logits}", *common)  # softmax here
    fi, st = frames_of(scene, "predictions=onnx", f"predictions.onnx.path={ids}", "predictions.onnx.output=ids", *common)
    assert fp[0].probs.shape[:2] == fp[0].shape == (480, 640)  # 120 x 160 outputs resized to the depth's size
    np.testing.assert_allclose(fl[0].probs, fp[0].probs, atol=2e-3)
    assert st["label_frames"] == 5 and fi[0].labels.shape == (480, 640)
    # ids from the graph's argmax = argmax of its probabilities (but where 'bright' wins: ignore)
    from PIL import Image

    small = np.asarray(Image.fromarray(scene.frames[0].rgb).resize((160, 120), Image.BILINEAR))
    src = np.argmax(numpy_net(small), axis=2)
    lut = np.array([SCANNET20.names.index(n) for n in ("chair", "wall", "floor")] + [IGNORE])
    from diffuser_lab.data.images import resize_nearest

    assert (fi[0].labels == resize_nearest(lut[src], (480, 640))).mean() > 0.999
    res = run(compose(*scene_overrides(), "predictions=onnx", f"predictions.onnx.path={soft}",
                      "predictions.onnx.output=probs", *common), scene=scene)
    assert res.predictions_stats["cached_frames"] == 5 and (res.labels != IGNORE).mean() > 0.9


@needs_7scenes
@pytest.mark.slow
def test_cli_model_end_to_end(mapping_csv, tmp_path):
    from conftest import run_cli

    args = [*scene_overrides(3), "predictions=model", "predictions.model._target_=tests.toy_networks.grey_levels",
            f"predictions.mapping={mapping_csv}", f"predictions.cache_dir={tmp_path / 'cache'}", "record=off"]
    out = []
    for k in range(2):
        p = run_cli(*args, f"hydra.run.dir={tmp_path / f'run{k}'}")
        assert p.returncode == 0, p.stderr
        out.append((p.stdout, json.loads((tmp_path / f"run{k}" / "summary.json").read_text())))
    (s0, j0), (s1, j1) = out
    assert "no ground truth: no mIoU; diffuser labelled" in s0 and "3 frames run, 0 from cache" in s0
    assert "0 frames run, 3 from cache" in s1
    assert j0["metrics"] is None and j0["status"] == "ok" and j1["predictions_stats"]["cached_frames"] == 3
    assert np.array_equal(np.load(tmp_path / "run0" / "labels.npy"), np.load(tmp_path / "run1" / "labels.npy"))



@needs_7scenes
def test_onnx_nhwc_bgr(scene, mapping_csv, tmp_path):
    pytest.importorskip("onnxruntime")
    net = tiny_onnx(tmp_path / "tf.onnx", W4, B4, nhwc=True)
    mean, std = [0.4, 0.45, 0.5], [0.25, 0.2, 0.3]  # in the network's (BGR) order
    frames, st = frames_of(scene, "predictions=onnx", f"predictions.onnx.path={net}", "predictions.onnx.output=probs",
                           "predictions.onnx.layout=nhwc", "predictions.onnx.output_layout=nhwc",
                           "predictions.onnx.channels=bgr", f"predictions.onnx.mean={mean}",
                           f"predictions.onnx.std={std}", f"predictions.mapping={mapping_csv}",
                           f"predictions.cache_dir={tmp_path / 'c'}")
    assert st["model_calls"] == 5
    f = frames[3]
    ref = numpy_net(f.rgb[..., ::-1], np.array(mean, np.float32), np.array(std, np.float32))
    np.testing.assert_allclose(f.probs, map_columns(ref), atol=2e-3)


@needs_7scenes
def test_features_of_a_callable_and_of_an_onnx_network_cached_per_frame(scene, tmp_path):
    """predictions=features with embeddings=model / onnx: the network's (D, h, w) output is the frame's
    feature map (float16, as cached), a second run reads the cache, the labels come from the queries."""
    from diffuser_lab.data.embeddings import write_queries
    from diffuser_lab.runs.pipeline import run
    from toy_networks import grey_embedding_queries

    names = ["chair", "wall", "floor", "table"]
    queries = write_queries(tmp_path / "q.npz", names, grey_embedding_queries(names))
    cache = tmp_path / "cache"
    ov = [*scene_overrides(), "predictions=features_model", "predictions.model._target_=toy_networks.grey_embeddings",
          f"predictions.queries={queries}",
          f"predictions.cache_dir={cache}"]
    frames, st = frames_of(scene, *ov[len(scene_overrides()):])
    f0 = frames[0]
    assert f0.features.dtype == np.float16 and f0.features.shape[2] == 16 and f0.labels is None
    assert f0.features.shape[:2] == (-(-f0.shape[0] // 4), -(-f0.shape[1] // 4))
    n0 = CALLS["n"]
    res = run(compose(*ov), scene=scene)
    assert CALLS["n"] == n0 and res.predictions_stats["cached_frames"] == 5  # all from the cache
    labelled = res.labels[res.labels != IGNORE]
    assert labelled.size > 0.9 * scene.n_points
    assert set(np.unique(labelled)) <= {SCANNET20.names.index(n) for n in names}

    W8 = np.concatenate([W4, -W4]) * 0.5
    path = tiny_onnx(tmp_path / "feat.onnx", W8, np.zeros(8, np.float32), head="none")
    frames, st = frames_of(scene, "predictions=features_onnx", f"predictions.onnx.path={path}",
                           f"predictions.cache_dir={cache}", f"predictions.queries={queries}")
    fmap = frames[0].features
    assert fmap.shape == frames[0].shape + (8,) and fmap.dtype == np.float16 and st["model_calls"] == 5
    rgb = frames[0].rgb.astype(np.float32) / 255.0
    want = ((rgb - MEAN) / STD) @ W8.T
    np.testing.assert_allclose(fmap.astype(np.float32), want, rtol=2e-3, atol=2e-3)
