"""The simulated embedding network: prototypes like text embeddings, per-view embedding maps whose
distortions are not linear in the class probabilities, and query files with one-line errors."""
import numpy as np
import pytest

from diffuser_lab.data.embeddings import (
    load_queries,
    prototypes,
    simulate_features,
    text_encoder,
    write_queries,
)
from diffuser_lab.data.scene import IGNORE, SCANNET20

CLEAN = dict(dominance=1.0, boundary_mix=0.0, rotation_deg=0.0, noise=0.0)


def _scene_labels(H=96, W=128):
    """Three regions and an unlabeled band: (H, W) int16."""
    lab = np.zeros((H, W), np.int16)
    lab[:, 48:] = 3
    lab[48:, 80:] = 7
    lab[:16] = IGNORE
    return lab


def test_prototypes_unit_seeded_and_like_text_embeddings():
    E = prototypes(SCANNET20.names)
    assert E.shape == (20, 512) and E.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(E, axis=1), 1, atol=1e-6)
    cos = (E @ E.T)[~np.eye(20, dtype=bool)]
    assert 0.15 < cos.min() and cos.max() < 0.55 and 0.25 < cos.mean() < 0.45  # not orthogonal, not alike
    np.testing.assert_array_equal(E, prototypes(SCANNET20.names))
    # a name's row does not depend on the list it is in (a text encoder's behaviour)
    np.testing.assert_array_equal(prototypes(["sofa", "chair"])[1], E[SCANNET20.names.index("chair")])
    assert not np.allclose(prototypes(["chair"], seed=1), prototypes(["chair"]))
    assert prototypes(["a", "b"], dim=64).shape == (2, 64)
    np.testing.assert_array_equal(text_encoder(["chair"]), prototypes(["chair"]))


def test_clean_features_are_the_prototypes():
    E = prototypes(SCANNET20.names, dim=64)
    lab = _scene_labels()
    f = simulate_features(lab, E, np.random.default_rng(0), stride=8, **CLEAN)
    assert f.shape == (12, 16, 64) and f.dtype == np.float16
    assert np.isnan(f[:2]).all() and not np.isnan(f[2:]).any()  # the unlabeled band's cells
    np.testing.assert_allclose(f[4, 0], E[0], atol=2e-3)
    np.testing.assert_allclose(f[4, 10], E[3], atol=2e-3)
    np.testing.assert_allclose(f[8, 12], E[7], atol=2e-3)
    # a cell straddling two classes: their prototypes by share, normalised
    g = simulate_features(lab, E, np.random.default_rng(0), stride=32, dtype=np.float32, **CLEAN)
    m = 0.5 * E[3] + 0.5 * E[7]  # rows 64-95, columns 64-79 class 3, 80-95 class 7
    np.testing.assert_allclose(g[2, 2], m / np.linalg.norm(m), atol=1e-5)


def test_shape_is_ceil_of_the_stride_and_probs_equal_labels():
    E = prototypes(["a", "b", "c"], dim=32)
    lab = np.random.default_rng(1).integers(-1, 3, (50, 70)).astype(np.int16)
    f = simulate_features(lab, E, np.random.default_rng(5), stride=14, dtype=np.float32)
    assert f.shape == (4, 5, 32)
    onehot = np.zeros((50, 70, 3), np.float32)
    onehot[lab >= 0, lab[lab >= 0]] = 1
    g = simulate_features(None, E, np.random.default_rng(5), probs=onehot, stride=14, dtype=np.float32)
    np.testing.assert_allclose(f, g, atol=1e-5)


def test_default_distortions_keep_the_class_and_differ_per_view():
    E = prototypes(SCANNET20.names)
    lab = _scene_labels(240, 320)
    a = simulate_features(lab, E, np.random.default_rng(0)).astype(np.float32)
    b = simulate_features(lab, E, np.random.default_rng(1)).astype(np.float32)
    again = simulate_features(lab, E, np.random.default_rng(0)).astype(np.float32)
    np.testing.assert_array_equal(np.isnan(a), np.isnan(again))
    np.testing.assert_array_equal(np.nan_to_num(a), np.nan_to_num(again))
    ok = ~np.isnan(a).any(-1)
    np.testing.assert_allclose(np.linalg.norm(a[ok], axis=-1), 1, atol=2e-3)
    # cells inside one region (away from its borders) still match their class best
    cell = lab[::8, ::8]
    inner = ok & (cell == np.roll(cell, 1, 0)) & (cell == np.roll(cell, -1, 0)) & \
        (cell == np.roll(cell, 1, 1)) & (cell == np.roll(cell, -1, 1))
    assert inner.sum() > 500
    assert ((a[inner] @ E.T).argmax(-1) == cell[inner]).mean() > 0.99
    own = (a[inner] * E[cell[inner]]).sum(-1)
    assert 0.8 < own.mean() < 0.99  # distorted, not the prototype
    # another view: another rotation and noise
    assert np.abs(np.nan_to_num(a) - np.nan_to_num(b)).max() > 0.05


def test_features_are_not_linear_in_the_probabilities():
    """F(Y1 + Y2) != F(Y1) + F(Y2) even without rotation and noise, and one view's rotation is
    another view's: no one E with F = Y E."""
    E = prototypes(["a", "b", "c"], dim=32)
    H, W = 16, 16
    y1 = np.zeros((H, W, 3), np.float32)
    y1[..., 0] = 0.7
    y1[..., 1] = 0.3
    y2 = np.zeros((H, W, 3), np.float32)
    y2[..., 2] = 1.0
    kw = dict(stride=8, dtype=np.float64, boundary_mix=0.0, rotation_deg=0.0, noise=0.0)
    rng = np.random.default_rng(0)
    f1, f2, f12 = (simulate_features(None, E, rng, probs=p, **kw) for p in (y1, y2, 0.5 * (y1 + y2)))
    assert np.abs(f12 - 0.5 * (f1 + f2)).max() > 0.05
    lin = (y1[0, 0] @ E) / np.linalg.norm(y1[0, 0] @ E)
    assert np.abs(f1[0, 0] - lin).max() > 0.01  # dominance: the majority class weighs more than its share
    kw["rotation_deg"] = 30.0
    r1 = simulate_features(None, E, np.random.default_rng(1), probs=y2, **kw)
    r2 = simulate_features(None, E, np.random.default_rng(2), probs=y2, **kw)
    assert np.abs(r1 - r2).max() > 0.05


def test_boundary_mixing_reaches_the_neighbour_cells_only():
    E = prototypes(["a", "b"], dim=32)
    lab = np.zeros((32, 64), np.int16)
    lab[:, 32:] = 1
    f = simulate_features(lab, E, np.random.default_rng(0), stride=8, dtype=np.float64,
                          **{**CLEAN, "boundary_mix": 0.3})
    np.testing.assert_allclose(f[:, 0], np.broadcast_to(E[0], (4, 32)), atol=1e-6)
    assert (f[:, 3] @ E[1] > 0.5 * f[:, 0] @ E[1]).all() and (f[:, 3] @ E[0] > f[:, 3] @ E[1]).all()


@pytest.mark.parametrize("kwargs, msg", [
    (dict(labels=np.zeros((4, 4), np.float32)), "expected (H, W) integer class ids"),
    (dict(labels=np.full((4, 4), 5, np.int16)), "expected -1..2"),
    (dict(labels=None, probs=np.zeros((4, 4, 2))), "expected (H, W, 3)"),
    (dict(labels=None), "give labels"),
])
def test_simulate_features_bad_input(kwargs, msg):
    E = prototypes(["a", "b", "c"], dim=8)
    with pytest.raises(ValueError) as e:
        simulate_features(kwargs.pop("labels"), E, np.random.default_rng(0), **kwargs)
    assert msg in str(e.value) and "\n" not in str(e.value)


def test_query_file_round_trip(tmp_path):
    E = prototypes(["chair", "table"], dim=16)
    p = write_queries(tmp_path / "q", ["chair", "table"], E.astype(np.float16))
    assert p.name == "q.npz"
    names, e = load_queries(p, dim=16)
    assert names == ["chair", "table"] and e.dtype == np.float32 and e.shape == (2, 16)
    np.testing.assert_allclose(e, E, atol=1e-3)


def _bad(tmp_path, name, **arrays):
    p = tmp_path / name
    np.savez(p, **arrays)
    return p


@pytest.mark.parametrize("case, msg", [
    ("missing", "no 'embeddings' array (has: names)"),
    ("shape", "embeddings of shape (8,), expected (2, D): one row per name"),
    ("rows", "embeddings of shape (3, 8), expected (2, D)"),
    ("dim", "embeddings of dimension 8, expected 16 (the features)"),
    ("nan", "embedding of 'b' is not finite or all zero"),
    ("zero", "embedding of 'a' is not finite or all zero"),
    ("object", "[names]: array of Python objects (object), expected numbers or strings"),
    ("numbers", "names of shape (2,) dtype int64, expected a (Q,) array of strings"),
    ("dup", "query names ['a'] repeated"),
    ("npy", "a single array, expected a .npz query file"),
    ("text", "unreadable"),
    ("absent", "unreadable (FileNotFoundError"),
])
def test_bad_query_files_give_one_line(tmp_path, case, msg):
    e = np.ones((2, 8), np.float32)
    names = np.array(["a", "b"])
    if case == "missing":
        p = _bad(tmp_path, "q.npz", names=names)
    elif case == "shape":
        p = _bad(tmp_path, "q.npz", names=names, embeddings=np.ones(8))
    elif case == "rows":
        p = _bad(tmp_path, "q.npz", names=names, embeddings=np.ones((3, 8)))
    elif case == "dim":
        p = _bad(tmp_path, "q.npz", names=names, embeddings=e)
    elif case == "nan":
        p = _bad(tmp_path, "q.npz", names=names, embeddings=np.array([np.ones(8), np.full(8, np.nan)]))
    elif case == "zero":
        p = _bad(tmp_path, "q.npz", names=names, embeddings=np.array([np.zeros(8), np.ones(8)]))
    elif case == "object":
        p = _bad(tmp_path, "q.npz", names=np.array(["a", "b"], dtype=object), embeddings=e)
    elif case == "numbers":
        p = _bad(tmp_path, "q.npz", names=np.array([1, 2]), embeddings=e)
    elif case == "dup":
        p = _bad(tmp_path, "q.npz", names=np.array(["a", "a"]), embeddings=e)
    elif case == "npy":
        p = tmp_path / "q.npy"
        np.save(p, e)
    elif case == "text":
        p = tmp_path / "q.npz"
        p.write_text("names,embeddings\n")
    else:
        p = tmp_path / "nothing.npz"
    with pytest.raises(ValueError) as exc:
        load_queries(p, dim=16 if case == "dim" else None)
    text = str(exc.value)
    assert text.startswith(str(p)) and msg in text and "\n" not in text, text
