"""The resolve step: a validated :class:`~diffuser_lab.config.Config` -> the config that runs.

Validation (:mod:`diffuser_lab.config`) checks every key against its declared range; this step,
after it, checks what only the registries know and applies what the fusion method fixes:

- the names of registry entries: ``scene.source`` (:mod:`diffuser_lab.data.sources`),
  ``taxonomy.name`` (the shipped taxonomies, ``file``, ``ids``), ``predictions.source``
  (:mod:`diffuser_lab.data.predictions`), ``method.name`` (:mod:`diffuser_lab.method.fusion`) and,
  when the caller hands in the protocols' registry, ``protocol.name``: one line naming the key and
  the registered names;
- the method's fixed keys (LDLS: ``graph.use_normals=false``, ``evidence.pixel_radius=1``), so the
  config a run records is the one that ran.

:func:`resolve` is idempotent and returns a new config (the sections it changes are copies). The
command line resolves in its pre-validation and in the job; the library's entry points
(:func:`diffuser_lab.runs.pipeline.run`, the single-frame and online protocols) resolve what
they are handed, so a config from :func:`diffuser_lab.config.default_config` runs as it always
did; :func:`default_config` here (``diffuser_lab.default_config``) returns it resolved.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Optional

from diffuser_lab import config
from diffuser_lab.config import Config, check_name
from diffuser_lab.data import predictions, sources
from diffuser_lab.data.taxonomy import taxonomy_names
from diffuser_lab.method import fusion

__all__ = ["resolve", "with_method", "with_options", "names", "default_config"]


def names(protocols: Optional[Mapping[str, Any]] = None) -> dict[str, list[str]]:
    """Each key that names a registry entry -> the names it takes now (what :func:`resolve`
    accepts, in the order its error line lists them: a registry's own order, the fusion methods
    sorted, the shipped taxonomies sorted then ``file``, ``ids``); ``protocol.name`` when
    ``protocols`` is given."""
    out = {"scene.source": sources.SOURCES.names(), "taxonomy.name": taxonomy_names(),
           "predictions.source": predictions.SOURCES.names(), "method.name": fusion.METHODS.names()}
    if protocols is not None:
        out["protocol.name"] = protocols.names() if hasattr(protocols, "names") else list(protocols)
    return out


def with_method(cfg: Config, name: str) -> Config:
    """``cfg`` running the fusion method ``name`` with what that method fixes applied (the
    single-frame protocol's rows run every method on one config this way)."""
    out = dataclasses.replace(cfg, method=dataclasses.replace(cfg.method, name=name),
                              graph=dataclasses.replace(cfg.graph), evidence=dataclasses.replace(cfg.evidence))
    fusion.get(name).apply(out)
    return out


def resolve(cfg: Config, protocols: Optional[Mapping[str, Any]] = None) -> Config:
    """Check the registry names of ``cfg`` (:func:`names`; ``protocols``: the protocols' registry,
    for ``protocol.name``) and apply the method's fixed keys. Raises
    :class:`~diffuser_lab.config.ConfigError` naming the first unknown name."""
    for key, valid in names(protocols).items():
        section, attr = key.split(".")
        check_name(key, getattr(getattr(cfg, section), attr), valid)
    cfg = with_options(cfg)
    _check_protocol_keys(cfg)
    _check_follow(cfg)
    return with_method(cfg, cfg.method.name)


LIFTING_PROTOCOLS = fusion.LIFTING_PROTOCOLS
"""The protocols that run the lifting rules (method/lifters.py), ``graph.affinity`` and ``solver.tikhonov``."""


def _check_protocol_keys(cfg: Config) -> None:
    """The lifting rules, ``graph.affinity`` and ``solver.tikhonov`` run in the global and the
    single-frame protocol, ``output.scores`` in the global one; elsewhere one line says so (rather than
    a run that ignores them)."""
    if cfg.output.scores and cfg.protocol.name != "global_3d":
        raise config.ConfigError(f"output.scores=true: scores.npy is written by protocol=global_3d, not "
                                 f"protocol={cfg.protocol.name}")
    if cfg.protocol.name in LIFTING_PROTOCOLS:
        return
    what = []
    if not fusion.get(cfg.method.name).runs_in(cfg.protocol.name):  # a lifting rule
        what.append(f"method.name={cfg.method.name}")
    if cfg.graph.affinity != config.GraphAffinity.none:
        what.append(f"graph.affinity={cfg.graph.affinity.value}")
    if cfg.solver.tikhonov > 0:
        what.append(f"solver.tikhonov={cfg.solver.tikhonov:g}")
    if what:
        raise config.ConfigError(f"{', '.join(what)}: runs in protocol={' or '.join(LIFTING_PROTOCOLS)}, "
                                 f"not protocol={cfg.protocol.name}")


def _check_follow(cfg: Config) -> None:
    """``scene.options.follow=true`` (a capture followed as a recorder writes it) runs in the online
    protocol, on a growing map or the given map of ``scene.options.cloud`` (no cloud can be fused from
    frames not written yet); elsewhere one line says so."""
    o = cfg.scene.options
    if not getattr(o, "follow", False):
        return
    if cfg.protocol.name != "online":
        raise config.ConfigError(f"scene.options.follow=true: a capture is followed in protocol=online, not "
                                 f"protocol={cfg.protocol.name}")
    if cfg.online.map == config.OnlineMap.given and not getattr(o, "cloud", None):
        raise config.ConfigError("scene.options.follow=true with online.map=given: expected scene.options.cloud (the "
                                 "map to label: PLY / LAS / LAZ); online.map=growing builds the map from the frames")


def with_options(cfg: Config) -> Config:
    """``scene.options`` as the dataclass its scene source declares (:attr:`SceneSource.options`):
    typed, defaults filled, ranges checked; one line naming ``scene.options.<key>`` otherwise."""
    scene = sources.typed_options(cfg.scene)
    return cfg if scene is cfg.scene else dataclasses.replace(cfg, scene=scene)


def default_config(**overrides: Any) -> Config:
    """A validated and resolved default :class:`~diffuser_lab.config.Config` for library use;
    ``overrides`` as dotted keys, e.g. ``default_config(**{"graph.k": 8})``."""
    return resolve(config.default_config(**overrides))
