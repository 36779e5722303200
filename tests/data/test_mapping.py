"""Class mappings (diffuser_lab.data.mapping) and 2D prediction files (diffuser_lab.data.prediction_files)."""
import numpy as np
import pytest
from PIL import Image

from diffuser_lab.data.mapping import identity_mapping, load_mapping, shipped_mappings
from diffuser_lab.data.prediction_files import (
    find_prediction,
    load_label_prediction,
    load_probability_prediction,
)
from diffuser_lab.data.images import resize_nearest
from diffuser_lab.data.scene import IGNORE, SCANNET20, SCANNET20_NYU40_IDS

WALL, C = SCANNET20.names.index("wall"), SCANNET20.num_classes


@pytest.fixture(scope="module")
def nyu():
    return load_mapping("nyu40_to_scannet20", SCANNET20)


def test_nyu40_to_scannet20(nyu):
    assert "nyu40_to_scannet20" in shipped_mappings() and nyu.target is SCANNET20
    assert nyu.lut.dtype == np.int16 and nyu.num_source == 41
    assert nyu.source_names[1] == "wall" and nyu.source_names[40] == "otherprop"
    kept = np.array(SCANNET20_NYU40_IDS)
    mapped, n_unmapped = nyu.apply(kept)
    np.testing.assert_array_equal(mapped, np.arange(C))  # kept ids in benchmark order
    assert n_unmapped == 0
    ids = np.array([[1, 40, 0], [39, 24, 13]], np.uint16)
    mapped, n_unmapped = nyu.apply(ids)
    assert mapped.shape == ids.shape and mapped.dtype == np.int16
    np.testing.assert_array_equal(mapped, [[WALL, IGNORE, IGNORE],
                                           [SCANNET20.names.index("otherfurniture"),
                                            SCANNET20.names.index("refrigerator"), IGNORE]])
    assert n_unmapped == 3  # otherprop, unannotated, blinds
    # Every id that is not one of the 20 kept ones is ignored.
    others = np.setdiff1d(np.arange(41), kept)
    assert (nyu.apply(others)[0] == IGNORE).all() and nyu.apply(others)[1] == others.size


def test_ids_outside_table_raise(nyu):
    with pytest.raises(ValueError, match=r"\[41, 255\].*nyu40_to_scannet20\.csv") as e:
        nyu.apply(np.array([1, 41, 255, 41]))
    assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match=r"\[-1\]"):
        nyu.apply(np.array([-1, 2]))


def _csv(tmp_path, body, name="m.csv"):
    p = tmp_path / name
    p.write_text("# test mapping\nsource_id,source_name,target\n" + body)
    return p


def test_bad_csvs_refused(tmp_path):
    p = _csv(tmp_path, "0,void,\n1,wall,wall\n1,building,wall\n")
    with pytest.raises(ValueError, match=r"m\.csv:5: duplicate source_id 1") as e:
        load_mapping(p, SCANNET20)
    assert "\n" not in str(e.value)
    p = _csv(tmp_path, "0,road,road\n")
    with pytest.raises(ValueError, match=r"m\.csv:3: unknown target class 'road'.*valid: wall, floor"):
        load_mapping(p, SCANNET20)
    p = _csv(tmp_path, "0,void\n")
    with pytest.raises(ValueError, match=r"m\.csv:3: malformed row"):
        load_mapping(p, SCANNET20)
    p = _csv(tmp_path, "x,void,ignore\n")
    with pytest.raises(ValueError, match=r"m\.csv:3: source_id 'x'"):
        load_mapping(p, SCANNET20)
    (tmp_path / "h.csv").write_text("id,name\n0,a\n")
    with pytest.raises(ValueError, match="header"):
        load_mapping(tmp_path / "h.csv", SCANNET20)
    with pytest.raises(FileNotFoundError, match="no shipped class mapping named 'nope'"):
        load_mapping("nope", SCANNET20)


def test_custom_csv_with_gaps_and_identity(tmp_path):
    # Cityscapes-like: ids 0, 2, 7 listed; 1 is a gap (outside the table); names case-insensitive.
    m = load_mapping(_csv(tmp_path, "0,road,Floor\n2,building,WALL\n7,sky,ignore\n"), SCANNET20)
    np.testing.assert_array_equal(m.apply(np.array([0, 2, 7]))[0], [1, WALL, IGNORE])
    with pytest.raises(ValueError, match=r"\[1\]"):
        m.apply(np.array([1]))
    ident = identity_mapping(SCANNET20)
    np.testing.assert_array_equal(ident.apply(np.arange(C))[0], np.arange(C))
    with pytest.raises(ValueError, match=r"\[20\]"):
        ident.apply(np.array([20]))
    np.testing.assert_array_equal(load_mapping("scannet20", SCANNET20).lut, np.arange(C))


# ------------------------------------------------------------------ prediction files

def test_label_prediction_resized_and_mapped(tmp_path, nyu):
    small = np.array([[1, 40], [0, 5]], np.uint16)
    big = np.kron(small, np.ones((4, 5), np.uint16))  # (8, 10) prediction for a (4, 5) frame
    Image.fromarray(big).save(tmp_path / "f0.png")
    labels, n_unmapped = load_label_prediction(tmp_path / "f0.png", nyu, (4, 5))
    assert labels.shape == (4, 5) and labels.dtype == np.int16
    np.testing.assert_array_equal(labels, resize_nearest(nyu.apply(big)[0], (4, 5)))
    assert labels[0, 0] == WALL and labels[3, 4] == SCANNET20.names.index("chair") and labels[0, 4] == IGNORE
    assert n_unmapped == np.count_nonzero(labels == IGNORE)
    Image.fromarray(np.array([[3, 7]], np.uint8)).save(tmp_path / "f1.png")  # 8-bit, taxonomy ids
    lab, n = load_label_prediction(tmp_path / "f1.png", None, (1, 2))
    np.testing.assert_array_equal(lab, [[3, 7]])
    assert n == 0
    Image.fromarray(np.array([[77]], np.uint8)).save(tmp_path / "f2.png")
    with pytest.raises(ValueError, match=r"f2\.png.*\[77\]"):
        load_label_prediction(tmp_path / "f2.png", nyu, (1, 1))


def test_resize_nearest_is_pixel_centre_aligned():
    img = np.arange(10)[None].repeat(2, 0)
    np.testing.assert_array_equal(resize_nearest(img, (1, 4)), [[1, 3, 6, 8]])  # floor((c+.5)*2.5)
    pil = np.asarray(Image.fromarray(img.astype(np.uint8)).resize((4, 1), Image.NEAREST))
    np.testing.assert_array_equal(resize_nearest(img, (1, 4)), pil)


def test_probability_prediction(tmp_path):
    rng = np.random.default_rng(0)
    hwc = rng.random((6, 8, C)).astype(np.float32)
    np.save(tmp_path / "chw.npy", np.moveaxis(hwc, 2, 0))  # (C, H, W) -> transposed
    np.testing.assert_array_equal(load_probability_prediction(tmp_path / "chw.npy", C, (6, 8)), hwc)
    np.savez(tmp_path / "p.npz", other=np.zeros(3), probs=hwc)
    out = load_probability_prediction(tmp_path / "p.npz", C, (3, 4))  # downsized by 2
    assert out.shape == (3, 4, C) and out.dtype == np.float32
    ref = np.asarray(Image.fromarray(hwc[..., 3], "F").resize((4, 3), Image.BILINEAR))
    np.testing.assert_allclose(out[..., 3], ref, atol=1e-6)  # probabilities bilinear (Pillow's), as a network's
    unit = hwc / hwc.sum(2, keepdims=True)
    np.savez(tmp_path / "u.npz", probs=unit)
    np.testing.assert_allclose(load_probability_prediction(tmp_path / "u.npz", C, (3, 4)).sum(2), 1.0, atol=1e-5)
    np.save(tmp_path / "bad.npy", rng.random((6, 8, 13)))
    with pytest.raises(ValueError, match=r"bad\.npy.*no axis of 20 classes"):
        load_probability_prediction(tmp_path / "bad.npy", C, (6, 8))
    hwc[0, 0, 0] = np.nan
    np.save(tmp_path / "nan.npy", hwc)
    with pytest.raises(ValueError, match="NaN"):
        load_probability_prediction(tmp_path / "nan.npy", C, (6, 8))
    np.save(tmp_path / "neg.npy", -np.ones((6, 8, C)))
    with pytest.raises(ValueError, match="negative"):
        load_probability_prediction(tmp_path / "neg.npy", C, (6, 8))


def test_find_prediction(tmp_path):
    (tmp_path / "000010.npz").write_bytes(b"")
    (tmp_path / "000020.label.png").write_bytes(b"")
    assert find_prediction(tmp_path, "000010").name == "000010.npz"
    assert find_prediction(tmp_path, "000020").name == "000020.label.png"
    with pytest.raises(FileNotFoundError, match=r"frame '000030'.*tried 000030\.png, 000030\.label\.png"):
        find_prediction(tmp_path, "000030")
