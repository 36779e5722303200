"""The paper's equations on tiny hand-made inputs (Eqs. 1-2, 4, 10-16)."""
import numpy as np
import pytest

from diffuser_lab.data.scene import IGNORE, Frame
from diffuser_lab.method.diffusion import diffuse, labels_from_scores, normalise
from diffuser_lab.method.evidence import accumulate
from diffuser_lab.method.graph import KnnGraph, build_graph, knn

K = np.array([[10.0, 0.0, 2.0], [0.0, 10.0, 1.0], [0.0, 0.0, 1.0]])  # 5 x 3 image


def five_points():
    # at z = 1 m in front of a camera at the origin, projecting to pixels (col 0..4, row 1)
    x = (np.arange(5) - 2) / 10.0
    return np.stack([x, np.zeros(5), np.ones(5)], 1).astype(np.float32)


def two_frames():
    depth_a = np.ones((3, 5), np.float32)
    labels_a = np.full((3, 5), IGNORE, np.int16)
    labels_a[1] = [0, 0, 1, 1, 1]
    depth_b = np.ones((3, 5), np.float32)
    depth_b[1, 0] = 0.5  # something 0.5 m in front of point 0: it is occluded in frame B
    labels_b = np.full((3, 5), IGNORE, np.int16)
    labels_b[1] = [0, 1, 1, 1, IGNORE]  # pixel of point 4 has no prediction
    return [Frame("a", K, np.eye(4), depth_a, labels=labels_a), Frame("b", K, np.eye(4), depth_b, labels=labels_b)]


def test_evidence_by_hand():
    ev = accumulate(five_points(), two_frames(), 2, depth_tol=0.05)
    expected = np.array([[1, 0], [1, 1], [0, 2], [0, 2], [0, 1]], np.float32)
    np.testing.assert_array_equal(ev.mass, expected)
    np.testing.assert_array_equal(ev.links, [1, 2, 2, 2, 1])
    assert ev.points_per_frame == [5, 4]  # point 0 fails the depth check in B


def test_frame_order_does_not_change_evidence():
    a = accumulate(five_points(), two_frames(), 2).mass
    b = accumulate(five_points(), two_frames()[::-1], 2).mass
    np.testing.assert_array_equal(a, b)


def test_occluded_and_out_of_view_points_get_no_evidence():
    pts = np.array([[0, 0, 1.0], [0, 0, 2.0], [5.0, 0, 1.0], [0, 0, -1.0]], np.float32)
    depth = np.ones((3, 5), np.float32)
    labels = np.zeros((3, 5), np.int16)
    ev = accumulate(pts, [Frame("f", K, np.eye(4), depth, labels=labels)], 1, depth_tol=0.05)
    # visible; behind the surface at 1 m; outside the image; behind the camera
    np.testing.assert_array_equal(ev.mass[:, 0], [1, 0, 0, 0])
    # a looser tolerance lets the hidden point through: the check is what blocks it
    ev = accumulate(pts, [Frame("f", K, np.eye(4), depth, labels=labels)], 1, depth_tol=1.5)
    np.testing.assert_array_equal(ev.mass[:, 0], [1, 1, 0, 0])


def test_zero_depth_is_no_evidence():
    depth = np.zeros((3, 5), np.float32)
    ev = accumulate(five_points(), [Frame("f", K, np.eye(4), depth, labels=np.zeros((3, 5), np.int16))], 1)
    assert ev.mass.sum() == 0


@pytest.mark.parametrize("col,row,n", [(2, 2, 9), (0, 0, 4), (4, 2, 6)])
def test_pixel_neighbourhood_radius_1_is_the_3x3_window(col, row, n):
    Kb = np.array([[10.0, 0, 2.0], [0, 10.0, 2.0], [0, 0, 1.0]])  # 5 x 5 image
    p = np.array([[(col - 2) / 10.0, (row - 2) / 10.0, 1.0]], np.float32)
    labels = np.arange(25, dtype=np.int16).reshape(5, 5)  # every pixel its own class
    frame = Frame("f", Kb, np.eye(4), np.ones((5, 5), np.float32), labels=labels)
    m = accumulate(p, [frame], 25, pixel_radius=1).mass[0]
    window = labels[max(row - 1, 0) : row + 2, max(col - 1, 0) : col + 2].ravel()
    assert set(np.flatnonzero(m)) == set(window.tolist())
    assert m.sum() == n
    assert accumulate(p, [frame], 25, pixel_radius=0).mass[0].sum() == 1


def test_soft_labels_sum_to_one_per_pixel():
    probs = np.zeros((3, 5, 3), np.float32)
    probs[...] = [1.0, 3.0, 1.0]  # unnormalised scores: each pixel still carries a mass of 1 (Eq. 13)
    f = Frame("f", K, np.eye(4), np.ones((3, 5), np.float32), probs=probs)
    m = accumulate(five_points(), [f, f], 3).mass
    np.testing.assert_allclose(m, np.tile([0.4, 1.2, 0.4], (5, 1)), rtol=1e-6)


def test_two_point_fixed_point_by_hand():
    # w_01 = w_10 = 1, lambda = 1, point 0 sees one pixel of class 0.
    # d_0 = 1 + 1 = 2, d_1 = 1  ->  P = [[0, 1/2], [1, 0]], B = [[1/2, 0], [0, 0]]
    # fixed point: z0 = z1/2 + 1/2, z1 = z0  ->  z0 = z1 = 1
    g = KnnGraph(neighbors=np.array([[1], [0]], np.int32), weights=np.ones((2, 1), np.float32), rho=1, sigma_d=1)
    sys_ = normalise(g, np.array([[1, 0], [0, 0]], np.float32), 1.0)
    np.testing.assert_allclose(sys_.P.toarray(), [[0, 0.5], [1, 0]])
    np.testing.assert_allclose(sys_.B, [[0.5, 0], [0, 0]])
    res = diffuse(sys_, max_iter=5000, tol=1e-7)
    assert res.converged
    np.testing.assert_allclose(res.Z, [[1, 0], [1, 0]], atol=1e-5)
    np.testing.assert_array_equal(labels_from_scores(res.Z), [0, 0])


def test_five_point_row_sums_and_fixed_point():
    ev = accumulate(five_points(), two_frames(), 2)
    # chain 0-1-2-3-4, each point linked to its chain neighbours with weight 0.5
    nb = np.array([[1, 1], [0, 2], [1, 3], [2, 4], [3, 3]], np.int32)
    w = np.array([[0.5, 0.0], [0.5, 0.5], [0.5, 0.5], [0.5, 0.5], [0.5, 0.0]], np.float32)
    g = KnnGraph(neighbors=nb, weights=w, rho=0.1, sigma_d=0.2)
    lam = 0.25
    s = normalise(g, ev.mass, lam)
    # Eqs. 14-15 by hand: d = [0.5+0.25, 1+0.5, 1+0.5, 1+0.5, 0.5+0.25]
    d = np.array([0.75, 1.5, 1.5, 1.5, 0.75])
    np.testing.assert_allclose(s.B, lam * ev.mass / d[:, None], rtol=1e-6)
    np.testing.assert_allclose(s.B[2], [0, 1 / 3], rtol=1e-6)
    np.testing.assert_allclose(s.P.toarray()[1], [0.5 / 1.5, 0, 0.5 / 1.5, 0, 0], rtol=1e-6)
    np.testing.assert_allclose(s.row_sums, 1.0, rtol=1e-6)  # rows of [P | B] sum to 1
    P = s.P.toarray().astype(np.float64)
    Zstar = np.linalg.solve(np.eye(5) - P, s.B.astype(np.float64))
    res = diffuse(s, max_iter=20000, tol=1e-8)
    np.testing.assert_allclose(res.Z, Zstar, rtol=1e-3, atol=1e-5)
    # point 1 is split 1:1 by its pixels; its neighbours decide: class 1 has more mass nearby
    np.testing.assert_array_equal(labels_from_scores(res.Z), np.argmax(Zstar, 1))


def test_unreached_points_are_unlabeled_not_class_0():
    # two separate pairs; only the first pair has evidence
    g = KnnGraph(neighbors=np.array([[1], [0], [3], [2]], np.int32), weights=np.ones((4, 1), np.float32),
                 rho=1, sigma_d=1)
    mass = np.array([[0, 3], [0, 0], [0, 0], [0, 0]], np.float32)
    res = diffuse(normalise(g, mass, 1e-4), max_iter=50)
    np.testing.assert_array_equal(labels_from_scores(res.Z), [1, 1, IGNORE, IGNORE])
    # and within reach only after enough iterations: a 3-hop chain after 2 iterations
    g = KnnGraph(neighbors=np.array([[1], [2], [1]], np.int32), weights=np.ones((3, 1), np.float32), rho=1,
                 sigma_d=1)
    res = diffuse(normalise(g, np.array([[1.0], [0], [0]], np.float32), 1e-4), max_iter=1, tol=0)
    np.testing.assert_array_equal(labels_from_scores(res.Z), [0, IGNORE, IGNORE])


def test_edge_weights_eq4():
    pts = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.3, 0]], np.float32)
    nrm = np.array([[0, 0, 1], [0, 1, 0], [0, 0, -1]], np.float32)
    g = build_graph(pts, 1, nrm, sigma_s=0.2, sigma_d=0.1)
    # point 0 -> 1: d^2 = 0.01, |n0 - n1|^2 = 2
    np.testing.assert_allclose(g.weights[0, 0], np.exp(-0.01 / 0.02 - 2 / 0.08), rtol=1e-5)
    # point 2 -> 0 with opposite normals: |n2 - n0|^2 = 4 signed, 0 orientation-invariant
    np.testing.assert_allclose(g.weights[2, 0], np.exp(-0.09 / 0.02 - 4 / 0.08), rtol=1e-4)
    gi = build_graph(pts, 1, nrm, sigma_s=0.2, sigma_d=0.1, invariant_normals=True)
    np.testing.assert_allclose(gi.weights[2, 0], np.exp(-0.09 / 0.02), rtol=1e-5)
    gd = build_graph(pts, 1, None, sigma_d=0.1)
    np.testing.assert_allclose(gd.weights[0, 0], np.exp(-0.01 / 0.02), rtol=1e-5)
    # default sigma_d = 2 rho, rho = mean nearest-neighbour distance = (0.1 + 0.1 + 0.3) / 3
    assert build_graph(pts, 1).sigma_d == pytest.approx(2 * 0.5 / 3, rel=1e-5)


def test_knn_excludes_self_even_with_duplicates():
    pts = np.array([[0, 0, 0], [0, 0, 0], [1, 0, 0], [3, 0, 0]], np.float32)
    d, idx = knn(pts, 2)
    assert not (idx == np.arange(4)[:, None]).any()
    np.testing.assert_array_equal(d[0], [0, 1])
    g = build_graph(pts, 2)
    assert np.isfinite(g.weights).all() and g.rho > 0
    with pytest.raises(ValueError, match="graph.k=4 must be smaller"):
        knn(pts, 4)


def crease(spacing=0.05):
    a = np.arange(0, 1.0 + 1e-9, spacing)
    fx, fy = np.meshgrid(a, a, indexing="ij")
    floor = np.stack([fx.ravel(), fy.ravel(), np.zeros(fx.size)], 1)
    wy, wz = np.meshgrid(a, a[1:], indexing="ij")
    wall = np.stack([np.zeros(wy.size), wy.ravel(), wz.ravel()], 1)
    pts = np.vstack([floor, wall]).astype(np.float32)
    nrm = np.vstack([np.tile([0, 0, 1.0], (len(floor), 1)), np.tile([1.0, 0, 0], (len(wall), 1))]).astype(np.float32)
    is_wall = np.arange(len(pts)) >= len(floor)
    mass = np.zeros((len(pts), 2), np.float32)
    mass[~is_wall, 0] = 1  # the floor is seen as class 0 everywhere
    mass[is_wall & (pts[:, 2] >= 0.8), 1] = 1  # only the top of the wall is seen, as class 1
    return pts, nrm, mass, is_wall


@pytest.mark.parametrize("use_normals", [False, True])
def test_two_planes_normals_stop_labels_at_the_crease(use_normals):
    pts, nrm, mass, is_wall = crease()
    g = build_graph(pts, 16, nrm if use_normals else None)
    lab = labels_from_scores(diffuse(normalise(g, mass, 1e-4), max_iter=200).Z)
    low_wall = is_wall & (pts[:, 2] <= 0.15)
    share_floor_label = np.mean(lab[low_wall] == 0)
    if use_normals:
        assert share_floor_label == 0.0  # the crease stops the floor's label
        assert np.all(lab[is_wall] == 1) and np.all(lab[~is_wall] == 0)
    else:
        assert share_floor_label > 0.9  # without the normal term it crosses


def test_normalising_twice_leaves_the_graph_intact():
    rng = np.random.default_rng(0)
    pts = rng.random((300, 3)).astype(np.float32)
    g = build_graph(pts, 8, sigma_d=0.01)  # tiny bandwidth: many weights fall under the edge floor
    before = g.neighbors.copy(), g.weights.copy()
    mass = np.zeros((300, 2), np.float32)
    mass[:10, 0] = 1
    a = diffuse(normalise(g, mass, 1e-4), max_iter=30).Z
    np.testing.assert_array_equal(g.neighbors, before[0])
    np.testing.assert_array_equal(g.weights, before[1])
    b = diffuse(normalise(g, mass, 1e-4), max_iter=30).Z
    np.testing.assert_array_equal(a, b)
