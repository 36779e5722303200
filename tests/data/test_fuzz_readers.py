"""Bounded fuzzing of the file readers: malformed PLY headers, truncated PNGs, pose and
intrinsics files with text or wrong shapes, mapping tables, empty folders. Every input either
reads or raises ValueError / FileNotFoundError with a message naming the file: never another
exception, a hang or a crash of the interpreter."""
import io
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from bounded import Hung, bounded

from diffuser_lab.data.mapping import load_mapping
from diffuser_lab.data.images import read_depth_png, read_label_png
from diffuser_lab.data.scene import SCANNET20
from diffuser_lab.data.clouds import read_point_cloud_ply
from diffuser_lab.data.intrinsics import read_intrinsics
from diffuser_lab.data.meshes import read_labelled_mesh
from diffuser_lab.data.poses import read_pose_c2w
from diffuser_lab.data.sources.rgbd_folder import load_rgbd_folder

# a hang is a failure: every case runs under bounded()'s alarm (a hypothesis deadline is checked only
# after the call returns, so it never stops one that does not)
FUZZ = settings(max_examples=int(os.environ.get("DIFFUSER_FUZZ_EXAMPLES", 40)), deadline=None,  # deeper: DIFFUSER_FUZZ_EXAMPLES=2000
                suppress_health_check=[HealthCheck.function_scoped_fixture])
CLEAR = (ValueError, FileNotFoundError)

PLY_LINES = ["ply", "format ascii 1.0", "format binary_little_endian 1.0", "format binary_big_endian 1.0",
             "element vertex 3", "element vertex -1", "element vertex 999999999999", "element face 1",
             "property float x", "property float y", "property float z", "property uchar label",
             "property list uchar int vertex_indices", "property double", "comment x", "end_header",
             "0 0 0", "1 2", "nan nan nan", "3 0 1 2", "garbage \x00\xff"]


def _check(reader, data: bytes, suffix: str, seconds: float = 5.0):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"f{suffix}"
        path.write_bytes(data)
        try:
            with bounded(seconds):
                reader(path)
        except (Hung, MemoryError) as exc:
            raise AssertionError(f"{path.name}: {type(exc).__name__}: {exc}") from exc
        except CLEAR as exc:
            assert str(path) in str(exc) or path.name in str(exc), str(exc)
            assert "\n" not in str(exc).strip()


@FUZZ
@given(st.lists(st.sampled_from(PLY_LINES), max_size=12), st.binary(max_size=64))
def test_ply_readers(lines, tail):
    data = ("\n".join(lines) + "\n").encode("latin-1") + tail
    _check(read_point_cloud_ply, data, ".ply")
    _check(read_labelled_mesh, data, ".ply")


def _png_bytes(rng_seed: int, mode: str) -> bytes:
    rng = np.random.default_rng(rng_seed)
    arr = rng.integers(0, 255, (12, 16)).astype(np.uint16 if mode == "I;16" else np.uint8)
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="PNG")
    return buf.getvalue()


@FUZZ
@given(st.integers(0, 10_000), st.sampled_from(["I;16", "L"]), st.floats(0.0, 1.0), st.binary(max_size=16))
def test_truncated_or_corrupt_pngs(seed, mode, cut, noise):
    data = _png_bytes(seed, mode)
    data = data[: int(len(data) * cut)] + noise  # truncated in the middle, junk appended
    _check(lambda p: read_depth_png(p, 1000.0), data, ".png")
    _check(read_label_png, data, ".png")


@FUZZ
@given(st.lists(st.lists(st.sampled_from(["1", "0", "-1", "0.5", "nan", "inf", "x", "1e400", ""]), max_size=5),
                max_size=5))
def test_pose_and_intrinsics_text(rows):
    data = "\n".join(" ".join(r) for r in rows).encode()
    _check(read_pose_c2w, data, ".txt")
    _check(read_intrinsics, data, ".txt")


@FUZZ
@given(st.lists(st.tuples(st.sampled_from(["0", "1", "2", "-3", "x", "1.5", "99999999999"]),
                          st.sampled_from(["wall", "", "foo"]),
                          st.sampled_from(["wall", "floor", "ignore", "", "nonsense", "chair,extra"])), max_size=6),
       st.booleans())
def test_mapping_tables(rows, header):
    text = ("source_id,source_name,target\n" if header else "") + "".join(f"{a},{b},{c}\n" for a, b, c in rows)
    _check(lambda p: load_mapping(str(p), SCANNET20), text.encode(), ".csv")


def _arrays_bytes(kind: str, shape: tuple, dtype: str) -> bytes:
    """A .npy of ``shape`` x ``dtype`` (a float16 (h, w, D) feature map, an (H, W) depth, strings), or a
    .npz of it as the query set's ``names`` and ``embeddings`` and the feature map's ``features``."""
    arr = np.zeros(shape, dtype)
    buf = io.BytesIO()
    if kind == "npy":
        np.save(buf, arr)
    else:
        np.savez_compressed(buf, names=np.array(["a", "b"]), embeddings=arr, features=arr)
    return buf.getvalue()


ARRAY_SHAPES = st.sampled_from([(2, 3), (4, 5, 6), (2, 4), (0,), (3, 2, 1)])


@FUZZ
@given(st.sampled_from(["npy", "npz"]), ARRAY_SHAPES, st.sampled_from(["<f2", "<f4", ">f8", "<i4", "<U2", "|b1"]),
       st.integers(0, 400), st.binary(max_size=16), st.floats(0.0, 1.0))
def test_arrays_damaged_anywhere(kind, shape, dtype, at, junk, cut):
    """The one array reader and its users (a feature map, a query set, a depth array): a file of any
    shape or dtype, bytes overwritten or cut short (a header, a zip directory), reads or fails in one
    line naming the file."""
    from diffuser_lab.data.arrays import open_npz, read_array
    from diffuser_lab.data.embeddings import load_queries
    from diffuser_lab.data.images import read_depth
    from diffuser_lab.data.prediction_files import load_feature_prediction

    data = bytearray(_arrays_bytes(kind, shape, dtype))
    data[at:at + len(junk)] = junk
    data = bytes(data[: max(1, int(len(data) * cut))] if cut < 0.5 else data)
    suffix = f".{kind}"

    def every_member(p):
        with open_npz(p, "a test file") as z:
            return [z.read(n) for n in z.files]

    _check(lambda p: read_array(p, "array", ndim=2, kinds="f"), data, suffix)
    _check(lambda p: read_array(p, "array", mmap=True), data, suffix)
    _check(load_feature_prediction, data, suffix)
    _check(lambda p: read_depth(p, 1000.0), data, suffix)
    if kind == "npz":
        _check(every_member, data, suffix)
        _check(load_queries, data, suffix)


def test_empty_folders(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist|no frame-XXXXXX.depth.png"):
        load_rgbd_folder(tmp_path)
    (tmp_path / "camera-intrinsics.txt").write_text("")
    with pytest.raises(CLEAR):
        load_rgbd_folder(tmp_path)


def test_a_reader_that_hangs_fails_the_check():
    """The alarm stops a reader that does not return (a deadline would wait for it): a failure."""
    import time

    t0 = time.perf_counter()
    with pytest.raises(AssertionError, match="Hung: a reader ran over 0.2 s"):
        _check(lambda p: time.sleep(30), b"x", ".txt", seconds=0.2)
    assert time.perf_counter() - t0 < 10
