"""scene.voxel_size=auto's rule (data/geometry.py voxel_edge): VOXEL_RHO x the cloud's spacing rho."""
import numpy as np
import pytest

from diffuser_lab.data.geometry import VOXEL_RHO, point_spacing, voxel_edge
from diffuser_lab.method.graph import knn, mean_spacing


def _grid(step: float) -> np.ndarray:
    g = np.arange(40) * step
    x, y = np.meshgrid(g, g)
    return np.c_[x.ravel(), y.ravel(), np.zeros(x.size)].astype(np.float32)


def test_the_spacing_of_a_grid_is_its_step_and_duplicates_are_skipped():
    p = _grid(0.05)
    assert point_spacing(p) == pytest.approx(0.05, rel=1e-5)
    assert point_spacing(np.r_[p, p[:500]]) == pytest.approx(0.05, rel=1e-5)  # a duplicate's nearest distinct
    assert voxel_edge("auto", p) == pytest.approx(VOXEL_RHO * 0.05, rel=1e-5)


def test_a_sample_agrees_with_the_graphs_rho():
    p = np.random.default_rng(1).random((60_000, 3)).astype(np.float32)
    p[:, 2] *= 0.01  # a thin slab: surface-like spacing
    rho = mean_spacing(knn(p, 4)[0])
    assert point_spacing(p, sample=10_000) == pytest.approx(rho, rel=0.03)
    assert point_spacing(p, sample=10_000) != point_spacing(p, sample=10_000, seed=5)  # a sample, not all


def test_numbers_pass_and_bad_values_are_named():
    assert voxel_edge(0.04, _grid(1.0)) == 0.04 and voxel_edge(0, _grid(1.0)) == 0.0
    for bad in ("big", -0.1, float("nan")):
        with pytest.raises(ValueError, match="expected metres"):
            voxel_edge(bad, _grid(1.0))
    with pytest.raises(ValueError, match="coincide"):
        point_spacing(np.zeros((5, 3), np.float32))


def test_scene_voxel_size_auto_runs_as_its_number():
    """``scene.voxel_size=auto`` is the key's value in the schema (typed, checked) and a run with it
    gives the labels of a run with the number it stands for; a value that is neither says the key."""
    from diffuser_lab.config import ConfigError
    from diffuser_lab.runs.pipeline import load_scene, run
    from diffuser_lab.runs.resolve import default_config

    small = {"scene.options.n_views": 6, "scene.options.point_spacing": 0.08, "solver.max_iter": 30}
    auto = default_config(**small, **{"scene.voxel_size": "auto"})
    edge = voxel_edge("auto", load_scene(auto.scene).points)
    assert 0.1 < edge < 0.3  # 2.7 x the 8 cm demo's spacing
    a = run(auto)
    b = run(default_config(**small, **{"scene.voxel_size": edge}))
    assert a.work_points.shape == b.work_points.shape and (a.labels == b.labels).all()
    for bad in ("big", -1.0):
        with pytest.raises(ConfigError, match="scene.voxel_size"):
            default_config(**{"scene.voxel_size": bad})
