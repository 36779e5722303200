"""diffuser_lab/data/arrays.py, the one .npy / .npz reader, and images.read_depth, the one depth reader:
what np.load gives for a good file (bit for bit, writable), one line naming the file and what was
expected for a bad one, and the run's inputs recorded by role."""
import io
import zipfile

import numpy as np
import pytest
from PIL import Image

from diffuser_lab.data import inputs
from diffuser_lab.data.arrays import check_array, open_npz, read_array
from diffuser_lab.data.images import image_complete, read_depth


def one_line(exc, path, *needles):
    text = str(exc.value)
    assert text.startswith(str(path)) and "\n" not in text, text
    for n in needles:
        assert n in text, text
    return text


def test_npy_and_npz_read_as_np_load_does(tmp_path):
    a = np.arange(24, dtype=">i4").reshape(2, 3, 4)
    f = np.asfortranarray(np.linspace(0, 1, 12, dtype=np.float16).reshape(3, 4))
    np.save(tmp_path / "a.npy", a)
    np.savez_compressed(tmp_path / "z.npz", f=f, names=np.array(["chair", "table"]))
    got = read_array(tmp_path / "a.npy", "array")
    assert got.dtype == a.dtype and got.flags.writeable
    np.testing.assert_array_equal(got, a)
    np.testing.assert_array_equal(read_array(tmp_path / "z.npz", "array", key="f"), f)
    np.testing.assert_array_equal(read_array(tmp_path / "z.npz", "array", key="absent"), f)  # the first member
    with open_npz(tmp_path / "z.npz", "a test file") as z:
        assert z.files == ["f", "names"] and "names" in z and "x" not in z
        assert z.read("names", ndim=1, kinds="SU").tolist() == ["chair", "table"]
    m = read_array(tmp_path / "a.npy", "array", mmap=True)
    assert isinstance(m, np.memmap) and not m.flags.writeable
    np.testing.assert_array_equal(m, a)


@pytest.mark.parametrize("expect,needle", [
    (dict(ndim=2), "features of shape (2, 3, 4) dtype >i4, expected 2-d"),
    (dict(kinds="f"), "expected an array floats"),
    (dict(shape=(2, None, 5)), "expected (2, *, 5)"),
    (dict(dtypes=(np.float16, np.float32), ndim=3), "expected 3-d (float16 or float32)"),
    (dict(ndim=3, kinds="f", expected="(h, w, D) floats"), "expected (h, w, D) floats"),
])
def test_what_the_caller_expects(tmp_path, expect, needle):
    p = tmp_path / "a.npy"
    np.save(p, np.zeros((2, 3, 4), ">i4"))
    with pytest.raises(ValueError) as exc:
        read_array(p, "features", **expect)
    one_line(exc, p, needle)
    assert check_array(np.zeros((2, 3)), "x", "y", ndim=(1, 2), kinds="f", shape=(2, None)).shape == (2, 3)


def _npy_bytes(arr, shape=None) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr)
    data = buf.getvalue()
    if shape is None:
        return data
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {**np.lib.format.header_data_from_array_1_0(arr), "shape": shape})
    return head.getvalue() + data[len(head.getvalue()):]


@pytest.mark.parametrize("case,needle", [
    ("lies", "header says shape (100000, 100000) of float32 = 40,000,000,000 bytes, the file holds 96"),
    ("short", "header says shape (2, 3) of float32 = 24 bytes, the file holds 20"),
    ("text", "not a .npy file"),
    ("object", "array of Python objects (object)"),
])
def test_a_bad_npy_is_one_line(tmp_path, case, needle):
    p = tmp_path / "a.npy"
    if case == "lies":
        p.write_bytes(_npy_bytes(np.zeros((4, 6), np.float32), (100_000, 100_000)))
    elif case == "short":
        p.write_bytes(_npy_bytes(np.zeros((2, 3), np.float32))[:-4])
    elif case == "text":
        p.write_text("0 1 2\n")
    else:
        np.save(p, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError) as exc:
        read_array(p, "array")
    one_line(exc, p, needle)


@pytest.mark.parametrize("case,needle", [
    ("absent", "no 'embeddings' array (has: names), expected a test file"),
    ("npy", "a single array, expected a test file"),
    ("text", "unreadable .npz (BadZipFile"),
    ("bomb", "[names]: says 200,000,000 bytes from"),
    ("lies", "[names]: header says shape (1000000,)"),
])
def test_a_bad_npz_is_one_line(tmp_path, case, needle):
    p = tmp_path / "q.npz"
    if case == "absent":
        np.savez(p, names=np.array(["a"]))
    elif case == "npy":
        p.write_bytes(_npy_bytes(np.zeros(3)))
    elif case == "text":
        p.write_text("names,embeddings\n")
    else:
        member = _npy_bytes(np.zeros(4, np.float32), (1_000_000,) if case == "lies" else None)
        with zipfile.ZipFile(p, "w", zipfile.ZIP_DEFLATED) as z:
            z.writestr("names.npy", member)
        if case == "bomb":  # the central directory's size of the member: more than deflate expands its bytes to
            data = bytearray(p.read_bytes())
            at = data.index(b"PK\x01\x02") + 24
            data[at:at + 4] = (200_000_000).to_bytes(4, "little")
            p.write_bytes(bytes(data))
    with pytest.raises(ValueError) as exc:
        with open_npz(p, "a test file") as z:
            z.read("names")
            z.read("embeddings")
    one_line(exc, p, needle)


def test_a_missing_file_names_itself(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"feature map .*nothing\.npy does not exist"):
        read_array(tmp_path / "nothing.npy", "feature map")
    with pytest.raises(FileNotFoundError, match=r"nothing\.npz does not exist"):
        with open_npz(tmp_path / "nothing.npz", "a query file"):
            pass


def test_the_file_is_recorded_as_an_input_of_its_role(tmp_path):
    np.save(tmp_path / "a.npy", np.ones(3))
    np.savez(tmp_path / "b.npz", x=np.ones(2))
    np.save(tmp_path / "c.npy", np.ones(2))
    with inputs.collecting() as c:
        read_array(tmp_path / "a.npy", "array", role="features")
        with open_npz(tmp_path / "b.npz", "a file", role="queries") as z:
            z.read("x")
        read_array(tmp_path / "c.npy", "array", role=None)  # a cache, a run's own output: not an input
    assert sorted((e.role, e.path.rsplit("/", 1)[1]) for e in c.rows()) == [("features", "a.npy"), ("queries", "b.npz")]


# --------------------------------------------------------------------------- the one depth reader

def test_depth_png_and_npy_metres_read_alike(tmp_path):
    mm = np.array([[0, 1000, 1234], [65535, 4500, 7]], np.uint16)
    Image.fromarray(mm).save(tmp_path / "d.png")
    metres = mm.astype(np.float32) / np.float32(1000)
    metres[1, 0] = np.nan  # no depth in either form
    np.save(tmp_path / "d.npy", metres)
    np.save(tmp_path / "d1.npy", metres[..., None])  # (H, W, 1)
    np.save(tmp_path / "mm.npy", mm.astype(np.int32))  # stored units, npy_unit metres each
    png = read_depth(tmp_path / "d.png", 1000.0, invalid=(0, 65535))
    assert png.dtype == np.float32 and png[1, 0] == 0 and png[0, 0] == 0
    np.testing.assert_array_equal(read_depth(tmp_path / "d.npy", 1000.0), png)
    np.testing.assert_array_equal(read_depth(tmp_path / "d1.npy", 1000.0), png)
    got = read_depth(tmp_path / "mm.npy", 1.0, npy_unit=0.001)
    np.testing.assert_allclose(np.delete(got.ravel(), 3), np.delete(png.ravel(), 3), rtol=1e-6)
    assert got[1, 0] == pytest.approx(65.535)  # an array has no raw "invalid" values: only <= 0, NaN, inf


@pytest.mark.parametrize("case,needle", [
    ("colour", "depth array of dtype float32 shape (2, 3, 3), expected (H, W) metres"),
    ("strings", "depth array of dtype <U1 shape (2, 3), expected (H, W) metres"),
    ("lies", "header says shape (50000, 50000)"),
    ("rgb_png", "depth image of dtype uint8 shape (2, 3, 3), expected single-channel 16-bit"),
])
def test_bad_depth_is_one_line(tmp_path, case, needle):
    p = tmp_path / ("d.png" if case == "rgb_png" else "d.npy")
    if case == "colour":
        np.save(p, np.ones((2, 3, 3), np.float32))
    elif case == "strings":
        np.save(p, np.full((2, 3), "a"))
    elif case == "lies":
        p.write_bytes(_npy_bytes(np.ones((2, 3), np.float32), (50_000, 50_000)))
    else:
        Image.fromarray(np.zeros((2, 3, 3), np.uint8)).save(p)
    with pytest.raises(ValueError) as exc:
        read_depth(p, 1000.0)
    one_line(exc, p, needle)


def test_a_npy_being_written_is_not_complete(tmp_path):
    data = _npy_bytes(np.ones((40, 50), np.float32))
    p = tmp_path / "frame-000000.depth.npy"
    p.write_bytes(data[:-100])
    assert not image_complete(p)
    p.write_bytes(data)
    assert image_complete(p)



def test_one_header_parsed_at_a_time(tmp_path, monkeypatch):
    """The frame loop reads ahead on every core, and numpy parses a header with ast.literal_eval,
    whose AST constructor in CPython 3.11 keeps its recursion depth in state the threads share (a
    full tests/data run once failed "SystemError: AST constructor recursion depth mismatch" on a
    probability file): the reader holds its lock while numpy parses (.npy and .npz members)."""
    from diffuser_lab.data import arrays

    seen = []
    parse = np.lib.format.read_array_header_1_0

    def watched(fh, *a, **k):
        seen.append(arrays._HEADER_LOCK.locked())
        return parse(fh, *a, **k)

    monkeypatch.setattr(np.lib.format, "read_array_header_1_0", watched)
    np.save(tmp_path / "a.npy", np.ones(3))
    np.savez(tmp_path / "b.npz", x=np.ones(2))
    read_array(tmp_path / "a.npy", "array", role=None)
    read_array(tmp_path / "b.npz", "array", role=None)
    assert seen == [True, True]
