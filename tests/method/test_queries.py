"""Open-vocabulary queries: the query set, cosine scores in chunks, labels with a threshold, query
names -> classes; prototypes as queries reproduce clean labels."""
import tracemalloc

import numpy as np
import pytest

from diffuser_lab.data.embeddings import prototypes, simulate_features, write_queries
from diffuser_lab.data.scene import IGNORE, SCANNET20
from diffuser_lab.method import queries as qm
from diffuser_lab.method.queries import Queries, query_classes, query_labels, similarity


def encode_wrong_rows(names):
    """A test encoder returning one row too many."""
    return np.ones((len(names) + 1, 8))


def encode_raises(names):
    raise RuntimeError("no GPU\nsecond line")


def test_queries_are_unit_read_only_and_checked():
    q = Queries(("a", "b"), np.array([[3.0, 4.0], [0.0, 2.0]]))
    np.testing.assert_allclose(q.embeddings, [[0.6, 0.8], [0.0, 1.0]], atol=1e-7)
    assert q.embeddings.dtype == np.float32 and len(q) == 2 and q.dim == 2 and q.names == ("a", "b")
    with pytest.raises(ValueError):
        q.embeddings[0, 0] = 1
    with pytest.raises(AttributeError):
        q.names = ("c",)
    with pytest.raises(ValueError, match=r"embeddings of shape \(1, 2\), expected \(2, D\)"):
        Queries(("a", "b"), np.ones((1, 2)))


def test_queries_from_file_and_encoder(tmp_path):
    E = prototypes(["chair", "table"], dim=32)
    path = write_queries(tmp_path / "q.npz", ["chair", "table"], 2 * E)
    q = Queries.from_file(path)
    assert q.names == ("chair", "table") and q.source == str(path)
    np.testing.assert_allclose(q.embeddings, E, atol=1e-6)
    with pytest.raises(ValueError, match="expected 64 .the features."):
        Queries.from_file(path, dim=64)
    r = Queries.from_encoder(["chair", "table"], "diffuser_lab.data.embeddings.text_encoder")
    assert r.dim == 512 and r.source == "encoder diffuser_lab.data.embeddings.text_encoder"
    np.testing.assert_allclose(r.embeddings, prototypes(["chair", "table"]), atol=1e-6)


@pytest.mark.parametrize("target, msg", [
    ("nodots", "encoder 'nodots': expected module.fn"),
    ("no_such_module_xyz.fn", "encoder no_such_module_xyz.fn: module no_such_module_xyz does not import"),
    ("diffuser_lab.data.embeddings.nope", "module diffuser_lab.data.embeddings has no 'nope'"),
    ("math.pi", "encoder math.pi: float, expected a function"),
    ("test_queries.encode_wrong_rows", "returned shape (3, 8), expected (2, D) for 2 names"),
    ("test_queries.encode_raises", "failed on 2 names (RuntimeError: no GPU)"),
])
def test_bad_encoders_give_one_line(target, msg):
    with pytest.raises(ValueError) as e:
        Queries.from_encoder(["a", "b"], target)
    assert msg in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_similarity_is_the_cosine_with_nan_for_empty_rows(monkeypatch):
    rng = np.random.default_rng(0)
    F = rng.standard_normal((1000, 16)).astype(np.float16)
    F[[3, 500, 999]] = 0
    E = rng.standard_normal((5, 16))
    monkeypatch.setattr(qm, "CHUNK_ELEMENTS", 16 * 97)  # chunks of 97 rows: boundaries inside
    s = similarity(F, Queries(tuple("abcde"), E))
    f = F.astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        ref = (f / np.linalg.norm(f, axis=1, keepdims=True)) @ (E / np.linalg.norm(E, axis=1, keepdims=True)).T
    assert s.shape == (1000, 5) and s.dtype == np.float32
    np.testing.assert_array_equal(np.isnan(s).all(1), np.isin(np.arange(1000), [3, 500, 999]))
    np.testing.assert_allclose(s, ref, atol=1e-5)
    np.testing.assert_allclose(similarity(F.astype(np.float32), E), s, atol=1e-6)  # a plain (Q, D) array too
    with pytest.raises(ValueError, match=r"features of shape \(1000, 16\), expected \(N, 8\)"):
        similarity(F, np.ones((2, 8)))


def test_similarity_makes_no_float32_copy_of_the_features():
    F = np.ones((200_000, 128), np.float16)  # 51 MB; a float32 copy: 102 MB
    q = Queries(("a", "b"), np.eye(2, 128))
    tracemalloc.start()
    try:
        s = similarity(F, q)
        lab = query_labels(F, q, np.array([0, 1]))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 40e6, peak  # the (N, 2) output and a chunk
    assert s.shape == (200_000, 2) and (lab == 0).all()


def test_query_labels_argmax_threshold_background():
    E = np.eye(3, 4)
    F = np.array([[1, 0.1, 0, 0], [0, 1, 0.2, 0], [0, 0, 0, 0], [0, 0.05, 1, 0], [0.1, 0.1, 0.1, 1], [np.nan] * 4],
                 np.float32)
    q = Queries(("x", "y", "z"), E)
    lab = query_labels(F, q, np.array([4, 2, 2]))
    assert lab.dtype == np.int16
    np.testing.assert_array_equal(lab, [4, 2, IGNORE, 2, 4, IGNORE])
    # the fifth point matches nothing well (cosine 0.1): background, a class or unlabeled
    np.testing.assert_array_equal(query_labels(F, q, np.array([4, 2, 2]), threshold=0.5, background=9),
                                  [4, 2, IGNORE, 2, 9, IGNORE])
    np.testing.assert_array_equal(query_labels(F, q, np.array([4, 2, 2]), threshold=0.5),
                                  [4, 2, IGNORE, 2, IGNORE, IGNORE])
    # a query standing for no class leaves its points unlabeled
    np.testing.assert_array_equal(query_labels(F, q, np.array([IGNORE, 2, 2])), [IGNORE, 2, IGNORE, 2, IGNORE, IGNORE])
    with pytest.raises(ValueError, match=r"to_class of shape \(2,\)"):
        query_labels(F, q, np.array([0, 1]))


def test_prototypes_as_queries_reproduce_clean_labels():
    """Linear features of clean one-hot labels, and the simulated network's clean per-cell
    features: the prototypes as queries give back the labels."""
    names = SCANNET20.names
    E = prototypes(names)
    rng = np.random.default_rng(3)
    labels = rng.integers(-1, 20, 5000).astype(np.int16)
    Y = np.zeros((5000, 20), np.float32)
    Y[labels >= 0, labels[labels >= 0]] = 1
    F = (Y @ E).astype(np.float16)  # a row of zeros where a point has no label
    q = Queries(tuple(names), E)
    np.testing.assert_array_equal(query_labels(F, q, query_classes(q.names, names)), labels)
    img = np.repeat(np.repeat(rng.integers(-1, 20, (12, 16)), 8, 0), 8, 1).astype(np.int16)
    cells = simulate_features(img, E, rng, stride=8, dominance=1.0, boundary_mix=0.0, rotation_deg=0.0, noise=0.0)
    got = query_labels(np.nan_to_num(cells.reshape(-1, 512)), q, np.arange(20))
    np.testing.assert_array_equal(got, img[::8, ::8].ravel())


def test_query_classes_by_name_and_mapping(tmp_path):
    classes = ("wall", "floor", "chair", "shower curtain")
    assert query_classes(["Chair", " wall", "SHOWER CURTAIN"], classes).tolist() == [2, 0, 3]
    m = tmp_path / "map.csv"
    m.write_text("# queries of my CLIP prompt set\nquery,class\narmchair,chair\nground,Floor\nlamp,ignore\nstool,\n")
    got = query_classes(["armchair", "ground", "wall", "lamp", "stool"], classes, mapping=m)
    assert got.tolist() == [2, 1, 0, IGNORE, IGNORE]


@pytest.mark.parametrize("names, text, msg", [
    (["lamp"], None, "query 'lamp' is not a class of the taxonomy (wall, floor, chair) and no mapping file is "
                     "given: expected a mapping line 'lamp,CLASS'"),
    (["lamp"], "query,class\nsofa,chair\n", "line 2: query 'sofa' is not in the query set (lamp)"),
    (["lamp"], "lamp,furniture\n", "line 1: class 'furniture' is not in the taxonomy (wall, floor, chair)"),
    (["lamp"], "lamp,chair,extra\n", "line 1: 3 fields"),
    (["lamp"], "lamp,chair\nlamp,wall\n", "line 2: query 'lamp' mapped twice"),
    (["lamp", "chair"], "chair,chair\n", "and MAP does not map it"),
])
def test_query_classes_errors_are_one_line(tmp_path, names, text, msg):
    mapping = None
    if text is not None:
        mapping = tmp_path / "map.csv"
        mapping.write_text(text)
    with pytest.raises(ValueError) as e:
        query_classes(names, ("wall", "floor", "chair"), mapping=mapping)
    got = str(e.value).replace(str(mapping), "MAP")
    assert msg in got and "\n" not in got, got
