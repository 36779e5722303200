"""Hydra structured configs: every knob of a run, typed and range-checked.

The dataclasses are registered in Hydra's ConfigStore as ``base_config``; the YAML files
under ``conf/`` fill them. A key that is not declared here, or a value of the wrong type,
fails when Hydra composes the config; ranges are checked in ``__post_init__``, which runs
when :func:`to_object` turns the composed config into these dataclasses.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, List, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, OmegaConf


class ConfigError(ValueError):
    """A config value is out of range; the message names the key."""


def _check(ok: bool, key: str, value: Any, expected: str) -> None:
    if not ok:
        raise ConfigError(f"{key}={value!r}: expected {expected}")


class SceneSource(Enum):
    demo = "demo"  # embedded procedural room
    mesh_views = "mesh_views"  # labelled mesh (PLY with per-vertex label) + rendered views
    scannet = "scannet"  # ScanNet export layout (color/ depth/ pose/ intrinsic/ label-filt/ + PLYs)
    rgbd_folder = "rgbd_folder"  # frame-XXXXXX.{color,depth,pose} + camera-intrinsics.txt


class Protocol(Enum):
    global_3d = "global_3d"  # label the scene's points, score 3D mIoU (paper Table I)
    single_frame = "single_frame"  # label each frame's back-projected depth, score 2D mIoU (Table II)


class PredictionSource(Enum):
    simulated = "simulated"  # simulated 2D-network mistakes on ground-truth label images
    gt = "gt"  # ground-truth label images (perfect 2D labels)
    files = "files"  # a 2D network's label images (mapped) or class probabilities (.npy/.npz)


class NormalSign(Enum):
    auto = "auto"  # signed for input normals, invariant for estimated ones
    signed = "signed"  # |n_i - n_j|^2 exactly as Eq. 4
    invariant = "invariant"  # min(|n_i - n_j|^2, |n_i + n_j|^2): normals of arbitrary sign


class SolverName(Enum):
    jacobi = "jacobi"  # the paper's iteration Z <- P Z + Z_IX (Eq. 10)
    exact = "exact"  # the fixed point (I - P) Z = B solved directly (Krylov / factorisation)


class SolverBackend(Enum):
    auto = "auto"  # the fastest available CPU backend
    scipy = "scipy"  # pure numpy/scipy
    numba = "numba"  # compiled CPU kernel (optional extra)
    torch = "torch"  # PyTorch on a GPU (optional extra; CUDA required)


class BayesianMode(Enum):
    likelihood = "likelihood"  # sum of per-pixel class probabilities (one-hot for hard labels)
    votes = "votes"  # sum of one-hot argmax votes


@dataclass
class DemoSceneConfig:
    """Procedural room (diffuser_lab.data.sources.demo)."""

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
class MeshViewsConfig:
    """Views rendered from a labelled mesh (diffuser_lab.data.sources.mesh_views)."""

    path: str = MISSING  # PLY mesh with a per-vertex `label` (e.g. ScanNet's *_vh_clean_2.labels.ply)
    mapping: Optional[str] = "nyu40_to_scannet20"  # mesh label ids -> taxonomy (shipped table or CSV); null = taxonomy ids
    n_views: int = 40
    seed: int = 0
    image_width: int = 320
    image_height: int = 240
    fov_deg: float = 58.0  # horizontal; ScanNet's depth camera: fx = 577.9 at 640 px
    min_coverage: float = 0.3  # reject views whose valid-depth share is below this
    eye_height_min: float = 1.2  # metres above the floor
    eye_height_max: float = 1.8

    def __post_init__(self) -> None:
        _check(self.n_views >= 1, "scene.mesh_views.n_views", self.n_views, ">= 1")
        _check(self.image_width >= 16 and self.image_height >= 16, "scene.mesh_views.image_width/height",
               (self.image_width, self.image_height), ">= 16 pixels")
        _check(10.0 <= self.fov_deg <= 150.0, "scene.mesh_views.fov_deg", self.fov_deg, "in [10, 150]")
        _check(0.0 <= self.min_coverage < 1.0, "scene.mesh_views.min_coverage", self.min_coverage, "in [0, 1)")
        _check(0.0 < self.eye_height_min <= self.eye_height_max, "scene.mesh_views.eye_height_min/max",
               (self.eye_height_min, self.eye_height_max), "0 < min <= max")


@dataclass
class ScannetConfig:
    """A scene in ScanNet's export layout (diffuser_lab.data.sources.scannet)."""

    root: str = MISSING  # folder holding color/ depth/ pose/ intrinsic/ label-filt/ and the PLYs
    frame_step: int = 10  # paper: every 10th frame
    max_frames: Optional[int] = None
    mapping: Optional[str] = "nyu40_to_scannet20"  # label ids -> taxonomy; null = the taxonomy's own ids

    def __post_init__(self) -> None:
        _check(self.frame_step >= 1, "scene.scannet.frame_step", self.frame_step, ">= 1")
        _check(self.max_frames is None or self.max_frames >= 1, "scene.scannet.max_frames", self.max_frames,
               ">= 1 or null")


@dataclass
class RgbdFolderConfig:
    """A posed RGB-D folder: frame-XXXXXX.{color.*,depth.png,pose.txt} + camera-intrinsics.txt."""

    root: str = MISSING  # the folder
    depth_scale: float = 1000.0  # raw depth units per metre (1000 = millimetres)
    depth_bit_shift: int = 0  # circular right shift of the raw 16-bit depth (SUN3D: 3)
    invalid_depth: List[int] = field(default_factory=lambda: [0, 65535])
    color_suffix: str = "color.jpg"
    label_suffix: Optional[str] = None  # ground-truth label images frame-XXXXXX.<suffix>, if any
    mapping: Optional[str] = None  # label ids -> taxonomy; null = ids are taxonomy ids
    cloud: Optional[str] = None  # PLY point cloud; null = back-project and voxel-merge the depth frames
    cloud_voxel: float = 0.02  # metres, for the back-projected cloud
    cloud_stride: int = 4  # every n-th pixel of each depth frame for the back-projected cloud
    max_depth: Optional[float] = None  # metres; ignore depth beyond it
    frame_step: int = 1
    max_frames: Optional[int] = None

    def __post_init__(self) -> None:
        _check(self.depth_scale > 0, "scene.rgbd_folder.depth_scale", self.depth_scale, "> 0")
        _check(0 <= self.depth_bit_shift < 16, "scene.rgbd_folder.depth_bit_shift", self.depth_bit_shift,
               "in [0, 15]")
        _check(self.cloud_voxel > 0, "scene.rgbd_folder.cloud_voxel", self.cloud_voxel, "> 0 metres")
        _check(self.cloud_stride >= 1, "scene.rgbd_folder.cloud_stride", self.cloud_stride, ">= 1")
        _check(self.frame_step >= 1, "scene.rgbd_folder.frame_step", self.frame_step, ">= 1")


REQUIRED = {"mesh_views": "path", "scannet": "root", "rgbd_folder": "root"}
"""Each scene source's required key (MISSING in its dataclass)."""


@dataclass
class SceneConfig:
    source: SceneSource = SceneSource.demo
    name: Optional[str] = None  # display name; null = derived from the source
    # one dataclass per source; a source's own settings are set (by its conf/scene/*.yaml) only
    # when it is the selected one, so its required keys (MISSING) are asked for only then
    demo: DemoSceneConfig = field(default_factory=DemoSceneConfig)
    mesh_views: Optional[MeshViewsConfig] = None
    scannet: Optional[ScannetConfig] = None
    rgbd_folder: Optional[RgbdFolderConfig] = None
    voxel_size: float = 0.0  # metres; > 0: voxel-downsample before diffusion, labels transferred back

    def __post_init__(self) -> None:
        _check(self.voxel_size >= 0.0, "scene.voxel_size", self.voxel_size, ">= 0 metres (0 = off)")
        # a source selected by scene.source alone (its settings never set): its required key
        own = getattr(self, self.source.value)
        if own is None:
            key = REQUIRED[self.source.value]
            raise ConfigError(f"scene.{self.source.value}.{key} is required for scene={self.source.value}")


SPECIAL_TAXONOMIES = ("file", "ids")


@dataclass
class TaxonomyConfig:
    """The run's class set (diffuser_lab.data.taxonomy): evaluation, records, plots follow it."""

    name: str = "scannet20"  # a shipped taxonomy | file (taxonomy.path) | ids (the label ids found in the data)
    path: Optional[str] = None  # name=file: a CSV (id,name[,r,g,b]) or YAML taxonomy file
    scan_frames: int = 10  # name=ids: label images of the first n frames are scanned for ids

    def __post_init__(self) -> None:
        from diffuser_lab.data.taxonomy import shipped_taxonomies

        valid = shipped_taxonomies() + list(SPECIAL_TAXONOMIES)
        _check(self.name in valid, "taxonomy.name", self.name, f"one of {', '.join(valid)}")
        _check(self.name != "file" or bool(self.path), "taxonomy.path", self.path,
               "a CSV or YAML file for taxonomy=file")
        _check(self.scan_frames >= 1, "taxonomy.scan_frames", self.scan_frames, ">= 1")


@dataclass
class PredictionsConfig:
    """What the frames' 2D labels are. The simulated mistakes are documented knob by knob in
    :func:`diffuser_lab.data.simulate.simulate_predictions` (defaults: 2D mIoU ~58 on the demo)."""

    source: PredictionSource = PredictionSource.simulated
    folder: Optional[str] = None  # files: the folder of per-frame predictions (named after the frames)
    mapping: Optional[str] = None  # files: network label ids -> taxonomy (e.g. nyu40_to_scannet20)
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
    """Diffusion (Eq. 10) stopping rule and implementation."""

    name: SolverName = SolverName.jacobi
    max_iter: int = 200
    tol: float = 1e-4  # jacobi: stop when max|Z_t - Z_{t-1}| <= tol * max|Z_t|; exact: relative residual
    backend: SolverBackend = SolverBackend.auto

    def __post_init__(self) -> None:
        _check(self.max_iter >= 1, "solver.max_iter", self.max_iter, ">= 1")
        _check(self.tol >= 0.0, "solver.tol", self.tol, ">= 0")


@dataclass
class MethodConfig:
    """The fusion method: a name of the registry in :mod:`diffuser_lab.method.fusion`."""

    name: str = "diffuser"  # diffuser | bayesian | direct | ldls
    view: int = 0  # frame index used by `direct` (negative counts from the end)
    bayesian_mode: BayesianMode = BayesianMode.likelihood

    def __post_init__(self) -> None:
        from diffuser_lab.method.fusion import get

        get(self.name)  # one line naming method.name and the registry's names


@dataclass
class ProtocolConfig:
    """Evaluation protocol (paper Sec. IV-A)."""

    name: Protocol = Protocol.global_3d
    window: int = 5  # single_frame: views fused per target frame in the multi-view rows (paper: 5)
    target_step: int = 1  # single_frame: evaluate every n-th frame of the sequence
    max_targets: Optional[int] = None  # single_frame: at most this many target frames

    def __post_init__(self) -> None:
        _check(self.window >= 1, "protocol.window", self.window, ">= 1")
        _check(self.target_step >= 1, "protocol.target_step", self.target_step, ">= 1")


class RecordMode(Enum):
    off = "off"
    rerun = "rerun"  # run.rrd
    mcap = "mcap"  # run.mcap
    both = "both"


class McapCompression(Enum):
    """run.mcap's chunk compression, as the mcap package offers it (readers: mcap, Foxglove, Rerun)."""

    lz4 = "lz4"  # fast (2.4 ms per 4 MB demo Z state, 0.50x)
    zstd = "zstd"  # mcap's zstd level 3 (8.0 ms, 0.46x)
    none = "none"


class ZPrecision(Enum):
    float32 = "float32"
    float16 = "float16"


@dataclass
class RecordConfig:
    """What the run records of the diffusion (diffuser_lab.recording); records never change results."""

    mode: RecordMode = RecordMode.both
    interval: int = 10  # record every n-th iteration; the first and the last always
    z_precision: ZPrecision = ZPrecision.float32  # precision of Z in run.mcap
    max_image_side: int = 320  # frames' images in run.rrd are downsampled to at most this many pixels
    compression: McapCompression = McapCompression.lz4  # run.mcap's chunks
    retain_heap_mb: int = 256  # diffuser-lab (the CLI) has glibc keep this much freed memory for reuse (0: its defaults)

    def __post_init__(self) -> None:
        _check(self.interval >= 1, "record.interval", self.interval, ">= 1")
        _check(self.max_image_side >= 16, "record.max_image_side", self.max_image_side, ">= 16")
        _check(0 <= self.retain_heap_mb <= 1024, "record.retain_heap_mb", self.retain_heap_mb, "in 0..1024")


@dataclass
class OutputConfig:
    labels_ply: bool = True  # write labels.ply (points coloured by label)
    quiet: bool = False  # do not print the result table


@dataclass
class Config:
    """A run. ``seed`` and ``n_views`` are shared keys the groups' YAML files refer to
    (``${seed}``, ``${n_views}``), so one sweep works on every scene source."""

    seed: int = 0  # seeds the demo room, the rendered camera path and the simulated mistakes
    n_views: int = 30  # views rendered by the demo and mesh_views sources
    memory_budget_gb: float = 16.0  # refuse runs whose estimated peak memory exceeds this
    scene: SceneConfig = field(default_factory=SceneConfig)
    taxonomy: TaxonomyConfig = field(default_factory=TaxonomyConfig)
    predictions: PredictionsConfig = field(default_factory=PredictionsConfig)
    evidence: EvidenceConfig = field(default_factory=EvidenceConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    method: MethodConfig = field(default_factory=MethodConfig)
    protocol: ProtocolConfig = field(default_factory=ProtocolConfig)
    record: RecordConfig = field(default_factory=RecordConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    def __post_init__(self) -> None:
        from diffuser_lab.method.fusion import get

        get(self.method.name).apply(self)  # what the method fixes (LDLS: no normals, 3x3 window)


def register() -> None:
    """Register the schema as ``base_config`` (the first entry of conf/config.yaml's defaults)."""
    ConfigStore.instance().store(name="base_config", node=Config)


def config_yaml(conf: Any) -> str:
    """The config as YAML, the text ``OmegaConf.to_yaml`` writes (enums by name). A
    :class:`Config` object is dumped from its plain fields: 5 ms instead of OmegaConf's 30 ms,
    which re-validates the whole tree first."""
    if dataclasses.is_dataclass(conf) and not isinstance(conf, type):
        import yaml

        def plain(o: Any) -> Any:
            if isinstance(o, dict):
                return {k: plain(v) for k, v in o.items()}
            if isinstance(o, (list, tuple)):
                return [plain(v) for v in o]
            return o.name if isinstance(o, Enum) else o

        return yaml.safe_dump(plain(dataclasses.asdict(conf)), default_flow_style=False, allow_unicode=True,
                              sort_keys=False)
    return OmegaConf.to_yaml(conf)


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
