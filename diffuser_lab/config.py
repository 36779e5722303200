"""Hydra structured configs: every knob of a run, typed and range-checked.

The dataclasses are registered in Hydra's ConfigStore as ``base_config``; the YAML files
under ``conf/`` fill them. A key that is not declared here, or a value of the wrong type,
fails when Hydra composes the config; ranges are checked in ``__post_init__``, which runs
when :func:`to_object` turns the composed config into these dataclasses.
"""
from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, Dict, List, Optional

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
    tum = "tum"  # TUM RGB-D: rgb.txt depth.txt groundtruth.txt, associated by timestamp


class Protocol(Enum):
    global_3d = "global_3d"  # label the scene's points, score 3D mIoU (paper Table I)
    single_frame = "single_frame"  # label each frame's back-projected depth, score 2D mIoU (Table II)
    online = "online"  # frames one at a time in sequence order; the map labels itself as they come (online.*)


class FrameNormals(Enum):
    """single_frame: where a target frame's cloud gets its normals (Eq. 4's normal term)."""

    knn = "knn"  # open3d PCA over graph.normal_knn neighbours of the back-projected cloud (the paper's)
    depth_image = "depth_image"  # the organised depth image, smoothed over protocol.normal_window_px


class PredictionSource(Enum):
    simulated = "simulated"  # simulated 2D-network mistakes on ground-truth label images
    gt = "gt"  # ground-truth label images (perfect 2D labels)
    files = "files"  # a 2D network's label images (mapped) or class probabilities (.npy/.npz)
    model = "model"  # a Python callable (Hydra _target_) run on each frame's RGB
    onnx = "onnx"  # an exported ONNX segmentation network run with onnxruntime on the CPU


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


class NormalSign(Enum):
    auto = "auto"  # signed for input normals, invariant for estimated ones
    signed = "signed"  # |n_i - n_j|^2 exactly as Eq. 4
    invariant = "invariant"  # min(|n_i - n_j|^2, |n_i + n_j|^2): normals of arbitrary sign


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


def _check_pattern(value: str, key: str, placeholder: str) -> None:
    _check(isinstance(value, str) and value.count("{" + placeholder + "}") == 1 and
           value.replace("{" + placeholder + "}", "").count("{") == 0, key, value,
           f"a relative file name with one {{{placeholder}}} and no other {{...}}")


@dataclass
class ScannetConfig:
    """A scene in ScanNet's export layout (diffuser_lab.data.sources.scannet). File names are
    relative to ``root``; ``{scene}`` = the root folder's name, ``{frame}`` = the frame number."""

    root: str = MISSING  # folder holding color/ depth/ pose/ intrinsic/ label-filt/ and the PLYs
    frame_step: int = 10  # paper: every 10th frame
    max_frames: Optional[int] = None
    mapping: Optional[str] = "nyu40_to_scannet20"  # label ids -> taxonomy; null = the taxonomy's own ids
    mesh: str = "{scene}_vh_clean_2.ply"  # the points to label (mesh vertices)
    labels_mesh: str = "{scene}_vh_clean_2.labels.ply"  # per-vertex ground truth; optional file
    depth: str = "depth/{frame}.png"  # 16-bit, depth_scale units per metre; frames are found by this
    color: str = "color/{frame}.jpg"  # optional: without it frames carry no RGB
    pose: str = "pose/{frame}.txt"  # 4x4 camera-to-world
    labels: str = "label-filt/{frame}.png"  # optional ground-truth label images (mapping's source ids)
    intrinsic_depth: str = "intrinsic/intrinsic_depth.txt"
    intrinsic_color: str = "intrinsic/intrinsic_color.txt"  # optional, only checked against intrinsic_depth
    depth_scale: float = 1000.0  # raw depth units per metre

    def __post_init__(self) -> None:
        _check(self.frame_step >= 1, "scene.scannet.frame_step", self.frame_step, ">= 1")
        _check(self.max_frames is None or self.max_frames >= 1, "scene.scannet.max_frames", self.max_frames,
               ">= 1 or null")
        _check(self.depth_scale > 0, "scene.scannet.depth_scale", self.depth_scale, "> 0")
        for key in ("depth", "color", "pose", "labels"):
            _check_pattern(getattr(self, key), f"scene.scannet.{key}", "frame")
        for key in ("mesh", "labels_mesh"):
            v = getattr(self, key)
            _check(v.replace("{scene}", "").count("{") == 0, f"scene.scannet.{key}", v,
                   "a file name, optionally with {scene}")


class DepthShiftKind(Enum):
    circular = "circular"  # 16-bit rotate right (SUN3D stores depth rotated left by 3 bits)
    plain = "plain"  # raw >> shift, the low bits dropped (e.g. (raw >> 3) / 1e4 m)


class PoseConvention(Enum):
    camera_to_world = "camera_to_world"  # the pose maps camera coordinates to world (7-Scenes, ScanNet, TUM)
    world_to_camera = "world_to_camera"  # the pose maps world coordinates to camera (extrinsics)


@dataclass
class RgbdFolderConfig:
    """A posed RGB-D folder: frame-XXXXXX.{color.*,depth.png,pose.txt} + camera-intrinsics.txt.
    A frame's files are ``<frame_prefix><digits>.<suffix>``; docs/layouts.md describes each key."""

    root: str = MISSING  # the folder
    intrinsics_file: str = "camera-intrinsics.txt"  # 3x3 K of the depth image, relative to root
    frame_prefix: str = "frame-"  # a frame's name = prefix + digits (frame-000000)
    depth_suffix: str = "depth.png"
    pose_suffix: str = "pose.txt"
    pose_convention: PoseConvention = PoseConvention.camera_to_world
    depth_scale: float = 1000.0  # metres = (raw, shifted) / depth_scale (1000 = millimetres)
    depth_bit_shift: int = 0  # right shift of the raw 16-bit depth before scaling (SUN3D: 3)
    depth_shift_kind: DepthShiftKind = DepthShiftKind.circular  # circular (SUN3D) | plain (raw >> shift)
    invalid_depth: List[int] = field(default_factory=lambda: [0, 65535])  # raw values, before the shift
    color_suffix: Optional[str] = "color.jpg"  # null = no colour; no such file at all = no colour (warning)
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
        for key in ("depth_suffix", "pose_suffix", "color_suffix", "label_suffix"):
            v = getattr(self, key)
            _check(v is None or (v and "/" not in v and "*" not in v), f"scene.rgbd_folder.{key}", v,
                   "a non-empty file name suffix, without / or *")
        _check(bool(self.intrinsics_file) and "*" not in self.intrinsics_file, "scene.rgbd_folder.intrinsics_file",
               self.intrinsics_file, "a file name relative to root")
        _check("/" not in self.frame_prefix and "*" not in self.frame_prefix, "scene.rgbd_folder.frame_prefix",
               self.frame_prefix, "a file name prefix without / or *")


class TumCamera(Enum):
    """Intrinsics presets of the TUM RGB-D benchmark's calibration page (colour camera, to which the
    depth images are registered): fx fy cx cy in pixels at 640x480."""

    auto = "auto"  # freiburg1/2/3 from the root folder's name (rgbd_dataset_freiburg1_xyz), else ros_default
    fr1 = "fr1"  # 517.3 516.5 318.6 255.3
    fr2 = "fr2"  # 520.9 521.0 325.1 249.7
    fr3 = "fr3"  # 535.4 539.2 320.1 247.6
    ros_default = "ros_default"  # 525.0 525.0 319.5 239.5 (OpenNI's default, TUM's point-cloud example)


@dataclass
class TumConfig:
    """A TUM RGB-D sequence (diffuser_lab.data.sources.tum): rgb.txt, depth.txt, groundtruth.txt with
    timestamps, associated by nearest timestamp; frames named after their RGB image's stem."""

    root: str = MISSING  # the sequence folder (rgbd_dataset_freiburg1_xyz)
    rgb_list: Optional[str] = "rgb.txt"  # 'timestamp file' lines; null = no colour
    depth_list: str = "depth.txt"  # 'timestamp file' lines; the frames
    groundtruth: str = "groundtruth.txt"  # 'timestamp tx ty tz qx qy qz qw', camera-to-world
    max_time_diff: float = 0.02  # seconds: nearest RGB / pose farther than this drops the frame (associate.py)
    depth_scale: float = 5000.0  # raw units per metre (TUM: 5000)
    camera: TumCamera = TumCamera.auto
    fx: Optional[float] = None  # pixels; set all four to override the camera preset
    fy: Optional[float] = None
    cx: Optional[float] = None
    cy: Optional[float] = None
    cloud_voxel: float = 0.02  # metres, for the back-projected cloud
    cloud_stride: int = 4
    max_depth: Optional[float] = None  # metres; ignore depth beyond it in the cloud
    frame_step: int = 1
    max_frames: Optional[int] = None

    def __post_init__(self) -> None:
        _check(self.max_time_diff > 0, "scene.tum.max_time_diff", self.max_time_diff, "> 0 seconds")
        _check(self.depth_scale > 0, "scene.tum.depth_scale", self.depth_scale, "> 0")
        given = [v is not None for v in (self.fx, self.fy, self.cx, self.cy)]
        _check(all(given) or not any(given), "scene.tum.fx/fy/cx/cy", (self.fx, self.fy, self.cx, self.cy),
               "all four set (pixels) or all null (= scene.tum.camera's preset)")
        _check(not any(given) or (self.fx > 0 and self.fy > 0), "scene.tum.fx/fy", (self.fx, self.fy), "> 0 pixels")
        _check(self.cloud_voxel > 0, "scene.tum.cloud_voxel", self.cloud_voxel, "> 0 metres")
        _check(self.cloud_stride >= 1, "scene.tum.cloud_stride", self.cloud_stride, ">= 1")
        _check(self.frame_step >= 1, "scene.tum.frame_step", self.frame_step, ">= 1")
        _check(self.max_frames is None or self.max_frames >= 1, "scene.tum.max_frames", self.max_frames,
               ">= 1 or null")


class DepthModel(Enum):
    perfect = "perfect"  # rendered depth as it is: exact z-depth
    sensor = "sensor"  # a Kinect-v1-like structured-light sensor (diffuser_lab.data.sensor)


class DepthQuantization(Enum):
    mm = "mm"  # millimetre steps (16-bit PNG depth)
    disparity = "disparity"  # the Kinect's 1/8-pixel disparity steps: z^2 / (f b) / 8
    none = "none"


@dataclass
class DepthNoiseConfig:
    """What the frames' depth is (diffuser_lab/data/sensor.py; docs/sensor.md): applied to rendered
    depth (scene=demo, mesh_views) and, with ``apply_to_real``, to the depth images of real sources."""

    model: DepthModel = DepthModel.perfect
    seed: int = 0  # with the frame's index, seeds its noise (conf/depth/sensor.yaml: ${seed})
    apply_to_real: bool = False  # also corrupt the depth of scannet / rgbd_folder / tum frames
    axial_scale: float = 1.0  # x Nguyen et al. 2012 sigma_z = 0.0012 + 0.0019 (z - 0.4)^2 m (+ angle term > 60 deg)
    lateral_scale: float = 1.0  # x Nguyen's sigma_L = 0.8 + 0.035 theta / (pi/2 - theta) px (640-px image) at edges
    projector_baseline: float = 0.075  # metres, IR camera -> projector (+x): shadows left of objects; 0 = none
    edge_jump: float = 0.05  # a 4-neighbour jump larger than this share of the nearer depth is a discontinuity
    edge_hole_px: int = 1  # hole band along discontinuities: the two pixels of the jump dilated by this - 1; 0 = none
    max_incidence_deg: float = 75.0  # no depth beyond this angle between ray and surface normal; 90 = never
    min_range: float = 0.5  # metres; sensor depth outside [min_range, max_range] is no return (Kinect: 0.5-4.5)
    max_range: float = 4.5
    quantization: DepthQuantization = DepthQuantization.mm
    disparity_focal_px: float = 580.0  # quantization=disparity: the IR camera's focal length (640 px)
    disparity_baseline: float = 0.075  # metres
    disparity_subpixel: float = 0.125  # disparity step, pixels (Kinect v1: 1/8)

    def __post_init__(self) -> None:
        for key in ("axial_scale", "lateral_scale", "projector_baseline"):
            _check(getattr(self, key) >= 0.0, f"depth.{key}", getattr(self, key), ">= 0 (0 = off)")
        _check(self.edge_jump > 0.0, "depth.edge_jump", self.edge_jump, "> 0 (a share of the depth)")
        _check(0 <= self.edge_hole_px <= 20, "depth.edge_hole_px", self.edge_hole_px, "in 0..20 pixels")
        _check(0.0 < self.max_incidence_deg <= 90.0, "depth.max_incidence_deg", self.max_incidence_deg,
               "in (0, 90] degrees")
        _check(0.0 <= self.min_range < self.max_range, "depth.min_range/max_range",
               (self.min_range, self.max_range), "0 <= min_range < max_range metres")
        for key in ("disparity_focal_px", "disparity_baseline", "disparity_subpixel"):
            _check(getattr(self, key) > 0.0, f"depth.{key}", getattr(self, key), "> 0")

    def sensor_model(self):
        """The :class:`~diffuser_lab.data.sensor.SensorModel` of these keys, or None for ``perfect``."""
        if self.model == DepthModel.perfect:
            return None
        from diffuser_lab.data.sensor import SensorModel

        return SensorModel(seed=self.seed, axial_scale=self.axial_scale, lateral_scale=self.lateral_scale,
                           projector_baseline=self.projector_baseline, edge_jump=self.edge_jump,
                           edge_hole_px=self.edge_hole_px, max_incidence_deg=self.max_incidence_deg,
                           min_range=self.min_range, max_range=self.max_range,
                           quantization=self.quantization.value, disparity_focal_px=self.disparity_focal_px,
                           disparity_baseline=self.disparity_baseline, disparity_subpixel=self.disparity_subpixel)


REQUIRED = {"mesh_views": "path", "scannet": "root", "rgbd_folder": "root", "tum": "root"}
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
    tum: Optional[TumConfig] = None
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
class OnnxConfig:
    """predictions=onnx: an exported segmentation network (diffuser_lab/data/networks.py)."""

    path: str = MISSING  # the .onnx file
    input_size: Optional[List[int]] = None  # [H, W] the network takes; null = its fixed size, else the frame's
    mean: List[float] = field(default_factory=lambda: [0.485, 0.456, 0.406])  # per input channel (network's order), pixel / 255
    std: List[float] = field(default_factory=lambda: [0.229, 0.224, 0.225])  # (ImageNet); [1,1,1] and 0 = raw
    channels: ChannelOrder = ChannelOrder.rgb  # channel order the network expects
    layout: TensorLayout = TensorLayout.nchw  # input tensor layout
    output: OnnxOutput = OnnxOutput.logits  # what the (first, or output_name) output holds
    output_layout: TensorLayout = TensorLayout.nchw  # layout of logits / probs outputs
    output_name: Optional[str] = None  # null = the graph's first output
    threads: int = 0  # onnxruntime intra-op threads; 0 = its default (all cores)

    def __post_init__(self) -> None:
        _check(self.input_size is None or (len(self.input_size) == 2 and min(self.input_size) >= 1),
               "predictions.onnx.input_size", self.input_size, "[H, W] >= 1 or null")
        _check(len(self.mean) == 3, "predictions.onnx.mean", self.mean, "3 values (one per channel)")
        _check(len(self.std) == 3 and min(self.std) > 0, "predictions.onnx.std", self.std, "3 values > 0")
        _check(self.threads >= 0, "predictions.onnx.threads", self.threads, ">= 0 (0 = onnxruntime's default)")


@dataclass
class PredictionsConfig:
    """What the frames' 2D labels are. The simulated mistakes are documented knob by knob in
    :func:`diffuser_lab.data.simulate.simulate_predictions` (defaults: 2D mIoU ~58 on the demo)."""

    source: PredictionSource = PredictionSource.simulated
    folder: Optional[str] = None  # files: the folder of per-frame predictions (named after the frames)
    mapping: Optional[str] = None  # files: network label ids -> taxonomy (e.g. nyu40_to_scannet20)
    # files: a frame's file name(s), {name} = the frame's name; a string or a list searched in order
    pattern: Any = field(default_factory=lambda: ["{name}.png", "{name}.label.png", "{name}.npy", "{name}.npz"])
    seed: int = 0
    strength: float = 1.0  # scales every simulated mistake; 0 = perfect labels
    jitter_px: float = 3.0  # std of the smooth boundary displacement field, pixels
    jitter_scale_px: float = 16.0  # its correlation length, pixels
    confuse_prob: float = 0.2  # probability that a connected region gets a wrong class
    confuse_max_frac: float = 0.3  # regions larger than this share of the image are never confused
    blob_count: float = 2.0  # mean number of wrong-class blobs per image (Poisson)
    blob_radius: float = 0.1  # mean blob radius, fraction of the image width
    blob_roughness: float = 0.35  # irregularity of blob outlines, 0 = discs
    # view-correlated mistakes and low-resolution output (docs/simulated-network.md)
    correlation: MistakeCorrelation = MistakeCorrelation.independent
    region_size: float = 0.5  # regions: world voxel edge cutting gt segments into 3D regions, metres
    persistence: float = 1.0  # regions: probability that a view shows a region's persistent decision
    confuse_region_frac: float = 1.0  # share of a confused region that is wrong (1 = all of it)
    view_gain: float = 0.0  # regions: confusion probability x (1 + view_gain * far/grazing in [0, 1])
    view_range_m: float = 4.0  # regions: range at which the "far" term saturates, metres
    output_stride: int = 1  # labels decided on stride x stride pixel cells, upsampled; 1 = off
    # model / onnx: a network run on each frame's RGB, its outputs (ids or probabilities in its own
    # label space) translated by ``mapping`` and cached on disk (docs/networks.md)
    model: Optional[Dict[str, Any]] = None  # model: {_target_: pkg.mod.callable, **kwargs}
    pass_depth: bool = False  # model: call model(rgb, depth) instead of model(rgb)
    onnx: Optional[OnnxConfig] = None  # onnx: set by conf/predictions/onnx.yaml
    cache_dir: Optional[str] = "~/.cache/diffuser-lab/predictions"  # model / onnx outputs; null = no cache

    def __post_init__(self) -> None:
        if isinstance(self.pattern, str):
            self.pattern = [self.pattern]
        self.pattern = list(self.pattern)
        for p in self.pattern:
            _check_pattern(p, "predictions.pattern", "name")
        _check(len(self.pattern) >= 1, "predictions.pattern", self.pattern, "at least one file name")
        if self.source == PredictionSource.model:
            target = (self.model or {}).get("_target_")
            _check(isinstance(target, str) and bool(target.strip()), "predictions.model._target_", target,
                   "a Python callable's import path (pkg.module.name) for predictions=model")
        if self.source == PredictionSource.onnx and self.onnx is None:
            raise ConfigError("predictions.onnx.path is required for predictions=onnx (pass predictions.onnx.path=...)")
        _check(self.strength >= 0.0, "predictions.strength", self.strength, ">= 0")
        _check(self.jitter_px >= 0.0, "predictions.jitter_px", self.jitter_px, ">= 0")
        _check(self.jitter_scale_px > 0.0, "predictions.jitter_scale_px", self.jitter_scale_px, "> 0")
        _check(0.0 <= self.confuse_prob <= 1.0, "predictions.confuse_prob", self.confuse_prob, "in [0, 1]")
        _check(0.0 <= self.confuse_max_frac <= 1.0, "predictions.confuse_max_frac", self.confuse_max_frac,
               "in [0, 1]")
        _check(self.blob_count >= 0.0, "predictions.blob_count", self.blob_count, ">= 0")
        _check(self.blob_radius > 0.0, "predictions.blob_radius", self.blob_radius, "> 0")
        _check(self.blob_roughness >= 0.0, "predictions.blob_roughness", self.blob_roughness, ">= 0")
        _check(self.region_size > 0.0, "predictions.region_size", self.region_size, "> 0 metres")
        _check(0.0 <= self.persistence <= 1.0, "predictions.persistence", self.persistence, "in [0, 1]")
        _check(0.0 < self.confuse_region_frac <= 1.0, "predictions.confuse_region_frac",
               self.confuse_region_frac, "in (0, 1]")
        _check(self.view_gain >= 0.0, "predictions.view_gain", self.view_gain, ">= 0")
        _check(self.view_range_m > 0.0, "predictions.view_range_m", self.view_range_m, "> 0 metres")
        _check(1 <= self.output_stride <= 64, "predictions.output_stride", self.output_stride, "in 1..64")


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
    sparse_classes: SparseClasses = SparseClasses.auto  # jacobi: a sparse per-point class set (docs/many-classes.md)
    classes_per_point: int = 16  # sparse_classes: the classes each point keeps (the M largest scores)

    def __post_init__(self) -> None:
        _check(self.max_iter >= 1, "solver.max_iter", self.max_iter, ">= 1")
        _check(self.tol >= 0.0, "solver.tol", self.tol, ">= 0")
        _check(1 <= self.classes_per_point <= 1024, "solver.classes_per_point", self.classes_per_point, "in 1..1024")


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
class CalibrationConfig:
    """How the methods' class distributions are scored (summary ``metrics.calibration``;
    :mod:`diffuser_lab.method.calibration`). Changes no label."""

    temperature: float = 1.0  # p <- softmax(log p / T) on every method's normalised Z / mass; 1 = as is
    bins: int = 15  # equal-width confidence bins of the ECE and the reliability diagram (Guo et al. 2017)

    def __post_init__(self) -> None:
        _check(self.temperature > 0, "calibration.temperature", self.temperature, "> 0")
        _check(self.bins >= 1, "calibration.bins", self.bins, ">= 1")


@dataclass
class ProtocolConfig:
    """Evaluation protocol (paper Sec. IV-A)."""

    name: Protocol = Protocol.global_3d
    window: int = 5  # single_frame: views fused per target frame in the multi-view rows (paper: 5)
    target_step: int = 1  # single_frame: evaluate every n-th frame of the sequence
    max_targets: Optional[int] = None  # single_frame: at most this many target frames
    # single_frame, a change to the paper's protocol (reported separately): a pixel without depth
    # takes the label (and distribution) of the nearest pixel with depth instead of counting as a miss
    fill_missing_depth: bool = False
    normals: FrameNormals = FrameNormals.knn  # single_frame: see FrameNormals
    normal_window_px: int = 7  # single_frame, normals=depth_image: box window of the depth smoothing

    def __post_init__(self) -> None:
        _check(self.window >= 1, "protocol.window", self.window, ">= 1")
        _check(self.target_step >= 1, "protocol.target_step", self.target_step, ">= 1")
        _check(self.normal_window_px >= 1, "protocol.normal_window_px", self.normal_window_px, ">= 1 pixels")


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


@dataclass
class OnlineConfig:
    """protocol=online (diffuser_lab/method/online.py, docs/online.md): per frame the evidence it
    adds, the graph extended for new points, ``steps`` warm-started steps of Z <- gamma P Z + B."""

    map: OnlineMap = OnlineMap.given
    solver: OnlineSolver = OnlineSolver.jacobi
    steps: Optional[int] = None  # per frame: Jacobi steps or GMRES's Krylov steps; null = 10 (given map), 16 (growing)
    # the batch iteration count the online result stands for; null = solver.max_iter. The steps
    # iterate Z <- gamma P Z + B with gamma = 2^(-2 / horizon): its fixed point weights P^t B by
    # gamma^t, half of the weight on t < horizon / 2 as the batch's T = horizon steps from Z = 0
    # do, so the result stays where the early-stopped batch is as frames accumulate
    horizon: Optional[int] = None
    discount: Optional[float] = None  # gamma itself; null = from horizon; 1 = the undiscounted iteration
    voxel_size: float = 0.03  # growing: map voxel edge, metres (online mappers use 2-10 cm; the paper 2 cm)
    depth_stride: int = 2  # growing: every n-th depth pixel in both directions is back-projected
    max_depth: Optional[float] = None  # growing: metres; depth beyond it adds no points (it still gives evidence)
    revisit: int = 5  # growing: a new point also gets the evidence of this many frames before the one that added it
    bad_frames: BadFrame = BadFrame.skip
    compare_batch: bool = True  # after the last frame, run the batch Diffuser on the same frames (and final cloud)

    def __post_init__(self) -> None:
        _check(self.steps is None or 1 <= self.steps <= 1000, "online.steps", self.steps, "in 1..1000 or null")
        _check(self.horizon is None or self.horizon >= 1, "online.horizon", self.horizon, ">= 1 or null")
        _check(self.discount is None or 0.0 < self.discount <= 1.0, "online.discount", self.discount,
               "in (0, 1] or null (= 2^(-2/horizon))")
        _check(self.voxel_size > 0.0, "online.voxel_size", self.voxel_size, "> 0 metres")
        _check(self.depth_stride >= 1, "online.depth_stride", self.depth_stride, ">= 1")
        _check(0 <= self.revisit <= 1000, "online.revisit", self.revisit, "in 0..1000 (0 = none)")
        _check(self.max_depth is None or self.max_depth > 0, "online.max_depth", self.max_depth,
               "> 0 metres or null")


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


@dataclass
class RecordConfig:
    """What the run records of the diffusion (diffuser_lab.recording); records never change results."""

    mode: RecordMode = RecordMode.both
    # recorded iterations: null = log-spaced 1, 2, 5, 10, 20, 50, 100, ... (1-2-5 steps); n = every
    # n-th; the first and the last always
    interval: Optional[int] = None
    z_precision: ZPrecision = ZPrecision.q8  # intermediate Z states in run.mcap (the last: float32, exact)
    clouds: CloudSchedule = CloudSchedule.decades  # labelled point clouds in run.mcap (Foxglove)
    max_image_side: int = 320  # frames' label (and colour) images in the records are strided to at most this many pixels
    max_depth_side: int = 160  # frames' depth images in run.rrd likewise (0: none); depth compresses ~5x worse than labels
    compression: McapCompression = McapCompression.zstd  # run.mcap's chunks
    retain_heap_mb: int = 256  # diffuser-lab (the CLI) has glibc keep this much freed memory for reuse (0: its defaults)
    # also stream run.rrd's content to a Rerun viewer as the run goes: null/off, spawn (start one),
    # or a viewer's gRPC URL (rerun+http://127.0.0.1:9876/proxy); run.rrd is written all the same
    live: Optional[str] = None

    def __post_init__(self) -> None:
        _check(self.interval is None or self.interval >= 1, "record.interval", self.interval, ">= 1 or null")
        _check(self.max_image_side >= 16, "record.max_image_side", self.max_image_side, ">= 16")
        _check(self.max_depth_side == 0 or self.max_depth_side >= 16, "record.max_depth_side", self.max_depth_side,
               "0 (no depth images) or >= 16")
        _check(0 <= self.retain_heap_mb <= 1024, "record.retain_heap_mb", self.retain_heap_mb, "in 0..1024")
        live = live_target(self.live)
        _check(live != "bad", "record.live", self.live,
               "null, off, spawn or a Rerun gRPC URL: rerun+http://HOST:PORT/proxy (or rerun+https://, rerun://)")
        _check(live is None or getattr(self.mode, "value", self.mode) in ("rerun", "both"), "record.live", self.live,
               "record=rerun or record=both (the live stream is run.rrd's content)")


_LIVE_URL = re.compile(r"(?:rerun|rerun\+https?)://(?:[^/\s:\[\]]+|\[[0-9A-Fa-f:.]+\])(?::(\d{1,5}))?/proxy")


def live_target(value: Any) -> Optional[str]:
    """record.live -> None (off), "spawn", a gRPC URL as Rerun's GrpcSink takes it
    (scheme rerun://, rerun+http:// or rerun+https://, host[:port], path /proxy), or "bad"."""
    if value is None or value is False or str(value).strip().lower() in ("", "off", "none", "null", "false"):
        return None
    v = str(value).strip()
    if v == "spawn":
        return v
    m = _LIVE_URL.fullmatch(v)
    if m and (m.group(1) is None or 1 <= int(m.group(1)) <= 65535):
        return v
    return "bad"


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
