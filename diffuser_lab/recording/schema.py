"""Protobuf schemas of run.mcap, built at import time with protobuf's descriptor API (no protoc).

The schemas travel inside every run.mcap (a ``FileDescriptorSet`` per schema record, encoding
``protobuf``), so any MCAP tool with protobuf support (Foxglove, ``rerun mcap convert``,
``mcap-protobuf-support``'s decoder) decodes the messages without this package. As .proto text::

    syntax = "proto3";
    package diffuser_lab;

    message Camera {                 // one frame's camera (pinhole, world -> camera pose)
      string name = 1;
      uint32 width = 2;  uint32 height = 3;
      repeated double K = 4;         // 3x3 row-major intrinsics, pixels
      repeated double T_cw = 5;      // 4x4 row-major world -> camera, metres
    }
    message RunInfo {                // once, after the evidence: what the diffusion runs on
      string scene = 1;  string method = 2;  string taxonomy = 3;
      repeated string class_names = 4;
      bytes class_colors = 5;        // (C, 3) uint8 RGB
      uint32 n_points = 6;           // N original points
      uint32 n_work_points = 7;      // M points the diffusion runs on (voxel centroids or the N points)
      bytes work_points = 8;         // (M, 3) float32 little-endian, world metres
      bytes original_to_work = 9;    // (N,) int32: nearest work point of each original point; empty when M == N
      bytes bayesian_labels = 10;    // (M,) int16 Bayesian-fusion labels, -1 = unlabeled
      bytes seen = 11;               // (M,) uint8: 1 where the point received pixel mass
      uint32 interval = 12;  uint32 max_iter = 13;
      string z_dtype = 14;           // "float32" | "float16"
      repeated Camera cameras = 15;
    }
    message ZState {                 // every recorded iteration: the full score matrix Z
      uint32 iteration = 1;
      uint32 n_points = 2;           // M rows
      uint32 n_classes = 3;          // C columns
      string dtype = 4;              // "float32" | "float16" | "q8" | "q16"
      bytes data = 5;                // little-endian, (C, M) row-major when class_major, else (M, C);
                                     // float32 / float16 values, or uint8 / uint16 shares for q8 / q16
      double scale = 6;              // float16: Z (the paper's units, Eq. 10) = data * scale; else 1
      bool class_major = 7;          // true: data holds Z transposed, one class's M scores after
                                     // another (its zeros then lie together and compress ~25% better)
      bytes row_sums = 8;            // q8 / q16: (M,) float32 sum_c Z_ic; Z_ic = row_sums[i] * data[c, i] / (2^bits - 1)
      bytes labels = 9;              // q8 / q16 / float16: (M,) int16 labels of the exact Z (Eq. 16), -1 = unlabeled
    }
    message IterationMetrics {       // every recorded iteration
      uint32 iteration = 1;
      double residual = 2;           // max|Z_t - Z_{t-1}| / max|Z_t| of this iteration
      uint32 n_changed = 3;          // labels changed since the previous recorded iteration (work cloud)
      uint32 previous_iteration = 4; // 0 for the first recorded iteration
      double miou = 5;               // percent on the original points; NaN without ground truth
      double accuracy = 6;           // percent; NaN without ground truth
      double coverage = 7;           // percent of work points with a label
      double mean_confidence = 8;    // mean over labelled points of max_c Z / sum_c Z
    }
    message OnlineFrame {            // protocol=online: every frame taken (FrameStats + metrics so far)
      uint32 index = 1;              // the frame's index in the sequence
      string name = 2;
      double latency_ms = 3;  double map_ms = 4;  double evidence_ms = 5;  double steps_ms = 6;
      uint32 points = 7;             // map points after the frame
      uint32 new_points = 8;  uint32 seen = 9;  uint32 graph_rows = 10;  uint32 steps = 11;
      double residual = 12;          // the last step's max|Z_t - Z_t-1| / max Z_t
      uint32 changed = 13;           // points whose label changed
      string skipped = 14;           // why the frame was skipped, else empty
      double diffuser_miou = 15;  double diffuser_accuracy = 16;   // percent so far; NaN without ground truth
      double bayesian_miou = 17;  double bayesian_accuracy = 18;
      double coverage = 19;          // percent of map points with a label; NaN without ground truth
      uint32 count = 20;             // 1-based count of frames taken
      string state = 21;             // how /diffuser_lab/z keeps this frame's Z: "" (not kept), q8, ..., float32
      string extra = 22;             // other metrics so far, JSON
    }
    message FeatureView {            // a features run, once after the evidence: the fixed projection
      uint32 dim = 1;                // D
      bytes basis = 2;               // (3, D) float32: the PCA's axes (fitted on the seen points' unit average features)
      bytes mean = 3;                // (D,) float32: the fitted rows' mean
      bytes lo = 4;  bytes hi = 5;   // (3,) float32: the component values mapped to 0 and 255
      string query = 6;              // the query of the similarity
      bytes embedding = 7;           // (D,) float32 its unit embedding
      double sim_lo = 8;  double sim_hi = 9;   // the cosines mapped to 0 and 254
      uint32 n_fit = 10;             // rows the PCA was fitted on
    }
    message TargetFrame {            // protocol=single_frame: each target frame, before its diffusion
      uint32 index = 1;              // the target frame's index in the sequence
      string name = 2;
      uint32 count = 3;              // 1-based count of targets
      uint32 start = 4;              // its first step on the run's step timeline: iteration t is step start + t
      repeated uint32 window = 5;    // the frames it is labelled from (its views; the target among them)
      uint32 n_points = 6;           // M: its back-projected depth (voxel centroids with scene.voxel_size)
      bytes work_points = 7;         // (M, 3) float32, world metres
      bytes work_gt = 8;             // (M,) int16 the most frequent ground truth of each point's pixels, -1 none
      uint32 width = 9;  uint32 height = 10;   // the frame's image
      bytes pixels = 11;             // (height, width) int32 each pixel's work point, -1 none
      bytes gt_image = 12;           // (height, width) int16 ground truth, -1 unlabeled
      string method = 13;            // the Table II row whose diffusion is recorded ("diffuser")
      uint32 views = 14;             // ... and its views
      repeated Camera cameras = 15;  // the window's cameras, in window order (full-size K)
    }
    message FeatureColors {          // a features run, every recorded iteration
      uint32 iteration = 1;
      uint32 n_points = 2;           // M
      bytes rgb = 3;                 // (M, 3) uint8: ((unit feature - mean) . basis - lo) * 255 / (hi - lo), 128 grey: no feature
      bytes similarity = 4;          // (M,) uint8: cosine = sim_lo + s * (sim_hi - sim_lo) / 254; 255: no feature
    }
"""
from __future__ import annotations

from google.protobuf import descriptor_pb2, descriptor_pool
from google.protobuf.message_factory import GetMessageClass

PACKAGE = "diffuser_lab"
FILE_NAME = "diffuser_lab/recording.proto"

_F = descriptor_pb2.FieldDescriptorProto
_SCALAR = {
    "string": _F.TYPE_STRING, "bytes": _F.TYPE_BYTES, "uint32": _F.TYPE_UINT32,
    "double": _F.TYPE_DOUBLE, "bool": _F.TYPE_BOOL,
}

# (message, [(field, number, type, repeated)]) — kept in step with the .proto text above
_MESSAGES = [
    ("Camera", [("name", 1, "string", False), ("width", 2, "uint32", False), ("height", 3, "uint32", False),
                ("K", 4, "double", True), ("T_cw", 5, "double", True)]),
    ("RunInfo", [("scene", 1, "string", False), ("method", 2, "string", False), ("taxonomy", 3, "string", False),
                 ("class_names", 4, "string", True), ("class_colors", 5, "bytes", False),
                 ("n_points", 6, "uint32", False), ("n_work_points", 7, "uint32", False),
                 ("work_points", 8, "bytes", False), ("original_to_work", 9, "bytes", False),
                 ("bayesian_labels", 10, "bytes", False), ("seen", 11, "bytes", False),
                 ("interval", 12, "uint32", False), ("max_iter", 13, "uint32", False),
                 ("z_dtype", 14, "string", False), ("cameras", 15, ".diffuser_lab.Camera", True)]),
    ("ZState", [("iteration", 1, "uint32", False), ("n_points", 2, "uint32", False),
                ("n_classes", 3, "uint32", False), ("dtype", 4, "string", False), ("data", 5, "bytes", False),
                ("scale", 6, "double", False), ("class_major", 7, "bool", False),
                ("row_sums", 8, "bytes", False), ("labels", 9, "bytes", False)]),
    ("IterationMetrics", [("iteration", 1, "uint32", False), ("residual", 2, "double", False),
                          ("n_changed", 3, "uint32", False), ("previous_iteration", 4, "uint32", False),
                          ("miou", 5, "double", False), ("accuracy", 6, "double", False),
                          ("coverage", 7, "double", False), ("mean_confidence", 8, "double", False)]),
    ("OnlineFrame", [("index", 1, "uint32", False), ("name", 2, "string", False), ("latency_ms", 3, "double", False),
                     ("map_ms", 4, "double", False), ("evidence_ms", 5, "double", False),
                     ("steps_ms", 6, "double", False), ("points", 7, "uint32", False),
                     ("new_points", 8, "uint32", False), ("seen", 9, "uint32", False),
                     ("graph_rows", 10, "uint32", False), ("steps", 11, "uint32", False),
                     ("residual", 12, "double", False), ("changed", 13, "uint32", False),
                     ("skipped", 14, "string", False), ("diffuser_miou", 15, "double", False),
                     ("diffuser_accuracy", 16, "double", False), ("bayesian_miou", 17, "double", False),
                     ("bayesian_accuracy", 18, "double", False), ("coverage", 19, "double", False),
                     ("count", 20, "uint32", False), ("state", 21, "string", False), ("extra", 22, "string", False)]),
    ("FeatureView", [("dim", 1, "uint32", False), ("basis", 2, "bytes", False), ("mean", 3, "bytes", False),
                     ("lo", 4, "bytes", False), ("hi", 5, "bytes", False), ("query", 6, "string", False),
                     ("embedding", 7, "bytes", False), ("sim_lo", 8, "double", False), ("sim_hi", 9, "double", False),
                     ("n_fit", 10, "uint32", False)]),
    ("TargetFrame", [("index", 1, "uint32", False), ("name", 2, "string", False), ("count", 3, "uint32", False),
                     ("start", 4, "uint32", False), ("window", 5, "uint32", True), ("n_points", 6, "uint32", False),
                     ("work_points", 7, "bytes", False), ("work_gt", 8, "bytes", False), ("width", 9, "uint32", False),
                     ("height", 10, "uint32", False), ("pixels", 11, "bytes", False), ("gt_image", 12, "bytes", False),
                     ("method", 13, "string", False), ("views", 14, "uint32", False),
                     ("cameras", 15, ".diffuser_lab.Camera", True)]),
    ("FeatureColors", [("iteration", 1, "uint32", False), ("n_points", 2, "uint32", False),
                       ("rgb", 3, "bytes", False), ("similarity", 4, "bytes", False)]),
]


def file_descriptor_proto() -> descriptor_pb2.FileDescriptorProto:
    """The schema file as a FileDescriptorProto (what the .proto text above compiles to)."""
    fd = descriptor_pb2.FileDescriptorProto(name=FILE_NAME, package=PACKAGE, syntax="proto3")
    for msg_name, fields in _MESSAGES:
        m = fd.message_type.add(name=msg_name)
        for name, number, typ, repeated in fields:
            f = m.field.add(name=name, number=number)
            f.label = _F.LABEL_REPEATED if repeated else _F.LABEL_OPTIONAL
            if typ.startswith("."):
                f.type, f.type_name = _F.TYPE_MESSAGE, typ
            else:
                f.type = _SCALAR[typ]
    return fd


_POOL = descriptor_pool.DescriptorPool()
_FILE = _POOL.Add(file_descriptor_proto())

Camera = GetMessageClass(_POOL.FindMessageTypeByName(f"{PACKAGE}.Camera"))
RunInfo = GetMessageClass(_POOL.FindMessageTypeByName(f"{PACKAGE}.RunInfo"))
ZState = GetMessageClass(_POOL.FindMessageTypeByName(f"{PACKAGE}.ZState"))
IterationMetrics = GetMessageClass(_POOL.FindMessageTypeByName(f"{PACKAGE}.IterationMetrics"))
OnlineFrame = GetMessageClass(_POOL.FindMessageTypeByName(f"{PACKAGE}.OnlineFrame"))
FeatureView = GetMessageClass(_POOL.FindMessageTypeByName(f"{PACKAGE}.FeatureView"))
FeatureColors = GetMessageClass(_POOL.FindMessageTypeByName(f"{PACKAGE}.FeatureColors"))
TargetFrame = GetMessageClass(_POOL.FindMessageTypeByName(f"{PACKAGE}.TargetFrame"))


def file_descriptor_set(message_class) -> bytes:
    """Serialized ``FileDescriptorSet`` of ``message_class``'s file and its dependencies (the
    MCAP ``protobuf`` schema encoding)."""
    fds = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(fdesc) -> None:
        for dep in fdesc.dependencies:
            if dep.name not in seen:
                seen.add(dep.name)
                add(dep)
        fdesc.CopyToProto(fds.file.add())

    add(message_class.DESCRIPTOR.file)
    return fds.SerializeToString()


__all__ = ["Camera", "RunInfo", "ZState", "IterationMetrics", "OnlineFrame", "FeatureView", "FeatureColors", "TargetFrame",
           "file_descriptor_set", "file_descriptor_proto"]
