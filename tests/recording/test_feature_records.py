"""Records of a features run (issue 37, item 5): the PCA-to-RGB projection and a query's
similarity per recorded iteration in run.rrd and run.mcap, small, never changing the result."""
import json

import numpy as np
import pytest
from conftest import run_cli

from diffuser_lab.cli.inspect import main as inspect_main
from diffuser_lab.config import default_config
from diffuser_lab.recording import make_hooks
from diffuser_lab.recording import features as fv
from diffuser_lab.recording.mcap_encode import TOPIC_FEATURE_VIEW, TOPIC_FEATURES
from diffuser_lab.runs.pipeline import run

SMALL = {"scene.options.n_views": 12, "scene.options.point_spacing": 0.07, "predictions.source": "features",
         "predictions.dim": 64, "solver.max_iter": 40}


def rrd_colors(path, entity):
    """{diffusion_step: (M,) uint32 colours} of ``entity`` in a .rrd."""
    from rerun.chunk import RrdReader

    out = {}
    for ch in RrdReader(path).stream():
        if ch.entity_path == entity and not ch.is_static:
            rb = ch.to_record_batch()
            if "Points3D:colors" not in rb.schema.names:
                continue
            for step, c in zip(rb.column("diffusion_step").to_pylist(), rb.column("Points3D:colors").to_pylist()):
                out[step] = np.asarray(c, np.uint32)
    return out


def mcap_features(path):
    """(FeatureView message, {iteration: FeatureColors message}) of a run.mcap."""
    from mcap.reader import make_reader

    from diffuser_lab.recording import schema

    view, steps = None, {}
    with open(path, "rb") as fh:
        for _s, ch, msg in make_reader(fh).iter_messages(topics=[TOPIC_FEATURE_VIEW, TOPIC_FEATURES]):
            if ch.topic == TOPIC_FEATURE_VIEW:
                view = schema.FeatureView.FromString(msg.data)
            else:
                m = schema.FeatureColors.FromString(msg.data)
                steps[m.iteration] = m
    return view, steps


def test_projection_is_fixed_grey_without_features_and_the_query_is_checked():
    rng = np.random.default_rng(1)
    mass = rng.normal(size=(500, 16)).astype(np.float32)
    mass[:50] = 0  # unseen
    q = rng.normal(size=(3, 16)).astype(np.float32)
    v = fv.fit_view(mass, ["a", "b", "c"], q, "b", max_rows=200)
    assert v.query == "b" and v.basis.shape == (3, 16) and v.n_fit == 200
    np.testing.assert_allclose(np.linalg.norm(v.basis, axis=1), 1, atol=1e-5)
    rgb, sim = fv.project(v, mass)
    assert rgb.dtype == np.uint8 and rgb.shape == (500, 3) and (rgb[:50] == fv.GREY).all()
    assert (sim[:50] == fv.NO_FEATURE).all() and (sim[50:] <= fv.SIM_STEPS).all()
    rgb2, sim2 = fv.project(v, 3.0 * mass)  # sums or unit rows: the same colours
    assert np.abs(rgb2.astype(int) - rgb).max() <= 1 and np.abs(sim2.astype(int) - sim).max() <= 1
    cos = (mass[50:] / np.linalg.norm(mass[50:], axis=1, keepdims=True)) @ (q[1] / np.linalg.norm(q[1]))
    got = fv.similarity_values(v, sim)[50:]
    inside = (cos > v.sim_lo) & (cos < v.sim_hi)
    assert np.abs(got[inside] - cos[inside]).max() <= (v.sim_hi - v.sim_lo) / fv.SIM_STEPS
    assert fv.fit_view(mass, ["a", "b", "c"], q, max_rows=200).query == "a"  # default: the first
    with pytest.raises(ValueError, match="record.query='chiar'.*its queries: a, b, c"):
        fv.fit_view(mass, ["a", "b", "c"], q, "chiar")


def test_a_features_run_records_its_projection_and_labels_do_not_change(small_demo_scene, tmp_path):
    cfg = default_config(**SMALL, **{"record.query": "chair"})
    hooks = make_hooks(cfg, tmp_path)
    try:
        res = run(cfg, scene=small_demo_scene, hooks=hooks)
    finally:
        hooks.close()
    off = run(default_config(**SMALL, **{"record.mode": "off"}), scene=small_demo_scene)
    np.testing.assert_array_equal(res.labels, off.labels)  # recording never changes the result
    assert res.space.basis_info["kind"] == "auto"  # 64-D: a reduced basis, the records lifted to R^D
    np.testing.assert_array_equal(res.space.method.coords, off.space.method.coords)
    M = len(res.work_points)
    view, steps = mcap_features(tmp_path / "run.mcap")
    assert view is not None and view.query == "chair" and view.dim == 64
    assert sorted(steps) == list(hooks.recorded) and hooks.recorded[-1] == res.diffusion.iterations
    last = steps[res.diffusion.iterations]
    # the basis in the file (in R^D) reproduces the last colours from the features in R^D
    rgb, sim = fv.project(fv.feature_view_of(view), res.space.unit_rows(res.space.method).astype(np.float32))
    assert np.abs(np.frombuffer(last.rgb, np.uint8).reshape(M, 3).astype(int) - rgb).max() <= 1
    assert np.abs(np.frombuffer(last.similarity, np.uint8).astype(int) - sim).max() <= 1
    pca = rrd_colors(tmp_path / "run.rrd", "/world/features")
    heat = rrd_colors(tmp_path / "run.rrd", "/world/query/chair")
    assert sorted(pca) == sorted(heat) == list(hooks.recorded)
    red = pca[res.diffusion.iterations] >> 24  # 0xRRGGBBAA
    assert len(red) == M and np.abs(red.astype(int) - rgb[:, 0]).max() <= 1
    assert inspect_main([str(tmp_path), "--to-rrd", str(tmp_path / "re.rrd")]) == 0  # re-logged from run.mcap
    again = rrd_colors(tmp_path / "re.rrd", "/world/features")
    assert sorted(again) == sorted(pca) and all((again[k] == pca[k]).all() for k in pca)
    assert sorted(rrd_colors(tmp_path / "re.rrd", "/world/query/chair")) == sorted(pca)


def test_an_unknown_query_is_one_error_before_the_run(small_demo_scene, tmp_path):
    cfg = default_config(**SMALL, **{"record.query": "chiar"})
    hooks = make_hooks(cfg, tmp_path)
    try:
        with pytest.raises(ValueError, match="record.query='chiar': no such query"):
            run(cfg, scene=small_demo_scene, hooks=hooks)
    finally:
        hooks.close()


@pytest.mark.slow
def test_the_demos_features_records_stay_under_300_bytes_a_point(tmp_path):
    """``diffuser-lab predictions=features`` (D = 512, default records): run.rrd and run.mcap
    each under 300 bytes a diffused point, the rrd with the features entity."""
    d = tmp_path / "run"
    p = run_cli("predictions=features", "output.quiet=true", f"hydra.run.dir={d}")
    assert p.returncode == 0, p.stderr
    s = json.loads((d / "summary.json").read_text())
    M = s["n_points_diffused"]
    for name in ("run.rrd", "run.mcap"):
        per_point = (d / name).stat().st_size / M
        assert per_point < 300, f"{name}: {per_point:.0f} bytes a point"
    pca = rrd_colors(d / "run.rrd", "/world/features")
    assert sorted(pca) == [1, 2, 5, 10, 20, 50, 100, 200] and all(len(c) == M for c in pca.values())
    view, steps = mcap_features(d / "run.mcap")
    assert view.dim == 512 and sorted(steps) == sorted(pca)
