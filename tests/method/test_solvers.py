"""Solvers and backends: compiled vs scipy paths, spatial order, solver=exact, torch, the bench CLI."""
import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from diffuser_lab.backends import numba as nb
from diffuser_lab.backends.numba import jacobi as kernels
from diffuser_lab.config import default_config
from diffuser_lab.method.diffusion import SortedSystem, diffuse, labels_from_scores, normalise
from diffuser_lab.method.solvers import solve
from diffuser_lab.method.evidence import accumulate
from diffuser_lab.method.exact import solve_exact
from diffuser_lab.method.graph import KnnGraph, SortedKnnGraph, build_graph

needs_numba = pytest.mark.skipif(not nb.available(), reason="numba not importable or DIFFUSER_LAB_NUMBA=0")


def cloud(n=2000, seed=0):
    rng = np.random.default_rng(seed)
    # two noisy planes meeting at a crease, like a voxelised wall and floor
    a = rng.random((n // 2, 2))
    floor = np.c_[a, np.zeros(n // 2)]
    wall = np.c_[np.zeros(n - n // 2), rng.random((n - n // 2, 2))]
    pts = np.vstack([floor, wall]) + rng.normal(scale=0.002, size=(n, 3))
    nrm = np.vstack([np.tile([0, 0, 1.0], (n // 2, 1)), np.tile([1.0, 0, 0], (n - n // 2, 1))])
    mass = np.zeros((n, 5), np.float32)
    seen = rng.random(n) < 0.3
    mass[seen, rng.integers(0, 4, seen.sum())] = rng.integers(1, 6, seen.sum())
    return pts.astype(np.float32), nrm.astype(np.float32), mass


def plain_graph(g: KnnGraph) -> KnnGraph:
    return KnnGraph(neighbors=g.neighbors.copy(), weights=g.weights.copy(), rho=g.rho, sigma_d=g.sigma_d)


@pytest.mark.parametrize("backend", [pytest.param("numba", marks=needs_numba), "scipy"])
def test_knn_is_exact(backend):
    pts, nrm, _ = cloud()
    pts = np.vstack([pts, pts[:5]])  # exact duplicates
    g = build_graph(pts, 12, backend=backend)
    d, idx = cKDTree(pts.astype(np.float64)).query(pts.astype(np.float64), k=13)
    nb = g.neighbors
    assert not (nb == np.arange(len(pts))[:, None]).any()
    # same distances as a KD-tree (sets may differ only among exact ties)
    mine = np.sort(np.linalg.norm(pts[nb] - pts[:, None], axis=2), 1)
    theirs = np.sort(np.where(idx == np.arange(len(pts))[:, None], np.inf, d), 1)[:, :12]
    dup = np.zeros(len(pts), bool)
    dup[:5] = dup[-5:] = True
    np.testing.assert_allclose(mine[~dup], theirs[~dup], rtol=1e-5, atol=1e-7)


@needs_numba
def test_sparse_cloud_falls_back_and_backends_agree():
    rng = np.random.default_rng(3)
    pts = np.vstack([rng.random((300, 3)) * 0.1, 1000.0 + rng.random((300, 3)) * 0.1]).astype(np.float32)
    a, b = build_graph(pts, 8, backend="numba"), build_graph(pts, 8, backend="scipy")
    np.testing.assert_array_equal(np.sort(a.neighbors, 1), np.sort(b.neighbors, 1))
    assert a.rho == pytest.approx(b.rho, rel=1e-12)


def test_sorted_system_matches_the_plain_one():
    pts, nrm, mass = cloud(600)
    g = build_graph(pts, 10, nrm)
    assert isinstance(g, SortedKnnGraph)
    s = normalise(g, mass, 1e-3)
    p = normalise(plain_graph(g), mass, 1e-3)
    assert isinstance(s, SortedSystem)
    np.testing.assert_allclose(s.P.toarray(), p.P.toarray(), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(s.B, p.B, rtol=1e-6)
    np.testing.assert_allclose(s.row_sums, 1.0, rtol=1e-5)


@pytest.mark.parametrize("backend", [pytest.param("numba", marks=needs_numba), "scipy"])
def test_backends_and_orders_agree(backend):
    pts, nrm, mass = cloud()
    g = build_graph(pts, 16, nrm)
    a = diffuse(normalise(g, mass, 1e-4), max_iter=60, tol=0, backend=backend)
    b = diffuse(normalise(plain_graph(g), mass, 1e-4), max_iter=60, tol=0, backend="scipy")
    assert a.Z.dtype == np.float32 and a.iterations == 60 and a.info["backend"] == backend
    np.testing.assert_allclose(a.Z, b.Z, rtol=2e-5, atol=1e-12 * b.Z.max())
    np.testing.assert_array_equal(labels_from_scores(a.Z), labels_from_scores(b.Z))
    np.testing.assert_allclose(a.residuals, b.residuals, rtol=1e-3)


@pytest.mark.parametrize("backend", [pytest.param("numba", marks=needs_numba), "scipy"])
def test_observer_sees_the_returned_z(backend):
    pts, nrm, mass = cloud(800)
    s = normalise(build_graph(pts, 12, nrm), mass, 1e-4)

    class Obs:
        def __init__(self):
            self.seen = {}

        def wants(self, it):
            return it % 10 == 0 or it == 1 or it == 25

        def __call__(self, it, Z, stats):
            assert not Z.flags.writeable and "residual" in stats
            self.seen[it] = Z.copy()

    obs = Obs()
    res = diffuse(s, max_iter=25, tol=0, observer=obs, backend=backend)
    assert sorted(obs.seen) == [1, 10, 20, 25]
    np.testing.assert_array_equal(obs.seen[25], res.Z)
    calls = []
    diffuse(s, max_iter=3, tol=0, observer=lambda it, Z, st: calls.append(it), backend=backend)
    assert calls == [1, 2, 3]  # a plain callable is called every iteration


def test_exact_solver_matches_dense_solve_and_leaves_unreachable_points_at_zero():
    pts, nrm, mass = cloud(400)
    pts = np.vstack([pts, pts[:20] + 50.0])  # an island that no pixel sees
    nrm = np.vstack([nrm, nrm[:20]])
    mass = np.vstack([mass, np.zeros((20, mass.shape[1]), np.float32)])
    s = normalise(build_graph(pts, 8, nrm), mass, 1e-2)
    res = solve_exact(s)
    P = s.P.toarray().astype(np.float64)
    reach = np.ones(len(pts), bool)
    reach[-20:] = False
    Zs = np.zeros_like(s.B, dtype=np.float64)
    A = np.eye(reach.sum()) - P[np.ix_(reach, reach)]
    Zs[reach] = np.linalg.solve(A, s.B[reach].astype(np.float64))
    np.testing.assert_allclose(res.Z, Zs, rtol=1e-4, atol=1e-7 * Zs.max())
    assert res.residual < 1e-8 and res.converged and res.info["method"] == "splu"
    assert (labels_from_scores(res.Z)[-20:] == -1).all()
    # Jacobi converges to the same fixed point
    jac = diffuse(s, max_iter=20000, tol=1e-9)
    np.testing.assert_allclose(jac.Z, res.Z, rtol=1e-2, atol=1e-6 * Zs.max())


def test_solver_config_dispatch(small_demo_scene):
    from diffuser_lab.runs.pipeline import run

    res = run(default_config(**{"solver.name": "exact"}), scene=small_demo_scene)
    # 2.8e-6 on the demo at 7 cm: points tied to the evidence by edges of weight ~1e-20 make I - P
    # nearly singular there; LU with iterative refinement stays at that floor (measured)
    assert res.diffusion.info["solver"] == "exact" and res.diffusion.residual < 1e-5
    assert res.metrics["miou"] > 0
    cfg = default_config(**{"solver.backend": "scipy", "solver.max_iter": 5})
    pts, nrm, mass = cloud(300)
    s = normalise(build_graph(pts, 8, nrm), mass, 1e-4)
    assert solve(s, cfg.solver).info["backend"] == "scipy"


def test_torch_code_path_on_cpu():
    """The torch backend behind the one diffusion loop, on the CPU: the same steps as scipy
    (float32 sums in another order), the same early stop, observers called as on the CPU."""
    pytest.importorskip("torch", reason="torch is not installed: the test extra leaves it out (PyPI's default "
                                  "torch is a multi-GB CUDA build); `pip install torch` (a CPU build will do) and this runs")
    pts, nrm, mass = cloud(500)
    s = normalise(build_graph(pts, 8, nrm), mass, 1e-4)
    seen = {}
    a = diffuse(s, max_iter=40, tol=0, backend="torch", device="cpu",
                observer=lambda it, Z, st: seen.__setitem__(it, Z.copy()))
    b = diffuse(s, max_iter=40, tol=0, backend="scipy")
    np.testing.assert_allclose(a.Z, b.Z, rtol=1e-4, atol=1e-9 * b.Z.max())
    np.testing.assert_array_equal(seen[40], a.Z)
    assert sorted(seen) == list(range(1, 41)) and a.info["backend"] == "torch" and a.info["device"] == "cpu"
    early_a = diffuse(s, max_iter=400, tol=1e-3, backend="torch", device="cpu")
    early_b = diffuse(s, max_iter=400, tol=1e-3, backend="scipy")
    assert early_a.converged and abs(early_a.iterations - early_b.iterations) <= 1
    np.testing.assert_allclose(early_a.residuals[:5], early_b.residuals[:5], rtol=1e-3)


def test_torch_backend_or_a_clear_error():
    from diffuser_lab.backends.torch import cuda_available

    pts, nrm, mass = cloud(500)
    s = normalise(build_graph(pts, 8, nrm), mass, 1e-4)
    if not cuda_available():
        with pytest.raises(RuntimeError, match="solver.backend=torch: "):
            diffuse(s, max_iter=5, backend="torch")
        pytest.skip("no CUDA GPU: the torch backend stops with a one-line error")
    a = diffuse(s, max_iter=50, tol=0, backend="torch")
    b = diffuse(s, max_iter=50, tol=0, backend="scipy")
    np.testing.assert_allclose(a.Z, b.Z, rtol=1e-4, atol=1e-9 * b.Z.max())


@needs_numba
def test_compiled_evidence_equals_numpy(small_demo_scene, monkeypatch):
    from diffuser_lab.data.predictions import with_predictions

    cfg = default_config()
    frames = list(with_predictions(small_demo_scene.frames, cfg.predictions, small_demo_scene.taxonomy))
    fast = accumulate(small_demo_scene.points, frames, 20)
    monkeypatch.setattr(nb, "NB", None)
    slow = accumulate(small_demo_scene.points, frames, 20)
    same_rows = np.all(fast.mass == slow.mass, axis=1)
    assert same_rows.mean() >= 0.999  # float64 vs float32 projection: rare rounding at pixel borders
    assert abs(sum(fast.points_per_frame) - sum(slow.points_per_frame)) <= 0.001 * sum(slow.points_per_frame)


@needs_numba
def test_generated_kernels_are_up_to_date():
    assert kernels._GEN.read_text() == kernels.generate_source()


def test_bench_cli(tmp_path, capsys):
    from diffuser_lab.cli.bench import main

    pts, nrm, mass = cloud(500)
    np.savez(tmp_path / "in.npz", points=pts, normals=nrm, evidence=mass)
    out = tmp_path / "labels.npy"
    assert main(["--input", str(tmp_path / "in.npz"), "--iters", "20", "--k", "8", "--out", str(out)]) == 0
    line = json.loads(capsys.readouterr().out.strip())
    assert {"n_points", "graph_s", "diffusion_s", "total_s", "iterations"} <= set(line)
    assert line["n_points"] == 500 and line["iterations"] == 20
    lab = np.load(out)
    assert main(["--input", str(tmp_path / "in.npz"), "--iters", "20", "--k", "8", "--solver", "reference",
                 "--out", str(tmp_path / "ref.npy")]) == 0
    assert np.mean(np.load(tmp_path / "ref.npy") == lab) >= 0.999
    assert main(["--input", str(tmp_path / "missing.npz")]) == 2


@needs_numba
@pytest.mark.parametrize("threads", [2, 3])
def test_threaded_steps_equal_one_thread_exactly(threads):
    """Rows are independent within a step, so splitting them over threads (small chunks, many
    barriers inside one compiled call) changes nothing; step by step equals all at once."""
    pts, nrm, mass = cloud(3000)
    s = normalise(build_graph(pts, 12, nrm), mass, 1e-4)
    nbr, wts = s.sorted_neighbors, s.sorted_P
    B = np.zeros((len(pts), 8), np.float32)
    B[:, :5] = s.B[s.order] / s.B.max()
    out = []
    for th, one_at_a_time in ((1, True), (threads, True), (threads, False)):
        Z, Zn = np.zeros_like(B), np.zeros_like(B)
        with kernels.StepRunner(len(pts), threads=th, min_rows_per_thread=1, chunk=97) as runner:
            assert runner.threads == th
            if one_at_a_time:
                for _ in range(30):
                    ch, tp = runner.step(8, nbr, wts, Z, Zn, B, 1e-18)
                    Z, Zn = Zn, Z
                per_step = None
            else:
                per_step = runner.run(8, nbr, wts, Z, Zn, B, 1e-18, -1.0, 30)
                assert per_step.shape == (30, 2)
                ch, tp = per_step[-1]  # 30 steps: the last state is back in Z
        out.append((Z, float(ch), float(tp)))
    for o in out[1:]:
        np.testing.assert_array_equal(out[0][0], o[0])
        assert out[0][1:] == o[1:]


@needs_numba
def test_compiled_runner_stops_where_the_python_loop_would():
    """All threads stop after the first step whose relative change is <= tol; diffuse() reports
    the same iterations, residuals and Z with and without an observer splitting the run."""
    pts, nrm, mass = cloud(3000)
    s = normalise(build_graph(pts, 12, nrm), mass, 1e-4)
    full = diffuse(s, max_iter=400, tol=0.0, backend="numba")
    r = full.residuals
    assert r[56] > r[57] * 1.001  # still falling by more than the backends' rounding differs
    tol = float(np.sqrt(r[56] * r[57]))  # between steps 57 and 58: the first step at or under it is 58
    a = diffuse(s, max_iter=400, tol=tol, backend="numba")
    seen = []
    b = diffuse(s, max_iter=400, tol=tol, backend="numba", observer=lambda it, Z, st: seen.append(it))
    assert a.converged and a.iterations == b.iterations == 58 and seen == list(range(1, 59))
    assert a.residuals == b.residuals == r[:58]
    np.testing.assert_array_equal(a.Z, b.Z)
    sc = diffuse(s, max_iter=400, tol=tol, backend="scipy")
    # scipy's float32 sums run in another order: its residuals agree to ~1e-6, far inside the margin
    np.testing.assert_allclose(sc.residuals, r[:len(sc.residuals)], rtol=1e-4)
    assert sc.iterations == 58


def test_fixed_rows_pads_short_rows_with_zero_weight():
    import scipy.sparse as sp

    P = sp.csr_matrix(np.array([[0, 0.5, 0.2], [0.3, 0, 0], [0, 0, 0]], np.float32))
    nbr, wts = kernels.fixed_rows(P.indptr.astype(np.int64), P.indices.astype(np.int32), P.data)
    assert nbr.shape == (3, 2) and wts.dtype == np.float32
    dense = np.zeros((3, 3), np.float32)
    np.add.at(dense, (np.repeat(np.arange(3), 2), nbr.ravel()), wts.ravel())
    np.testing.assert_array_equal(dense, P.toarray())


@needs_numba
def test_more_classes_than_one_kernel_block_stop_where_scipy_does():
    """Above 32 active classes the numba path runs several 16-wide class blocks in one compiled
    call under one residual: same iterations and labels as scipy's CSR products; an observer
    splitting the run (a call per step) changes nothing."""
    pts, nrm, mass = cloud(3000)
    rng = np.random.default_rng(1)
    wide = np.concatenate([mass] + [mass[rng.permutation(len(pts))] for _ in range(8)], 1)  # 45 columns, 36 voted for
    s = normalise(build_graph(pts, 12, nrm), wide, 1e-4)
    assert s.B.any(0).sum() > 32
    r = diffuse(s, max_iter=60, tol=0.0, backend="numba").residuals
    tol = 0.5 * (r[56] + r[57])  # halfway between steps 57 and 58: both stop at 58
    a = diffuse(s, max_iter=400, tol=tol, backend="numba")
    b = diffuse(s, max_iter=400, tol=tol, backend="scipy")
    assert a.converged and a.iterations == b.iterations == 58
    np.testing.assert_allclose(a.Z, b.Z, rtol=0, atol=1e-5 * float(b.Z.max()))
    assert np.mean(labels_from_scores(a.Z) == labels_from_scores(b.Z)) >= 0.999
    seen = []
    c = diffuse(s, max_iter=400, tol=tol, backend="numba", observer=lambda it, Z, st: seen.append(it))
    assert seen == list(range(1, 59)) and c.residuals == a.residuals
    np.testing.assert_array_equal(a.Z, c.Z)


@needs_numba
def test_several_blocks_on_threads_equal_one_thread_exactly():
    """Three class blocks in one ``steps_W`` call, rows claimed 97 at a time by 1 or 3 threads: the same Z."""
    pts, nrm, mass = cloud(3000)
    s = normalise(build_graph(pts, 12, nrm), mass, 1e-4)
    W = kernels.MULTI_WIDTH
    rng = np.random.default_rng(0)
    B = np.zeros((3, len(pts), W), np.float32)
    B[..., :5] = np.stack([s.B[s.order][rng.permutation(len(pts))] for _ in range(3)]) / s.B.max()
    out = []
    for th in (1, 3):
        Z, Zn = np.zeros_like(B), np.zeros_like(B)
        with kernels.StepRunner(len(pts), threads=th, min_rows_per_thread=1, chunk=97) as runner:
            args = (s.sorted_neighbors, s.sorted_P, Z.reshape(3, -1), Zn.reshape(3, -1), B.reshape(3, -1),
                    np.float32(1e-18), -1.0, kernels.EVERY_ROW)
            res = runner.launch(kernels._multi_kernel(), args, 30, 2)
        assert res.shape == (30, th, 2)
        out.append((Z.copy(), res.max(axis=1)))
    np.testing.assert_array_equal(out[0][0], out[1][0])
    np.testing.assert_array_equal(out[0][1], out[1][1])
    assert out[0][0][..., 5:].max() == 0 and out[0][0].max() > 0


@needs_numba
def test_no_evidence_at_all_leaves_z_at_zero():
    """No class has evidence (no frame sees a point): the numba path, like scipy's, stops at once
    with Z = 0 and every point unlabeled."""
    pts, nrm, mass = cloud(3000)
    s = normalise(build_graph(pts, 12, nrm), np.zeros_like(mass), 1e-4)
    for backend in ("numba", "scipy"):
        r = diffuse(s, max_iter=50, tol=1e-3, backend=backend)
        assert not r.Z.any() and (labels_from_scores(r.Z) < 0).all(), backend


@needs_numba
@pytest.mark.parametrize("W", [16, 32])
@pytest.mark.parametrize("region", [False, True])
def test_explicit_vector_blocks_equal_the_generated_kernel_bit_for_bit(W, region):
    """Several blocks: the step loop over :mod:`backends.numba._zmm`'s 16-lane row kernel (issue 53,
    ``steps_Wz``) gives the generated (SLP) kernel's Z and residuals exactly, rows claimed 97 at a time
    by 2 threads, or a region's runs of rows."""
    from diffuser_lab.backends.numba import _unrolled
    from diffuser_lab.backends.base import row_runs
    pts, nrm, mass = cloud(3000)
    s = normalise(build_graph(pts, 12, nrm), mass, 1e-4)
    rng = np.random.default_rng(1)
    B = np.zeros((3, len(pts), W), np.float32)
    B[..., :W - 3] = rng.random((3, len(pts), W - 3), dtype=np.float32) * (rng.random((3, len(pts), 1)) < 0.1)
    rows = np.unique(np.r_[np.arange(200, 1300), rng.integers(0, len(pts), 300)])
    runs = row_runs(rows, 97) if region else kernels.EVERY_ROW
    out = []
    for f, stats in ((getattr(_unrolled, f"steps_{W}"), (runs, *kernels.untracked(25, 2))),
                     (getattr(_unrolled, f"steps_{W}z"), (runs,))):
        Z, Zn = np.zeros_like(B), np.zeros_like(B)
        with kernels.StepRunner(len(pts), threads=2, min_rows_per_thread=1, chunk=97) as runner:
            args = (s.sorted_neighbors, s.sorted_P, Z.reshape(3, -1), Zn.reshape(3, -1), B.reshape(3, -1),
                    np.float32(1e-18), -1.0, *stats)  # the generated kernel's statistics: none tracked
            res = runner.launch(f, args, 25, 2)
        out.append((Zn.copy(), res.max(axis=1)))
    np.testing.assert_array_equal(out[0][0], out[1][0])
    np.testing.assert_array_equal(out[0][1], out[1][1])
    assert out[0][0].max() > 0 and out[0][0][..., W - 3:].max() == 0
