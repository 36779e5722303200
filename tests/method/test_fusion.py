"""The fusion-method registry (diffuser_lab.method.fusion): one entry per method, asked by the
pipeline and the single-frame protocol; the config accepts exactly its names; the library face."""
import numpy as np
import pytest
from conftest import ROOT
from omegaconf import OmegaConf

from diffuser_lab.method import fusion


def test_every_method_has_its_yaml_and_the_yaml_shows_what_the_method_fixes():
    files = {p.stem: p for p in (ROOT / "conf" / "method").glob("*.yaml")}
    assert set(files) == set(fusion.METHODS)
    for name, m in fusion.METHODS.items():
        y = OmegaConf.load(files[name])
        y = y if "method" in y else OmegaConf.create({"method": y})  # @package _global_ or the group's
        assert y.method.name == name
        if m.normals is not None:
            assert y.graph.use_normals == m.normals
        if m.k is not None:
            assert y.graph.k == m.k
        if m.pixel_radius is not None:
            assert y.evidence.pixel_radius == m.pixel_radius


def test_config_takes_the_registry_names_and_applies_what_a_method_fixes():
    from diffuser_lab import default_config
    from diffuser_lab.config import ConfigError

    cfg = default_config(**{"method.name": "ldls", "graph.use_normals": True, "graph.k": 24,
                            "evidence.pixel_radius": 3})
    assert (cfg.graph.use_normals, cfg.graph.k, cfg.evidence.pixel_radius) == (False, 10, 2)  # LDLS's definition
    assert default_config(**{"method.name": "diffuser", "evidence.pixel_radius": 3}).evidence.pixel_radius == 3
    with pytest.raises(ConfigError, match="method.name='foo': expected one of bayesian, diffuser, direct, ldls"):
        default_config(**{"method.name": "foo"})


def test_a_new_method_is_one_registry_entry(monkeypatch):
    """A method added to the registry runs in the pipeline and the single-frame protocol with no
    other code: here Bayesian votes under another name, which must label as `bayesian` does."""
    from diffuser_lab import default_config, run
    from diffuser_lab.runs.single_frame import single_frame

    entry = fusion.FusionMethod("copy_of_bayesian", "the Bayesian baseline, renamed", graph=False,
                                evidence=fusion.BASELINE, multi_view_row=True)
    monkeypatch.setitem(fusion.METHODS, entry.name, entry)
    small = {"scene.options.n_views": 6, "scene.options.point_spacing": 0.1, "record.mode": "off"}
    a = run(default_config(**small, **{"method.name": "copy_of_bayesian"}))
    b = run(default_config(**small, **{"method.name": "bayesian"}))
    assert a.method == "copy_of_bayesian"
    np.testing.assert_array_equal(a.labels, b.labels)
    sf = single_frame(default_config(**small, **{"protocol.max_targets": 2, "protocol.window": 3}))
    rows = {(r["method"], r["views"]): r["miou"] for r in sf.rows}
    assert rows[("copy_of_bayesian", 1)] == rows[("bayesian", 1)]
    assert rows[("copy_of_bayesian", 3)] == rows[("bayesian", 3)]
    assert [k for k in rows if k[0] != "copy_of_bayesian"] == [("direct", 1), ("ldls", 1), ("bayesian", 1),
                                                               ("bayesian", 3), ("diffuser", 1), ("diffuser", 3)]


def test_library_face():
    import diffuser_lab
    from diffuser_lab import Config, Frame, RunResult, Scene, default_config, run

    assert callable(run) and isinstance(default_config(), Config)
    assert Scene.__module__ == "diffuser_lab.data.scene" and Frame.__module__ == "diffuser_lab.data.scene"
    assert RunResult.__module__ == "diffuser_lab.runs.pipeline"
    with pytest.raises(AttributeError):
        diffuser_lab.no_such_name  # noqa: B018
