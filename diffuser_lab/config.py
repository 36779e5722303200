"""Hydra structured configs: every knob of a run, typed and range-checked.

The dataclasses are registered in Hydra's ConfigStore as ``base_config``; the YAML files
under ``conf/`` fill them. A key that is not declared here, or a value of the wrong type,
fails when Hydra composes the config; each key's range or choices are declared once, as the
metadata of its field (:func:`key`), and checked by one validator (:func:`validate`) when
:func:`to_object` turns the composed config into these dataclasses (their ``__post_init__``),
with the few checks that involve several keys beside it (``_check_keys``).

Names that a registry defines (``method.name``, ``scene.source``, ``predictions.source``,
``protocol.name``, ``taxonomy.name``) are plain strings here (:func:`named`): the resolve step
after validation (:mod:`diffuser_lab.runs.resolve`) checks them against the registries and
applies what a fusion method fixes. This module imports nothing from ``diffuser_lab``.
"""
from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, Callable, ClassVar, Dict, List, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, OmegaConf


class ConfigError(ValueError):
    """A config value is out of range; the message names the key."""


def check(ok: bool, key: str, value: Any, expected: str) -> None:
    if not ok:
        raise ConfigError(f"{key}={value!r}: expected {expected}")


def check_name(key: str, value: Any, names: List[str]) -> None:
    """A registry name: :class:`ConfigError` ``key='value': expected one of a, b, c`` unless
    ``value`` is one of ``names`` (in the order given)."""
    check(value in names, key, value, f"one of {', '.join(names)}")


# --------------------------------------------------------------------------- declared constraints

@dataclass(frozen=True)
class Check:
    """A key's declared constraint: the values it takes (``test``; None passes when ``null``) and
    the text after "expected" in the one-line error and in docs/config.md."""

    expected: str
    test: Callable[[Any], bool]
    null: bool = False

    def ok(self, value: Any) -> bool:
        if value is None:
            return self.null
        return bool(self.test(value))


def _num(x: float) -> str:
    return f"{x:g}"


def _text(base: str, unit: str, null: bool, note: str) -> str:
    return base + (f" {unit}" if unit else "") + (" or null" if null else "") + (f" {note}" if note else "")


def at_least(lo: float, unit: str = "", *, null: bool = False, note: str = "") -> Check:
    """``>= lo``."""
    return Check(_text(f">= {_num(lo)}", unit, null, note), lambda v: v >= lo, null)


def above(lo: float, unit: str = "", *, null: bool = False, note: str = "") -> Check:
    """``> lo``."""
    return Check(_text(f"> {_num(lo)}", unit, null, note), lambda v: v > lo, null)


def within(lo: float, hi: float, unit: str = "", *, open_lo: bool = False, open_hi: bool = False,
           steps: bool = False, null: bool = False, note: str = "") -> Check:
    """``lo <= v <= hi`` (``open_lo``/``open_hi``: strict); written ``in [lo, hi]``, or ``in lo..hi``
    with ``steps`` (integer keys)."""
    if steps:
        base = f"in {_num(lo)}..{_num(hi)}"
    else:
        base = f"in {'(' if open_lo else '['}{_num(lo)}, {_num(hi)}{')' if open_hi else ']'}"

    def test(v: Any) -> bool:
        return (v > lo if open_lo else v >= lo) and (v < hi if open_hi else v <= hi)

    return Check(_text(base, unit, null, note), test, null)


def rule(expected: str, test: Callable[[Any], bool], *, null: bool = False) -> Check:
    """Any other constraint: ``test`` and its text."""
    return Check(expected, test, null)


def key(default: Any = MISSING, check: Optional[Check] = None, *, factory: Optional[Callable[[], Any]] = None) -> Any:
    """A schema field with its constraint (``check``) declared as the field's metadata."""
    meta = {"check": check} if check is not None else {}
    if factory is not None:
        return field(default_factory=factory, metadata=meta)
    return field(default=default, metadata=meta)


def named(default: str, registry: str) -> Any:
    """A schema field whose value is a name in ``registry`` (checked by the resolve step)."""
    return field(default=default, metadata={"registry": registry})


def validate(section: Any) -> None:
    """The one validator: every field of the dataclass ``section`` with a declared :class:`Check`
    against its value; :class:`ConfigError` naming the first key out of range. Nested sections
    are checked when they are built (their own ``__post_init__``)."""
    for f in dataclasses.fields(section):
        rule_ = f.metadata.get("check")
        if rule_ is not None:
            value = getattr(section, f.name)
            check(rule_.ok(value), f"{section.KEY}.{f.name}" if section.KEY else f.name, value, rule_.expected)


class Section:
    """Base of the schema's dataclasses: building one validates it (:func:`validate`, then
    :meth:`_check_keys`). ``KEY`` is its dotted key path (``scene.options``; ``""`` at the top)."""

    KEY: ClassVar[str] = ""

    def __post_init__(self) -> None:
        validate(self)
        self._check_keys()

    def _check_keys(self) -> None:
        """Checks that involve several keys (``min <= max``, one of two keys set, ...)."""


# --------------------------------------------------------------------------- enums

class FrameNormals(Enum):
    """single_frame: where a target frame's cloud gets its normals (Eq. 4's normal term)."""

    knn = "knn"  # open3d PCA over graph.normal_knn neighbours of the back-projected cloud (the paper's)
    depth_image = "depth_image"  # the organised depth image, smoothed over protocol.normal_window_px


class MistakeCorrelation(Enum):
    independent = "independent"  # every view draws its mistakes on its own (the default)
    regions = "regions"  # a mistake belongs to a 3D surface region, shared by the views that see it


class ChannelOrder(Enum):
    rgb = "rgb"
    bgr = "bgr"  # OpenCV / Caffe-trained networks


class TensorLayout(Enum):
    nchw = "nchw"  # (1, C, H, W): PyTorch exports
    nhwc = "nhwc"  # (1, H, W, C): TensorFlow exports


class OnnxOutput(Enum):
    logits = "logits"  # class scores, softmax applied here
    probs = "probs"  # class probabilities (softmax inside the graph)
    ids = "ids"  # class ids (argmax inside the graph), (1, H, W) or (H, W)
    features = "features"  # per-pixel embeddings (1, D, h, w) or (1, h, w, D): predictions=features


class NormalSign(Enum):
    auto = "auto"  # signed for input normals, invariant for estimated ones
    signed = "signed"  # |n_i - n_j|^2 exactly as Eq. 4
    invariant = "invariant"  # min(|n_i - n_j|^2, |n_i + n_j|^2): normals of arbitrary sign


class GraphAffinity(Enum):
    """graph.affinity: a third factor of Eq. 4's edge weights, the similarity of the points' own
    attributes (LUDVIG, ICCV 2025: graph diffusion whose weights carry the features' similarity)."""

    none = "none"  # Eq. 4 as the paper writes it
    colour = "colour"  # x exp(-|c_i - c_j|^2 / (2 sigma_c^2)), c the points' RGB in [0, 1] (the cloud's colours)
    features = "features"  # ... c the points' averaged evidence (unit features; labels: class distributions)


class SolverName(Enum):
    jacobi = "jacobi"  # the paper's iteration Z <- P Z + Z_IX (Eq. 10)
    exact = "exact"  # the fixed point (I - P) Z = B solved directly (Krylov / factorisation)


class SparseClasses(Enum):
    auto = "auto"  # sparse above 32 active classes on numba when a point's neighbourhood sees few classes
    on = "on"  # every point keeps at most solver.classes_per_point classes (bounded approximation)
    off = "off"  # dense Z (N x C) throughout


class SolverBackend(Enum):
    auto = "auto"  # the fastest available CPU backend
    scipy = "scipy"  # pure numpy/scipy
    numba = "numba"  # compiled CPU kernel (optional extra)
    torch = "torch"  # PyTorch on a GPU (optional extra; CUDA required)


class CloudFormat(Enum):
    """output.clouds: formats the labelled cloud is written in besides labels.npy / labels.ply."""

    las = "las"  # labels.las (LAS 1.4)
    laz = "laz"  # labels.laz (LAS compressed)
    ros2 = "ros2"  # labels_ros2/ (a ROS 2 bag: labels_ros2.mcap + metadata.yaml, one sensor_msgs/PointCloud2)


class Split(Enum):
    """split: which part of a tuning protocol a run belongs to (summary.json's ``split``; docs/sweeps.md)."""

    validation = "validation"  # a parameter search's run: its figures chose the configuration
    test = "test"  # a held-out run of the chosen configuration (and of what it is compared with)


class BayesianMode(Enum):
    likelihood = "likelihood"  # sum of per-pixel class probabilities (one-hot for hard labels)
    votes = "votes"  # sum of one-hot argmax votes


# --------------------------------------------------------------------------- scene

def file_pattern(placeholder: str) -> Check:
    """A relative file name with one ``{placeholder}`` and no other ``{...}``."""
    ph = "{" + placeholder + "}"
    return rule(f"a relative file name with one {ph} and no other {{...}}",
                lambda v: isinstance(v, str) and v.count(ph) == 1 and v.replace(ph, "").count("{") == 0)


class PoseConvention(Enum):
    camera_to_world = "camera_to_world"  # the pose maps camera coordinates to world (7-Scenes, ScanNet, TUM)
    world_to_camera = "world_to_camera"  # the pose maps world coordinates to camera (extrinsics)


class DepthModel(Enum):
    perfect = "perfect"  # rendered depth as it is: exact z-depth
    sensor = "sensor"  # a Kinect-v1-like structured-light sensor (diffuser_lab.data.sensor)


class DepthQuantization(Enum):
    mm = "mm"  # millimetre steps (16-bit PNG depth)
    disparity = "disparity"  # the Kinect's 1/8-pixel disparity steps: z^2 / (f b) / 8
    none = "none"


@dataclass
class DepthNoiseConfig(Section):
    """What the frames' depth is (diffuser_lab/data/sensor.py; docs/sensor.md): applied to rendered
    depth (scene=demo, mesh_views) and, with ``apply_to_real``, to the depth images of real sources.
    :func:`diffuser_lab.data.sensor.sensor_model` makes the sensor model of these keys."""

    KEY = "depth"
    model: DepthModel = DepthModel.perfect
    seed: int = 0  # with the frame's index, seeds its noise (conf/depth/sensor.yaml: ${seed})
    apply_to_real: bool = False  # also corrupt the depth of scannet / rgbd_folder / tum frames
    axial_scale: float = key(1.0, at_least(0, note="(0 = off)"))  # x Nguyen et al. 2012 sigma_z = 0.0012 + 0.0019 (z - 0.4)^2 m (+ angle term > 60 deg)
    lateral_scale: float = key(1.0, at_least(0, note="(0 = off)"))  # x Nguyen's sigma_L = 0.8 + 0.035 theta / (pi/2 - theta) px (640-px image) at edges
    projector_baseline: float = key(0.075, at_least(0, note="(0 = off)"))  # metres, IR camera -> projector (+x): shadows left of objects; 0 = none
    edge_jump: float = key(0.05, above(0, note="(a share of the depth)"))  # a 4-neighbour jump larger than this share of the nearer depth is a discontinuity
    edge_hole_px: int = key(0, within(0, 20, "pixels", steps=True))  # hole band along discontinuities: the two pixels of the jump dilated by this - 1; 0 = none (real ScanNet depth: docs/sensor.md)
    max_incidence_deg: float = key(80.0, within(0, 90, "degrees", open_lo=True))  # no depth beyond this angle between ray and surface normal; 90 = never (80: real ScanNet depth)
    min_range: float = 0.5  # metres; sensor depth outside [min_range, max_range] is no return (Kinect: 0.5-4.5)
    max_range: float = 4.5
    quantization: DepthQuantization = DepthQuantization.mm
    disparity_focal_px: float = key(580.0, above(0))  # quantization=disparity: the IR camera's focal length (640 px)
    disparity_baseline: float = key(0.075, above(0))  # metres
    disparity_subpixel: float = key(0.125, above(0))  # disparity step, pixels (Kinect v1: 1/8)

    def _check_keys(self) -> None:
        check(0.0 <= self.min_range < self.max_range, "depth.min_range/max_range",
               (self.min_range, self.max_range), "0 <= min_range < max_range metres")


MOVED_SCENE_KEYS = ("demo", "city", "mesh_views", "scannet", "rgbd_folder", "tum")
"""Sources whose keys were ``scene.<source>.KEY`` until 2026-12; every source's are ``scene.options.KEY``."""


def moved_key(dotted: str) -> Optional[str]:
    """The new spelling of a scene source's key spelled the old way (``scene.demo.n_views`` ->
    ``scene.options.n_views``; a leading ``+``/``++``/``~`` is ignored), else None."""
    parts = dotted.lstrip("+~").split("=", 1)[0].split(".")
    if len(parts) >= 2 and parts[0] == "scene" and parts[1] in MOVED_SCENE_KEYS:
        return ".".join(["scene", "options", *parts[2:]])
    return None


def check_moved(dotted: str) -> None:
    """Raise :class:`ConfigError` for a key spelled the old way (:func:`moved_key`), naming the new key."""
    new = moved_key(dotted)
    if new is not None:
        old = dotted.lstrip("+~").split("=", 1)[0]
        raise ConfigError(f"{old} is now {new}: every scene source's keys are scene.options.KEY "
                          f"(docs/config.md)")


@dataclass
class SceneConfig(Section):
    """What the run labels. ``source`` names an entry of the scene sources' registry
    (:mod:`diffuser_lab.data.sources`); ``options`` are that source's keys (``scene.options.KEY``):
    the resolve step turns them into the dataclass the source's entry declares (typed, defaults
    filled, ranges checked), or leaves a free-form dict for a source without one."""

    KEY = "scene"
    source: str = named("demo", "scene sources")  # the scene source's name (registry: diffuser_lab/data/sources)
    name: Optional[str] = None  # display name; null = derived from the source
    voxel_size: Any = key(0.0, rule("metres >= 0 (0 = off) or auto", lambda v: v == "auto" or (
        isinstance(v, (int, float)) and not isinstance(v, bool) and v >= 0)))  # metres; > 0: voxel-downsample before diffusion, labels transferred back; auto = 2.7 x the cloud's point spacing (docs/results/defaults.md)
    options: Dict[str, Any] = field(default_factory=dict)  # the source's keys (conf/scene/<source>.yaml sets its dataclass)
    keyframe_translation: Optional[float] = key(None, above(0, "metres", null=True))  # keyframes: keep a frame when the camera moved this far since the last kept one; null = off (docs/datasets.md)
    keyframe_rotation_deg: Optional[float] = key(None, within(0, 180, "degrees", open_lo=True, null=True))  # keyframes: ... or when it turned this much since the last kept one; null = off
    read_ahead: Optional[int] = key(None, at_least(0, null=True))  # frames decoded ahead of the one in use, on a pool of threads; null = 2 x the cores; 0 = one thread


SPECIAL_TAXONOMIES = ("file", "ids")
"""The taxonomy names besides the shipped ones: a file (taxonomy.path), the ids found in the data."""


@dataclass
class TaxonomyConfig(Section):
    """The run's class set (diffuser_lab.data.taxonomy): evaluation, records, plots follow it."""

    KEY = "taxonomy"
    name: str = named("scannet20", "taxonomies")  # a shipped taxonomy | file (taxonomy.path) | ids (the label ids found in the data)
    path: Optional[str] = None  # name=file: a CSV (id,name[,r,g,b]) or YAML taxonomy file
    scan_frames: int = key(10, at_least(1))  # name=ids: label images of the first n frames are scanned for ids

    def _check_keys(self) -> None:
        check(self.name != "file" or bool(self.path), "taxonomy.path", self.path,
               "a CSV or YAML file for taxonomy=file")


# --------------------------------------------------------------------------- predictions, method

@dataclass
class OnnxConfig(Section):
    """predictions=onnx: an exported segmentation network (diffuser_lab/data/networks.py)."""

    KEY = "predictions.onnx"
    path: str = MISSING  # the .onnx file
    input_size: Optional[List[int]] = key(None, rule("[H, W] >= 1 or null", lambda v: len(v) == 2 and min(v) >= 1,
                                                     null=True))  # [H, W] the network takes; null = its fixed size, else the frame's
    mean: List[float] = key(check=rule("3 values (one per channel)", lambda v: len(v) == 3),
                            factory=lambda: [0.485, 0.456, 0.406])  # per input channel (network's order), pixel / 255
    std: List[float] = key(check=rule("3 values > 0", lambda v: len(v) == 3 and min(v) > 0),
                           factory=lambda: [0.229, 0.224, 0.225])  # (ImageNet); [1,1,1] and 0 = raw
    channels: ChannelOrder = ChannelOrder.rgb  # channel order the network expects
    layout: TensorLayout = TensorLayout.nchw  # input tensor layout
    output: OnnxOutput = OnnxOutput.logits  # what the (first, or output_name) output holds
    output_layout: TensorLayout = TensorLayout.nchw  # layout of logits / probs outputs
    output_name: Optional[str] = None  # null = the graph's first output
    threads: int = key(0, at_least(0, note="(0 = onnxruntime's default)"))  # onnxruntime intra-op threads; 0 = its default (all cores)


_FILE_NAME = file_pattern("name")


@dataclass
class PredictionsConfig(Section):
    """What the frames' 2D labels are. ``source`` names an entry of the prediction sources'
    registry (:mod:`diffuser_lab.data.predictions`). The simulated mistakes are documented knob by
    knob in :func:`diffuser_lab.data.simulate.simulate_predictions` (defaults: 2D mIoU ~58 on the demo)."""

    KEY = "predictions"
    source: str = named("simulated", "prediction sources")  # the prediction source's name (registry: diffuser_lab/data/predictions.py)
    folder: Optional[str] = None  # files: the folder of per-frame predictions (named after the frames)
    mapping: Optional[str] = None  # files: network label ids -> taxonomy (e.g. nyu40_to_scannet20)
    # files: a frame's file name(s), {name} = the frame's name; a string or a list searched in order
    pattern: Any = field(default_factory=lambda: ["{name}.png", "{name}.label.png", "{name}.npy", "{name}.npz"])
    seed: int = 0
    strength: float = key(1.0, at_least(0))  # scales every simulated mistake; 0 = perfect labels
    jitter_px: float = key(3.0, at_least(0))  # std of the smooth boundary displacement field, pixels
    jitter_scale_px: float = key(16.0, above(0))  # its correlation length, pixels
    confuse_prob: float = key(0.2, within(0, 1))  # probability that a connected region gets a wrong class
    confuse_max_frac: float = key(0.3, within(0, 1))  # regions larger than this share of the image are never confused
    blob_count: float = key(2.0, at_least(0))  # mean number of wrong-class blobs per image (Poisson)
    blob_radius: float = key(0.1, above(0))  # mean blob radius, fraction of the image width
    blob_roughness: float = key(0.35, at_least(0))  # irregularity of blob outlines, 0 = discs
    # view-correlated mistakes and low-resolution output (docs/simulated-network.md)
    correlation: MistakeCorrelation = MistakeCorrelation.independent
    region_size: float = key(0.5, above(0, "metres"))  # regions: world voxel edge cutting gt segments into 3D regions, metres
    persistence: float = key(1.0, within(0, 1))  # regions: probability that a view shows a region's persistent decision
    confuse_region_frac: float = key(1.0, within(0, 1, open_lo=True))  # share of a confused region that is wrong (1 = all of it)
    view_gain: float = key(0.0, at_least(0))  # regions: confusion probability x (1 + view_gain * far/grazing in [0, 1])
    view_range_m: float = key(4.0, above(0, "metres"))  # regions: range at which the "far" term saturates, metres
    output_stride: int = key(1, within(1, 64, steps=True))  # labels decided on stride x stride pixel cells, upsampled; 1 = off
    # model / onnx: a network run on each frame's RGB, its outputs (ids or probabilities in its own
    # label space) translated by ``mapping`` and cached on disk (docs/networks.md)
    model: Optional[Dict[str, Any]] = None  # model: {_target_: pkg.mod.callable, **kwargs}
    pass_depth: bool = False  # model: call model(rgb, depth) instead of model(rgb)
    onnx: Optional[OnnxConfig] = None  # onnx: set by conf/predictions/onnx.yaml
    cache_dir: Optional[str] = "~/.cache/diffuser-lab/predictions"  # model / onnx outputs; null = no cache
    # features (predictions=features): per-pixel embeddings instead of labels, queried with words (docs/features.md)
    embeddings: str = key("simulated", rule("simulated, files, model or onnx", lambda v: v in (
        "simulated", "files", "model", "onnx")))  # features: the simulated network, files in predictions.folder, a callable or ONNX network (predictions.model / predictions.onnx)
    dim: int = key(512, within(8, 1024))  # features, simulated: the embedding's dimension D
    stride: int = key(8, within(1, 64, steps=True))  # features, simulated: pixels per patch of the network's grid
    embedding_seed: int = 0  # features, simulated: the class prototypes' seed (the default queries are the prototypes)
    boundary_mix: float = key(0.5, within(0, 1))  # features, simulated: weight of the neighbouring patches' classes
    rotation_deg: float = key(20.0, within(0, 90))  # features, simulated: per-view rotation of a random subspace, degrees
    rotation_dims: int = key(16, within(2, 1024))  # features, simulated: that subspace's dimension
    noise: float = key(0.3, at_least(0))  # features, simulated: Gaussian noise, relative to a unit feature
    npz_key: str = "features"  # features, files: the .npz array holding the map (else its only array)
    layout: str = key("auto", rule("auto, hwd or dhw", lambda v: v in ("auto", "hwd", "dhw")))  # features, files: (h, w, D), (D, h, w) or either
    queries: Optional[str] = None  # features: a query set .npz (names, embeddings); null: the taxonomy's names
    encoder: Optional[str] = None  # features: a text encoder module.fn(list[str]) -> (Q, D) for the taxonomy's names
    query_mapping: Optional[str] = None  # features: CSV query,class (default: a query names its class)
    threshold: Optional[float] = None  # features: a point whose best cosine is below this gets ``background``
    background: Optional[str] = None  # features: that class's name; null = unlabeled
    # features: the columns a run diffuses (docs/features.md "The basis"): auto = the queries' span + the
    # leading principal directions of the frames' features + probes of the rest (labels exact, |f| and the
    # saved features within the error summary.json reports); full = all D (auto too where it would not halve them)
    basis: str = key("auto", rule("auto or full", lambda v: v in ("auto", "full")))
    basis_dim: int = key(8, within(0, 1024, steps=True))  # features, basis=auto: principal directions beyond the queries' span
    basis_probes: int = key(3, within(0, 64, steps=True))  # features, basis=auto: random probe columns estimating |f| outside the basis
    basis_frames: int = key(6, within(1, 1000, steps=True))  # features, basis=auto: frames (evenly spaced) whose feature cells fit the basis

    def _check_keys(self) -> None:
        if isinstance(self.pattern, str):
            self.pattern = [self.pattern]
        self.pattern = list(self.pattern)
        for p in self.pattern:
            check(_FILE_NAME.ok(p), "predictions.pattern", p, _FILE_NAME.expected)
        check(len(self.pattern) >= 1, "predictions.pattern", self.pattern, "at least one file name")
        if self.source == "model" or (self.source == "features" and self.embeddings == "model"):
            target = (self.model or {}).get("_target_")
            check(isinstance(target, str) and bool(target.strip()), "predictions.model._target_", target,
                   "a Python callable's import path (pkg.module.name) for predictions=model")
        if self.source == "onnx" and self.onnx is None:
            raise ConfigError("predictions.onnx.path is required for predictions=onnx (pass predictions.onnx.path=...)")
        if self.source == "features" and self.embeddings == "onnx" and self.onnx is None:
            raise ConfigError("predictions.onnx.path is required for predictions.embeddings=onnx "
                              "(predictions=features_onnx predictions.onnx.path=FILE.onnx)")


@dataclass
class EvidenceConfig(Section):
    """Pixel-to-point edges (Eqs. 1-2, 11-13)."""

    KEY = "evidence"
    pixel_weight: float = key(1e-4, above(0, note="(paper: 1e-4)"))  # the paper's lambda
    depth_tol: float = key(0.05, above(0, "metres"))  # metres: |z_point - depth(pixel)| <= depth_tol passes the occlusion check
    pixel_radius: int = key(0, within(0, 10))  # link to the (2r+1)^2 pixels around the projection; 0 = paper's choice


@dataclass
class GraphConfig(Section):
    """Point-to-point edges (Eqs. 3-4)."""

    KEY = "graph"
    k: int = key(24, at_least(1, note="(paper: 24)"))
    use_normals: bool = True  # the normal term of Eq. 4; off = LDLS-like distance-only graph
    sigma_s: float = key(0.2, above(0, note="(paper: 0.2)"))
    sigma_d: Optional[float] = key(None, above(0, "metres", null=True, note="(= sigma_d_factor * rho)"))  # metres; None = sigma_d_factor * rho (rho: mean NN spacing)
    sigma_d_factor: float = key(2.0, above(0, note="(paper: 2)"))
    normal_sign: NormalSign = NormalSign.auto
    normal_knn: int = key(16, at_least(3))  # neighbours for normal estimation when the input has none
    affinity: GraphAffinity = GraphAffinity.none  # none = Eq. 4; colour / features: x the attributes' similarity (method/affinity.py)
    sigma_c: float = key(0.2, above(0))  # affinity's bandwidth, in the attributes' units (RGB in [0, 1]; unit features)


@dataclass
class SolverConfig(Section):
    """Diffusion (Eq. 10) stopping rule and implementation."""

    KEY = "solver"
    name: SolverName = SolverName.jacobi
    max_iter: int = key(200, at_least(1))
    tol: float = key(1e-4, at_least(0))  # jacobi: stop when max|Z_t - Z_{t-1}| <= tol * max|Z_t|; exact: relative residual
    backend: SolverBackend = SolverBackend.auto
    sparse_classes: SparseClasses = SparseClasses.auto  # jacobi: a sparse per-point class set (docs/many-classes.md)
    classes_per_point: int = key(16, within(1, 1024, steps=True))  # sparse_classes: the classes each point keeps (the M largest scores)
    tikhonov: float = key(0.0, at_least(0, note="(0 = off)"))  # t: + t d_i |z_i - mean_i|^2 for points with evidence (method/exact.py; Splat Feature Solver)


@dataclass
class MethodConfig(Section):
    """The fusion method: a name of the registry in :mod:`diffuser_lab.method.fusion`."""

    KEY = "method"
    name: str = named("diffuser", "fusion methods")  # the fusion method's name (registry: diffuser_lab/method/fusion.py)
    view: int = 0  # frame index used by `direct` (negative counts from the end)
    bayesian_mode: BayesianMode = BayesianMode.likelihood
    top_k: int = key(3, within(1, 1000, steps=True))  # topk: the views each point keeps (method/lifters.py)


@dataclass
class CalibrationConfig(Section):
    """How the methods' class distributions are scored (summary ``metrics.calibration``;
    :mod:`diffuser_lab.method.calibration`). Changes no label."""

    KEY = "calibration"
    temperature: float = key(1.0, above(0))  # p <- softmax(log p / T) on every method's normalised Z / mass; 1 = as is
    bins: int = key(15, at_least(1))  # equal-width confidence bins of the ECE and the reliability diagram (Guo et al. 2017)


@dataclass
class ProtocolConfig(Section):
    """Evaluation protocol (paper Sec. IV-A): ``name`` names an entry of the protocols' registry
    (:mod:`diffuser_lab.runs.protocols`)."""

    KEY = "protocol"
    name: str = named("global_3d", "protocols")  # the protocol's name (registry: diffuser_lab/runs/protocols.py)
    window: int = key(5, at_least(1))  # single_frame: views fused per target frame in the multi-view rows (paper: 5)
    target_step: int = key(1, at_least(1))  # single_frame: evaluate every n-th frame of the sequence
    max_targets: Optional[int] = None  # single_frame: at most this many target frames
    # single_frame, a change to the paper's protocol (reported separately): a pixel without depth
    # takes the label (and distribution) of the nearest pixel with depth instead of counting as a miss
    fill_missing_depth: bool = False
    normals: FrameNormals = FrameNormals.knn  # single_frame: see FrameNormals
    normal_window_px: int = key(7, at_least(1, "pixels"))  # single_frame, normals=depth_image: box window of the depth smoothing


class OnlineMap(Enum):
    """protocol=online: what the map is."""

    given = "given"  # the scene's cloud (a prior map or mesh): evidence arrives frame by frame
    growing = "growing"  # each frame's depth back-projected and merged on a voxel grid: points appear as seen


class BadFrame(Enum):
    """protocol=online: a frame that fails the batch pipeline's checks (no depth, a pose that is not rigid)."""

    skip = "skip"  # one warning line naming the frame, the run goes on
    stop = "stop"  # one error line, the run stops (what it has recorded stays readable)


class OnlineSolver(Enum):
    """protocol=online: how each frame's steps approach the discounted fixed point."""

    jacobi = "jacobi"  # online.steps Jacobi steps Z <- gamma P Z + B, warm-started (the paper's iteration, discounted)
    gmres = "gmres"  # GMRES(online.steps) warm-started, per class column: closer per product, ~3x the time per step


class FinalPass(Enum):
    """protocol=online: the pass after the last frame (``online.finish``)."""

    batch = "batch"  # the batch method on the map built online: horizon steps of the paper's iteration from Z = 0
    settle = "settle"  # the discounted iteration warm-started until a step changes Z by <= solver.tol


@dataclass
class OnlineConfig(Section):
    """protocol=online (diffuser_lab/method/online.py, docs/online.md): per frame the evidence it
    adds, the graph extended for new points, ``steps`` warm-started steps of Z <- gamma P Z + B."""

    KEY = "online"
    map: OnlineMap = OnlineMap.given
    solver: OnlineSolver = OnlineSolver.jacobi
    steps: Optional[int] = key(None, within(1, 1000, steps=True, null=True))  # per frame: Jacobi steps or GMRES's Krylov steps; null = 10 (given map), 16 (growing)
    # the batch iteration count the online result stands for; null = solver.max_iter. The steps
    # iterate Z <- gamma P Z + B with gamma = 2^(-2 / horizon): its fixed point weights P^t B by
    # gamma^t, half of the weight on t < horizon / 2 as the batch's T = horizon steps from Z = 0
    # do, so the result stays where the early-stopped batch is as frames accumulate
    horizon: Optional[int] = key(None, at_least(1, null=True))
    # region: a frame's steps take the rows it changed (evidence, edges, new points) and those within
    # `frontier` hops of them (null: as many hops as the frame's steps reach); false = every row. Every
    # `sweep`-th frame adds one step on every row (its change bounds the error the regions leave)
    region: bool = True
    frontier: Optional[int] = key(4, within(0, 1000, steps=True, null=True, note="(null = online.steps)"))
    sweep: int = key(8, within(1, 100_000, steps=True))
    discount: Optional[float] = key(None, within(0, 1, open_lo=True, null=True, note="(= 2^(-2/horizon))"))  # gamma itself; null = from horizon; 1 = the undiscounted iteration
    voxel_size: float = key(0.03, above(0, "metres"))  # growing: map voxel edge, metres (online mappers use 2-10 cm; the paper 2 cm)
    depth_stride: int = key(2, at_least(1))  # growing: every n-th depth pixel in both directions is back-projected
    max_depth: Optional[float] = key(None, above(0, "metres", null=True))  # growing: metres; depth beyond it adds no points (it still gives evidence)
    # growing: a new point also gets the evidence of the frames before the one that added it (as the batch
    # run on the final cloud does): null = every earlier frame kept (within revisit_mb), n = the n last
    revisit: Optional[int] = key(None, within(0, 100_000, steps=True, null=True, note="(0 = none)"))
    revisit_mb: float = key(2048.0, above(0, "MB"))  # growing: the earlier frames kept for that (depth and 2D predictions) take at most this; the oldest go first (counted in summary.json)
    bad_frames: BadFrame = BadFrame.skip
    compare_batch: bool = True  # after the last frame, run the batch Diffuser on the same frames (and final cloud)
    # the sensor's frame rate: what a frame's update leaves of its 1 / rate seconds goes to extra steps
    # (idle time; reported apart from the latency); 0 = none: each frame's `steps` only (reproducible)
    rate: float = key(30.0, at_least(0, "Hz", note="(0 = no idle steps)"))
    final: FinalPass = FinalPass.batch  # after the last frame: batch = the early-stopped batch iteration on the final map (the frames' labels track a discounted fixed point near it); settle = that fixed point
    finish: int = key(5000, within(0, 1_000_000, steps=True, note="(0 = none)"))  # the pass after the last frame (online.final): 0 = none; settle: up to this many steps until one changes Z by <= solver.tol


@dataclass
class TilingConfig(Section):
    """protocol=tiled (diffuser_lab/runs/tiled.py, docs/tiling.md): the cloud cut into a regular x-y
    grid of ``size`` tiles; each tile runs the global pipeline on its points and a ``halo`` around
    them, with the frames whose view meets that box, and keeps its own points' labels."""

    KEY = "tiling"
    size: float = key(2.0, above(0, "metres"))  # tile edge in x and y, metres
    halo: Optional[float] = key(None, at_least(0, "metres", null=True, note="(= halo_factor * sigma_d)"))  # points within this distance (x, y) of a tile join its diffusion; null = halo_factor * graph.sigma_d
    halo_factor: float = key(30.0, above(0))  # tiling.halo=null: the halo is this many graph.sigma_d (which scales with the point spacing as a Jacobi step's reach does); docs/tiling.md: labels equal vs halo
    max_depth: Optional[float] = key(None, above(0, "metres", null=True))  # a frame's view reaches this far when its tiles are chosen; null = unlimited
    workers: int = key(0, at_least(0, note="(0 = the tiles one after another in this process)"))  # >= 1: tiles are Ray tasks; a local Ray instance gets this many CPUs
    address: Optional[str] = None  # Ray cluster to run the tiles on: auto (a running cluster), ray://host:port; null = a local instance
    max_retries: int = key(2, at_least(0))  # Ray retries of a failing tile before it is reported
    resume: Optional[str] = None  # an earlier tiled run's folder: its finished tiles (tiles/*.npz) are kept, the rest computed there


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
    """How run.mcap keeps the intermediate Z states (the last recorded one is always float32, exact)."""

    q8 = "q8"  # each row: its sum (float32) and its shares Z_ic / sum_c Z_ic in 1/255 steps (error <= 0.2% of the sum)
    q16 = "q16"  # the same in 1/65535 steps (error <= 7.7e-6 of the sum)
    float16 = "float16"  # Z / max(Z) as float16 (relative error 2^-11; values below 6e-8 max(Z) lose digits)
    float32 = "float32"  # exact


class CloudSchedule(Enum):
    """Recorded iterations that also get a labelled foxglove.PointCloud in run.mcap."""

    decades = "decades"  # 100, 1000, ... and the last
    all = "all"  # every recorded iteration


LIVE_OFF = ("", "off", "none", "null", "false")
"""``record.live`` values that mean no live stream (besides null)."""
LIVE_URL = re.compile(r"(?:rerun|rerun\+https?)://(?:[^/\s:\[\]]+|\[[0-9A-Fa-f:.]+\])(?::(\d{1,5}))?/proxy")
"""A Rerun viewer's gRPC URL as Rerun's GrpcSink takes it (scheme, host[:port], path /proxy)."""


def live_is_off(value: Any) -> bool:
    """``record.live`` asks for no live stream."""
    return value is None or value is False or str(value).strip().lower() in LIVE_OFF


def live_is_valid(value: Any) -> bool:
    """``record.live``'s constraint: off, ``spawn``, or a gRPC URL (:data:`LIVE_URL`) with a port in 1..65535.
    :func:`diffuser_lab.recording.live.live_target` turns a valid value into the recorder's target."""
    if live_is_off(value) or str(value).strip() == "spawn":
        return True
    m = LIVE_URL.fullmatch(str(value).strip())
    return bool(m) and (m.group(1) is None or 1 <= int(m.group(1)) <= 65535)


@dataclass
class RecordConfig(Section):
    """What the run records of the diffusion (diffuser_lab.recording); records never change results."""

    KEY = "record"
    mode: RecordMode = RecordMode.both
    # recorded iterations: null = log-spaced 1, 2, 5, 10, 20, 50, 100, ... (1-2-5 steps); n = every
    # n-th; the first and the last always
    interval: Optional[int] = key(None, at_least(1, null=True))
    z_precision: ZPrecision = ZPrecision.q8  # intermediate Z states in run.mcap (the last: float32, exact)
    clouds: CloudSchedule = CloudSchedule.decades  # labelled point clouds in run.mcap (Foxglove)
    max_image_side: int = key(320, at_least(16))  # frames' label (and colour) images in the records are strided to at most this many pixels
    max_depth_side: int = key(160, rule("0 (no depth images) or >= 16", lambda v: v == 0 or v >= 16))  # frames' depth images in run.rrd likewise (0: none); depth compresses ~5x worse than labels
    compression: McapCompression = McapCompression.zstd  # run.mcap's chunks
    retain_heap_mb: int = key(256, within(0, 1024, steps=True))  # diffuser-lab (the CLI) has glibc keep this much freed memory for reuse (0: its defaults)
    # also stream run.rrd's content to a Rerun viewer as the run goes: null/off, spawn (start one),
    # or a viewer's gRPC URL (rerun+http://127.0.0.1:9876/proxy); run.rrd is written all the same
    # a features run (predictions=features): the query whose cosine similarity run.rrd shows as a
    # heat map (world/query/<name>) and run.mcap keeps; null: the run's first query
    query: Optional[str] = None
    live: Optional[str] = key(None, rule("null, off, spawn or a Rerun gRPC URL: rerun+http://HOST:PORT/proxy "
                                         "(or rerun+https://, rerun://)", live_is_valid, null=True))

    def _check_keys(self) -> None:
        check(live_is_off(self.live) or self.mode in (RecordMode.rerun, RecordMode.both), "record.live", self.live,
               "record=rerun or record=both (the live stream is run.rrd's content)")


@dataclass
class OutputConfig(Section):
    """What a run writes besides summary.json and its records."""

    KEY = "output"
    labels_ply: bool = True  # write labels.ply (points coloured by label)
    # also write the labelled cloud as: las, laz (class in the classification field), ros2 (a ROS 2
    # MCAP bag with a sensor_msgs/PointCloud2 that rviz2 and Foxglove open); docs/layouts.md
    clouds: List[CloudFormat] = field(default_factory=list)
    # also write scores.npy ((N, C) float16: each point's class distribution, Eq. 16's normalised row; 0 where
    # nothing reached it) and the points' confidence (top score, margin, entropy) in labels.ply, the LAS output
    # and run.rrd; global_3d only (docs/calibration.md "Saved scores")
    scores: bool = False
    quiet: bool = False  # do not print the result table


@dataclass
class Config(Section):
    """A run. ``seed`` and ``n_views`` are shared keys the groups' YAML files refer to
    (``${seed}``, ``${n_views}``), so one sweep works on every scene source.

    A validated config still names registry entries unchecked and holds the method's fixed keys
    as given: :func:`diffuser_lab.runs.resolve.resolve` is the step that checks the names and
    applies what the method fixes (``diffuser_lab.default_config`` returns resolved configs)."""

    seed: int = 0  # seeds the demo room, the rendered camera path and the simulated mistakes
    n_views: int = 30  # views rendered by the demo and mesh_views sources
    memory_budget_gb: float = 16.0  # refuse runs whose estimated peak memory exceeds this
    split: Optional[Split] = None  # validation or test: the run's part of a tuning protocol (summary.json's split); null = neither
    scene: SceneConfig = field(default_factory=SceneConfig)
    depth: DepthNoiseConfig = field(default_factory=DepthNoiseConfig)
    taxonomy: TaxonomyConfig = field(default_factory=TaxonomyConfig)
    predictions: PredictionsConfig = field(default_factory=PredictionsConfig)
    evidence: EvidenceConfig = field(default_factory=EvidenceConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    method: MethodConfig = field(default_factory=MethodConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    protocol: ProtocolConfig = field(default_factory=ProtocolConfig)
    online: OnlineConfig = field(default_factory=OnlineConfig)
    tiling: TilingConfig = field(default_factory=TilingConfig)
    record: RecordConfig = field(default_factory=RecordConfig)
    output: OutputConfig = field(default_factory=OutputConfig)


def claim_run_dir(parent: str, name: str, now: Any = None) -> str:
    """``parent/<HH-MM-SS-ffffff>_<name>``, created here (``os.mkdir``, atomic): a run's own folder.
    Two runs started in the same microsecond never share one: the second finds the folder made and
    takes the next stamp. conf/config.yaml's ``hydra.run.dir`` (resolver ``diffuser_lab.run_dir``,
    cached: a process resolves it to one folder). ``now``: the start time (a datetime; default now)."""
    import datetime
    import os

    os.makedirs(parent, exist_ok=True)
    now = now or datetime.datetime.now()
    while True:  # loop until a free stamp: one step, but for a run started in the same microsecond
        path = os.path.join(parent, f"{now:%H-%M-%S-%f}_{name}")
        try:
            os.mkdir(path)
            return path
        except FileExistsError:  # the next microsecond: sorts after the taken one (the wall clock may be another day)
            now = now + datetime.timedelta(microseconds=1)


def register() -> None:
    """Register the schema as ``base_config`` (the first entry of conf/config.yaml's defaults) and the
    run folder's resolver (:func:`claim_run_dir`)."""
    ConfigStore.instance().store(name="base_config", node=Config)
    if not OmegaConf.has_resolver("diffuser_lab.run_dir"):
        OmegaConf.register_new_resolver("diffuser_lab.run_dir", claim_run_dir, use_cache=True)


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
    """A validated default :class:`Config`; ``overrides`` as dotted keys, e.g.
    ``default_config(**{"graph.k": 8})``. Not resolved: the library's entry points resolve what
    they are given; ``diffuser_lab.default_config`` (:func:`diffuser_lab.runs.resolve.default_config`)
    returns the resolved config."""
    cfg = OmegaConf.structured(Config)
    for key_, value in overrides.items():
        check_moved(key_)
        OmegaConf.update(cfg, key_, value, merge=False)
    return to_object(cfg)
