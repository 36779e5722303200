"""What a user extends is a registry entry: scene sources (diffuser_lab/data/sources), prediction
sources (diffuser_lab/data/predictions.py) and protocols (diffuser_lab/runs/protocols.py),
as fusion methods are. A source registered at run time runs through every protocol with no other code."""
import dataclasses

import numpy as np
import pytest

from diffuser_lab.config import ConfigError, SceneConfig, Section, at_least, key, within
from diffuser_lab.data import predictions, sources
from diffuser_lab.data.frames import LazyFrames
from diffuser_lab.data.scene import Scene
from diffuser_lab.data.sources.demo import make_demo_scene
from diffuser_lab.runs import report
from diffuser_lab.runs.protocols import PROTOCOLS
from diffuser_lab.runs.resolve import default_config

ROOM = {"seed": 1, "n_views": 6, "image_width": 64, "image_height": 48, "point_spacing": 0.1}
RUN = {"solver.max_iter": 30, "record.mode": "off", "protocol.max_targets": 2, "protocol.window": 3,
       "online.compare_batch": False, "online.rate": 0.0}  # online labels compared exactly: no wall-clock idle steps


@pytest.fixture
def tiny(monkeypatch):
    """A scene source ``tiny`` registered at run time: a small room (points, normals, ground-truth
    labels; frames with depth and ground-truth label images), its settings in ``scene.options``;
    and a prediction source ``oracle`` (the ground-truth label images)."""
    monkeypatch.setattr(sources, "SOURCES", sources.SOURCES.copy())
    monkeypatch.setattr(predictions, "SOURCES", predictions.SOURCES.copy())
    seen = []

    def load(cfg: SceneConfig, taxonomy, sensor) -> Scene:
        seen.append(dict(cfg.options))
        room, _ = make_demo_scene(**{k: cfg.options[k] for k in ROOM})
        frames = list(room.frames)  # a source may hand any sequence of frames
        return Scene(name="tiny", points=room.points, taxonomy=taxonomy, normals=room.normals,
                     gt_labels=room.gt_labels, frames=LazyFrames(len(frames), frames.__getitem__))

    def oracle(frames, cfg, taxonomy, scene_name):
        return LazyFrames.mapped(frames, lambda i, f: dataclasses.replace(f, labels=f.gt_labels, probs=None))

    sources.register(sources.SceneSource("tiny", "a test's room", load))
    predictions.register(predictions.PredictionSource("oracle", "ground truth, by another name", oracle,
                                                      lambda cfg: "oracle 2D labels"))
    return seen


def test_a_source_registered_at_run_time_runs_every_protocol(tiny, tmp_path):
    cfg = default_config(**{"scene.source": "tiny", "scene.options": ROOM, "predictions.source": "oracle", **RUN})
    demo = default_config(**{**{f"scene.options.{k}": v for k, v in ROOM.items()}, "predictions.source": "gt", **RUN})
    for name in ("global_3d", "single_frame", "online"):
        protocol = PROTOCOLS[name]
        res = protocol.run(cfg)
        same = protocol.run(demo)  # the built-in demo source with the same room and perfect labels
        assert res.scene.name == "tiny"
        # what the command line does with the result: its files, summary.json and table
        (tmp_path / name).mkdir()
        summary = report.SummaryFile(tmp_path / name, [])
        done = protocol.finish(res, cfg, tmp_path / name, summary, {})
        assert done["status"] == "ok" and done["scene"] == "tiny" and done["metrics"]["miou"] > 50
        assert "tiny" in protocol.table(res, tmp_path / name)
        if name == "global_3d":
            np.testing.assert_array_equal(res.labels, same.labels)
            assert (tmp_path / name / "labels.npy").is_file()
        elif name == "single_frame":
            assert res.rows == same.rows
        else:
            np.testing.assert_array_equal(res.labels, same.labels)
    assert tiny == [ROOM] * 3  # the loader read its keys from scene.options, once per run


def test_registry_names_are_checked_in_one_line(tiny):
    names = ", ".join(sources.SOURCES.names())
    assert names.startswith("demo, mesh_views, scannet, rgbd_folder, tum, ") and names.endswith(", tiny")
    with pytest.raises(ConfigError, match=rf"^scene\.source='nope': expected one of {names}$"):
        default_config(**{"scene.source": "nope"})
    with pytest.raises(ConfigError, match=r"^predictions\.source='nope': expected one of simulated, gt, files, "
                                          r"model, onnx, features, oracle$"):
        default_config(**{"predictions.source": "nope"})
    with pytest.raises(ValueError, match="already registered"):
        sources.register(sources.SceneSource("demo", "another demo", sources.SOURCES["demo"].load))


@dataclasses.dataclass
class RoomKeys(Section):
    """A registered source's own keys, declared as every key is (types, defaults, ranges)."""

    KEY = "scene.options"
    seed: int = 0
    n_views: int = key(6, at_least(1))
    point_spacing: float = key(0.1, within(0.02, 0.5, "metres"))


def test_a_registered_source_declares_its_keys(monkeypatch):
    """A source's own keys as a dataclass in its entry: scene.options arrives typed, with its
    defaults, and a value out of range or a key it does not have stops with one line."""
    monkeypatch.setattr(sources, "SOURCES", sources.SOURCES.copy())
    got = []

    def load(cfg: SceneConfig, taxonomy, sensor) -> Scene:
        got.append(cfg.options)
        room, _ = make_demo_scene(seed=cfg.options.seed, n_views=cfg.options.n_views, image_width=64, image_height=48,
                                  point_spacing=cfg.options.point_spacing)
        return Scene(name="keyed", points=room.points, taxonomy=taxonomy, normals=room.normals,
                     gt_labels=room.gt_labels, frames=room.frames)

    sources.register(sources.SceneSource("keyed", "a room with declared keys", load, options=RoomKeys))
    cfg = default_config(**{"scene.source": "keyed", "scene.options": {"n_views": "4"}, **RUN})
    assert cfg.scene.options == RoomKeys(seed=0, n_views=4, point_spacing=0.1)  # "4" typed, defaults filled
    res = PROTOCOLS["global_3d"].run(cfg)
    assert res.scene.name == "keyed" and len(res.frames) == 4 and got == [cfg.scene.options]
    with pytest.raises(ConfigError, match=r"^scene\.options\.point_spacing=1\.0: expected in \[0\.02, 0\.5\] metres$"):
        default_config(**{"scene.source": "keyed", "scene.options": {"point_spacing": 1.0}})
    with pytest.raises(ConfigError, match=r"^scene\.options\.colour: "):
        default_config(**{"scene.source": "keyed", "scene.options": {"colour": 1}})
