"""Scene sources: the registry :data:`SOURCES`, one entry per source, named by ``scene.source``.

Built in: the demo room (demo.py), the procedural city (city.py: outdoors, cityscapes19), views
rendered from a labelled mesh (mesh_views.py), a ScanNet
export with its mesh (scannet.py), a posed RGB-D folder (rgbd_folder.py), a TUM RGB-D sequence
(tum.py); and the capture formats built on :mod:`diffuser_lab.data.capture`: path templates for any
other layout (templates.py; ScanNet without a mesh and as SensReader writes it are YAMLs of it),
nerfstudio's transforms.json (nerfstudio.py), Replica as NICE-SLAM ships it (replica.py), COLMAP
models (colmap.py), ROS 1 / ROS 2 bags (rosbag.py). Each module has a
``load(cfg, taxonomy, sensor) -> Scene`` that reads ``cfg.options``, an instance of the options
dataclass its entry declares (every source's keys are ``scene.options.KEY``).

Adding a dataset format is one module with such a ``load`` and an options dataclass (extending
:class:`~diffuser_lab.data.capture.CaptureOptions` for a frame-based capture), one
``conf/scene/<name>.yaml`` whose defaults list takes ``- options: <name>`` and says
``source: <name>``, and one registry line: an entry in :data:`SOURCES` below, or, from outside the
package, ``register(SceneSource("<name>", ..., load, options=...))`` before the run. Its keys are then
``scene.options.KEY=VALUE`` on the command line, typed and range-checked; a source without an
options dataclass reads ``scene.options`` as a free-form dict (``+scene.options.KEY=VALUE``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np
from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf
from omegaconf.errors import MissingMandatoryValue, OmegaConfBaseException

from diffuser_lab.config import ConfigError, SceneConfig
from diffuser_lab.data.scene import Frame, Scene, Taxonomy
from diffuser_lab.data.sensor import SensorModel
from diffuser_lab.registry import Registry

from . import city, colmap, demo, mesh_views, nerfstudio, replica, rgbd_folder, rosbag, scannet, templates, tum

__all__ = ["SceneSource", "SOURCES", "register", "get", "typed_options"]


@dataclass(frozen=True)
class SceneSource:
    """One scene source.

    Attributes:
        name: the ``scene.source`` value that selects it.
        description: a few words (docs/config.md's choices).
        load: ``(scene config, taxonomy, sensor) -> Scene`` whose frames carry ground-truth labels
            when known, in ``taxonomy``. ``sensor`` (a :class:`~diffuser_lab.data.sensor.SensorModel`
            or None) is for sources that render their depth (``rendered``); the others may ignore it.
        rendered: the source renders its frames' depth, applying ``sensor`` as it does; otherwise
            the depth is real and ``depth.apply_to_real`` applies the sensor model to the loaded frames.
        label_ids: for ``taxonomy=ids``: ``(scene config, n) -> [(unique label ids, where found)]``
            from the first ``n`` ground-truth label images (or a labelled mesh); None = none.
        options: the dataclass of the source's own keys under ``scene.options`` (a
            :class:`~diffuser_lab.config.Section` with ``KEY = "scene.options"``: types, defaults
            and ranges declared as for every key); the resolve step turns ``scene.options`` into
            it, so ``load`` reads ``cfg.options`` typed and checked. None: a free-form dict.
        frames: ``(scene config, taxonomy, sensor) -> LazyFrames``: the frames alone, as ``load``
            gives them, without building the cloud (a tiled run's workers read only their frames);
            None = ``load(...).frames``.
        generated: a procedural scene, made from its options and ``seed`` alone (no file read):
            summary.json's ``inputs`` names it and its seed (``inputs.generator``).
    """

    name: str
    description: str
    load: Callable[[SceneConfig, Taxonomy, Optional[SensorModel]], Scene]
    rendered: bool = False
    label_ids: Optional[Callable[[SceneConfig, int], list[tuple[np.ndarray, str]]]] = None
    options: Optional[type] = None
    frames: Optional[Callable[[SceneConfig, Taxonomy, Optional[SensorModel]], Sequence[Frame]]] = None
    generated: bool = False


SOURCES: Registry = Registry("scene.source", "scene source", [
    SceneSource("demo", "embedded procedural room", demo.load, rendered=True,
                options=demo.DemoOptions, generated=True),
    SceneSource("mesh_views", "labelled mesh (PLY with per-vertex label) + rendered views", mesh_views.load,
                rendered=True, label_ids=mesh_views.label_ids, options=mesh_views.MeshViewsOptions),
    SceneSource("scannet", "ScanNet export layout (color/ depth/ pose/ intrinsic/ label-filt/ + PLYs)", scannet.load,
                label_ids=scannet.label_ids, options=scannet.ScannetOptions),
    SceneSource("rgbd_folder", "frame-XXXXXX.{color,depth,pose} + camera-intrinsics.txt", rgbd_folder.load,
                label_ids=rgbd_folder.label_ids, options=rgbd_folder.RgbdFolderOptions),
    SceneSource("tum", "TUM RGB-D: rgb.txt depth.txt groundtruth.txt, associated by timestamp", tum.load,
                options=tum.TumOptions),
    SceneSource("rosbag", "ROS 1 .bag / ROS 2 bag (mcap, db3): depth, colour, CameraInfo, tf or a pose topic",
                rosbag.load, options=rosbag.RosbagOptions),
    SceneSource("templates", "any layout: a path template per file kind ({scene}, {frame:06d})", templates.load,
                options=templates.TemplatesOptions),
    SceneSource("nerfstudio", "nerfstudio transforms.json (ns-process-data, Record3D, Polycam, ScanNet++)",
                nerfstudio.load, options=nerfstudio.NerfstudioOptions),
    SceneSource("replica", "Replica as NICE-SLAM ships it: traj.txt + results/ + cam_params.json", replica.load,
                options=replica.ReplicaOptions),
    SceneSource("colmap", "COLMAP sparse model (.bin/.txt) + images (+ MVS depth maps, fused.ply)", colmap.load,
                options=colmap.ColmapOptions),
    SceneSource("city", "embedded procedural outdoor city (cityscapes19), drone and street views", city.load,
                rendered=True, frames=city.frames, options=city.CityOptions, generated=True),
])
"""The scene sources by name (``scene.source``)."""


def _store_options(entry: SceneSource) -> None:
    """A source's keys dataclass as Hydra's ``scene/options`` config ``<name>``: its YAML's defaults
    list takes it (``- options: <name>``), so every key is there, typed, to override without ``+``."""
    if entry.options is not None:
        ConfigStore.instance().store(group="scene/options", name=entry.name, node=entry.options)


for _entry in SOURCES.values():
    _store_options(_entry)


def register(entry: SceneSource) -> SceneSource:
    """Add a scene source (a run started after this may name it)."""
    _store_options(entry)
    return SOURCES.register(entry)


def typed_options(cfg: SceneConfig) -> SceneConfig:
    """``cfg`` with ``options`` as the dataclass its source declares (:attr:`SceneSource.options`):
    typed, defaults filled, ranges checked (``cfg`` itself when they already are, or the source
    reads a free-form dict); one line naming ``scene.options.<key>`` otherwise."""
    kind = get(cfg.source).options
    if kind is None or isinstance(cfg.options, kind):
        return cfg
    try:
        options = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(kind), dict(cfg.options)))
    except OmegaConfBaseException as exc:
        where = f"scene.options.{exc.full_key}" if getattr(exc, "full_key", None) else "scene.options"
        if isinstance(exc, MissingMandatoryValue):  # a required key, as the command line says it
            raise ConfigError(f"{where} is required (pass {where}=...)") from None
        msg = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise ConfigError(f"{where}: {msg}") from None
    return dataclasses.replace(cfg, options=options)


def get(name: str) -> SceneSource:
    """The entry a name names, or one line naming scene.source and the names."""
    return SOURCES.named(name)
