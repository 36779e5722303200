"""Hydra structured configs: every knob of a run, typed and range-checked.

The dataclasses are registered in Hydra's ConfigStore as ``base_config``; the YAML files
under ``conf/`` fill them. A key that is not declared here, or a value of the wrong type,
fails when Hydra composes the config; ranges are checked in ``__post_init__``, which runs
when :func:`to_object` turns the composed config into these dataclasses.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Any, List, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf


class ConfigError(ValueError):
    """A config value is out of range; the message names the key."""


def _check(ok: bool, key: str, value: Any, expected: str) -> None:
    if not ok:
        raise ConfigError(f"{key}={value!r}: expected {expected}")


class SceneSource(Enum):
    demo = "demo"


class PredictionSource(Enum):
    simulated = "simulated"  # simulated 2D-network mistakes on ground-truth label images
    gt = "gt"  # ground-truth label images (perfect 2D labels)


class MethodName(Enum):
    diffuser = "diffuser"  # paper's method (Eqs. 1-16)
    bayesian = "bayesian"  # per-point sum of pixel likelihoods / votes, argmax
    direct = "direct"  # labels from a single view's projection
    ldls = "ldls"  # distance-only graph + pixel neighbourhood (Wang et al. 2019)


class NormalSign(Enum):
    auto = "auto"  # signed for input normals, invariant for estimated ones
    signed = "signed"  # |n_i - n_j|^2 exactly as Eq. 4
    invariant = "invariant"  # min(|n_i - n_j|^2, |n_i + n_j|^2): normals of arbitrary sign


class SolverName(Enum):
    jacobi = "jacobi"  # the paper's iteration Z <- P Z + Z_IX (Eq. 10)


class BayesianMode(Enum):
    likelihood = "likelihood"  # sum of per-pixel class probabilities (one-hot for hard labels)
    votes = "votes"  # sum of one-hot argmax votes


@dataclass
class DemoSceneConfig:
    """Procedural room (diffuser_lab.sources.demo)."""

    seed: int = 0
    room_size: List[float] = field(default_factory=lambda: [5.0, 4.0, 2.6])  # x, y, z metres
    n_views: int = 30
    image_width: int = 160
    image_height: int = 120
    fov_deg: float = 70.0  # horizontal field of view
    point_spacing: float = 0.04  # metres between sampled surface points
    point_noise: float = 0.002  # std of gaussian position noise, metres

    def __post_init__(self) -> None:
        _check(len(self.room_size) == 3 and min(self.room_size) > 1.0, "scene.demo.room_size",
               self.room_size, "three sizes > 1 m")
        _check(self.n_views >= 1, "scene.demo.n_views", self.n_views, ">= 1")
        _check(self.image_width >= 16 and self.image_height >= 16, "scene.demo.image_width/height",
               (self.image_width, self.image_height), ">= 16 pixels")
        _check(10.0 <= self.fov_deg <= 150.0, "scene.demo.fov_deg", self.fov_deg, "in [10, 150]")
        _check(0.005 <= self.point_spacing <= 0.5, "scene.demo.point_spacing", self.point_spacing,
               "in [0.005, 0.5] metres")
        _check(self.point_noise >= 0.0, "scene.demo.point_noise", self.point_noise, ">= 0")


@dataclass
class SceneConfig:
    source: SceneSource = SceneSource.demo
    demo: DemoSceneConfig = field(default_factory=DemoSceneConfig)
    voxel_size: float = 0.0  # metres; > 0: voxel-downsample before diffusion, labels transferred back

    def __post_init__(self) -> None:
        _check(self.voxel_size >= 0.0, "scene.voxel_size", self.voxel_size, ">= 0 metres (0 = off)")


@dataclass
class PredictionsConfig:
    """What the frames' 2D labels are. The simulated mistakes are documented knob by knob in
    :func:`diffuser_lab.simulate.simulate_predictions` (defaults: 2D mIoU ~58 on the demo)."""

    source: PredictionSource = PredictionSource.simulated
    seed: int = 0
    strength: float = 1.0  # scales every simulated mistake; 0 = perfect labels
    jitter_px: float = 3.0  # std of the smooth boundary displacement field, pixels
    jitter_scale_px: float = 16.0  # its correlation length, pixels
    confuse_prob: float = 0.2  # probability that a connected region gets a wrong class
    confuse_max_frac: float = 0.3  # regions larger than this share of the image are never confused
    blob_count: float = 2.0  # mean number of wrong-class blobs per image (Poisson)
    blob_radius: float = 0.1  # mean blob radius, fraction of the image width
    blob_roughness: float = 0.35  # irregularity of blob outlines, 0 = discs

    def __post_init__(self) -> None:
        _check(self.strength >= 0.0, "predictions.strength", self.strength, ">= 0")
        _check(self.jitter_px >= 0.0, "predictions.jitter_px", self.jitter_px, ">= 0")
        _check(self.jitter_scale_px > 0.0, "predictions.jitter_scale_px", self.jitter_scale_px, "> 0")
        _check(0.0 <= self.confuse_prob <= 1.0, "predictions.confuse_prob", self.confuse_prob, "in [0, 1]")
        _check(0.0 <= self.confuse_max_frac <= 1.0, "predictions.confuse_max_frac", self.confuse_max_frac,
               "in [0, 1]")
        _check(self.blob_count >= 0.0, "predictions.blob_count", self.blob_count, ">= 0")
        _check(self.blob_radius > 0.0, "predictions.blob_radius", self.blob_radius, "> 0")
        _check(self.blob_roughness >= 0.0, "predictions.blob_roughness", self.blob_roughness, ">= 0")


@dataclass
class EvidenceConfig:
    """Pixel-to-point edges (Eqs. 1-2, 11-13)."""

    pixel_weight: float = 1e-4  # the paper's lambda
    depth_tol: float = 0.05  # metres: |z_point - depth(pixel)| <= depth_tol passes the occlusion check
    pixel_radius: int = 0  # link to the (2r+1)^2 pixels around the projection; 0 = paper's choice

    def __post_init__(self) -> None:
        _check(self.pixel_weight > 0.0, "evidence.pixel_weight", self.pixel_weight, "> 0 (paper: 1e-4)")
        _check(self.depth_tol > 0.0, "evidence.depth_tol", self.depth_tol, "> 0 metres")
        _check(0 <= self.pixel_radius <= 10, "evidence.pixel_radius", self.pixel_radius, "in [0, 10]")


@dataclass
class GraphConfig:
    """Point-to-point edges (Eqs. 3-4)."""

    k: int = 24
    use_normals: bool = True  # the normal term of Eq. 4; off = LDLS-like distance-only graph
    sigma_s: float = 0.2
    sigma_d: Optional[float] = None  # metres; None = sigma_d_factor * rho (rho: mean NN spacing)
    sigma_d_factor: float = 2.0
    normal_sign: NormalSign = NormalSign.auto
    normal_knn: int = 16  # neighbours for normal estimation when the input has none

    def __post_init__(self) -> None:
        _check(self.k >= 1, "graph.k", self.k, ">= 1 (paper: 24)")
        _check(self.sigma_s > 0.0, "graph.sigma_s", self.sigma_s, "> 0 (paper: 0.2)")
        _check(self.sigma_d is None or self.sigma_d > 0.0, "graph.sigma_d", self.sigma_d,
               "> 0 metres or null (= sigma_d_factor * rho)")
        _check(self.sigma_d_factor > 0.0, "graph.sigma_d_factor", self.sigma_d_factor, "> 0 (paper: 2)")
        _check(self.normal_knn >= 3, "graph.normal_knn", self.normal_knn, ">= 3")


@dataclass
class SolverConfig:
    """Diffusion (Eq. 10) stopping rule."""

    name: SolverName = SolverName.jacobi
    max_iter: int = 200
    tol: float = 1e-4  # stop when max|Z_t - Z_{t-1}| <= tol * max|Z_t|

    def __post_init__(self) -> None:
        _check(self.max_iter >= 1, "solver.max_iter", self.max_iter, ">= 1")
        _check(self.tol >= 0.0, "solver.tol", self.tol, ">= 0")


@dataclass
class MethodConfig:
    name: MethodName = MethodName.diffuser
    view: int = 0  # frame index used by `direct` (negative counts from the end)
    bayesian_mode: BayesianMode = BayesianMode.likelihood


@dataclass
class OutputConfig:
    labels_ply: bool = True  # write labels.ply (points coloured by label)
    quiet: bool = False  # do not print the result table


@dataclass
class Config:
    scene: SceneConfig = field(default_factory=SceneConfig)
    predictions: PredictionsConfig = field(default_factory=PredictionsConfig)
    evidence: EvidenceConfig = field(default_factory=EvidenceConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    method: MethodConfig = field(default_factory=MethodConfig)
    output: OutputConfig = field(default_factory=OutputConfig)


def register() -> None:
    """Register the schema as ``base_config`` (the first entry of conf/config.yaml's defaults)."""
    ConfigStore.instance().store(name="base_config", node=Config)


def to_object(cfg: Any) -> Config:
    """Composed DictConfig -> validated :class:`Config` (runs every ``__post_init__``)."""
    known = set(Config.__dataclass_fields__)
    extra = sorted(set(cfg.keys()) - known - {"hydra"})
    if extra:
        raise ConfigError(f"unknown top-level key(s) {', '.join(extra)}: expected only {', '.join(sorted(known))}")
    obj = OmegaConf.to_object(cfg)
    if not isinstance(obj, Config):  # e.g. a DictConfig without the schema
        obj = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(Config), cfg))
    return obj  # type: ignore[return-value]


def default_config(**overrides: Any) -> Config:
    """A validated default :class:`Config` for library use; ``overrides`` as dotted keys,
    e.g. ``default_config(**{"graph.k": 8})``."""
    cfg = OmegaConf.structured(Config)
    for key, value in overrides.items():
        OmegaConf.update(cfg, key, value, merge=False)
    return to_object(cfg)
