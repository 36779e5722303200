"""A 2D network in the loop: ``predictions=model`` (any Python callable) and ``predictions=onnx``.

Per frame, the network sees the frame's colour image ``rgb`` (H, W, 3) uint8 (registered to the
depth image, so H, W are the depth's; ``predictions.pass_depth`` adds ``depth`` (H, W) float32
metres, 0 = none) and returns, in ITS OWN label space,

- label ids: (h, w) integer array, or
- class probabilities: (h, w, C) float array, scores >= 0 (rows need not sum to 1).

Anything ``np.asarray`` turns into such an array is accepted (a CPU torch tensor too). The
output is translated by ``predictions.mapping`` (a class-mapping CSV,
:mod:`diffuser_lab.data.mapping`): ids through its lookup table; probabilities by summing the
source columns of each target class (columns mapped to ``ignore`` are dropped, a pixel left
without mass is no evidence). Without a mapping the output already is in the scene's taxonomy.
An output of another size is resized to the depth's: nearest for ids, bilinear for
probabilities (pixel centres aligned).

Outputs are cached on disk, one compressed ``.npz`` per frame (ids in the smallest integer type,
probabilities as float16; the run uses the float16-rounded values cached or not, so a cached run
gives the same labels), under ``cache_dir / <model key> / <scene> / <frame>-<rgb hash>.npz``:

- model key: sha256 of the ``_target_`` and its kwargs (``predictions=model``), or of the ONNX
  file's bytes and the preprocessing keys (``predictions=onnx``), with ``pass_depth``;
- the frame: the scene's and frame's names and a hash of the rgb bytes (and depth, when passed).

So a sweep over graph or solver parameters runs the network once; a changed kwarg, ONNX file or
image is a new entry. The network is built (imported, weights loaded) only at the first frame
that is not cached. What is NOT in the key: the content of weight files a callable loads itself
(change a kwarg, e.g. a version, or clear the cache, when they change).
"""
from __future__ import annotations

import dataclasses
import hashlib
import inspect
import json
import os
import re
import tempfile
import warnings
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np
from omegaconf import OmegaConf

from diffuser_lab import progress
from diffuser_lab.config import ChannelOrder, OnnxConfig, OnnxOutput, PredictionsConfig, TensorLayout

from . import inputs
from .arrays import open_npz
from .frames import LazyFrames
from .mapping import ClassMapping, load_mapping
from .images import resize_bilinear, resize_nearest
from .scene import IGNORE, Frame, Taxonomy

__all__ = ["NetworkPredictor", "build_callable", "OnnxModel", "translate", "model_key",
           "onnx_key", "check_target", "model_predictions", "onnx_predictions"]

CACHE_VERSION = 1  # bump when the cached file's content changes meaning


# --------------------------------------------------------------------------- building the network

def check_target(spec: dict) -> Any:
    """The object ``spec['_target_']`` names (imported, not called); ValueError naming the key."""
    target = str(spec.get("_target_"))
    try:
        return _locate(target)
    except Exception as exc:  # noqa: BLE001 - import errors of user code come in many types
        raise ValueError(f"predictions.model._target_={target}: cannot import it "
                         f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None


def _locate(path: str) -> Any:
    """``pkg.mod.attr.attr`` -> the object: the longest importable module prefix, then attributes.
    A module that exists but fails to import (e.g. a missing dependency of it) raises its error."""
    import importlib

    parts = path.split(".")
    if not all(parts):
        raise ImportError(f"{path!r} is not a dotted import path (pkg.module.name)")
    for i in range(len(parts), 0, -1):
        name = ".".join(parts[:i])
        try:
            obj = importlib.import_module(name)
        except ModuleNotFoundError as e:
            if e.name and (name == e.name or name.startswith(e.name + ".")):
                continue  # this prefix is not a module: try a shorter one
            raise
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                raise AttributeError(f"{name} has no attribute {attr!r}")
            obj = getattr(obj, attr)
        return obj
    raise ModuleNotFoundError(f"no module named {parts[0]!r} (is it installed, or on PYTHONPATH?)")


def _is_frame_function(obj: Any, kwargs: dict) -> bool:
    """Whether ``obj`` is a function that takes the frame itself: its first parameter is
    positional, has no default and is not given in the kwargs (so calling it with the kwargs
    alone, as Hydra would, fails). A class, or a function needing no argument, is a factory."""
    if inspect.isclass(obj) or not callable(obj):
        return False
    try:
        params = list(inspect.signature(obj).parameters.values())
    except (TypeError, ValueError):  # builtins without a signature: call as a factory
        return False
    for p in params:
        if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) and p.name not in kwargs:
            return p.default is p.empty
    return False


def build_callable(spec: dict) -> Callable:
    """``predictions.model`` -> the per-frame callable, through ``hydra.utils.instantiate``.

    - a class: instantiated with the kwargs; the instance is called per frame;
    - a function whose first parameter is the frame (``fn(rgb, ..., **kwargs)``): bound to the
      kwargs (Hydra's ``_partial_``), called per frame;
    - any other function (a factory, e.g. ``load_model(weights=...)``): called with the kwargs,
      what it returns is called per frame.

    An explicit ``_partial_`` in ``spec`` is honoured. Kwargs reach the target as plain Python
    values (``_convert_: all``) unless ``spec`` says otherwise.
    """
    from hydra.utils import instantiate

    obj = check_target(spec)
    kwargs = {k: v for k, v in spec.items() if not str(k).startswith("_")}
    spec = dict(spec)
    spec.setdefault("_convert_", "all")
    if "_partial_" not in spec and _is_frame_function(obj, kwargs):
        spec["_partial_"] = True
    try:
        model = instantiate(spec)
    except Exception as exc:  # noqa: BLE001 - the user's constructor: name the key and the cause
        cause = exc.__cause__ or exc
        raise ValueError(f"predictions.model._target_={spec['_target_']}: building it failed "
                         f"({type(cause).__name__}: {str(cause).splitlines()[0] if str(cause) else ''})") from exc
    if not callable(model):
        raise ValueError(f"predictions.model._target_={spec['_target_']} gave a {type(model).__name__}, "
                         f"expected a callable model(rgb) -> ids or probabilities")
    return model


def record_model_files(target: Any, spec: dict) -> None:
    """A Python network's files as the run's inputs (role ``network``): the source file of the
    ``_target_``'s module, and every keyword argument naming an existing file (its weights)."""
    try:
        src = inspect.getsourcefile(inspect.getmodule(target) or target)
    except TypeError:  # a builtin: no file
        src = None
    files = [src] + [v for k, v in spec.items() if not str(k).startswith("_") and isinstance(v, str)]
    for f in files:  # the module and a few keyword arguments
        if f and os.path.isfile(os.path.expanduser(f)):
            inputs.record(os.path.expanduser(f), "network")


class OnnxModel:
    """An ONNX segmentation network on onnxruntime's CPU provider, as a callable
    ``model(rgb (H, W, 3) uint8) -> ids (h, w) int64 | probabilities (h, w, C) float32``.

    Preprocessing: resize to the input size (bilinear, Pillow), channel order as configured,
    ``(x / 255 - mean) / std`` (mean/std in the network's channel order), layout as configured,
    batch of one. Logits get a softmax over classes.
    """

    def __init__(self, cfg: OnnxConfig):
        try:
            import onnxruntime as ort
        except ImportError:
            raise ModuleNotFoundError("predictions=onnx needs onnxruntime: pip install 'diffuser-lab[onnx]'") from None

        self.cfg = cfg
        path = Path(cfg.path).expanduser()
        so = ort.SessionOptions()
        if cfg.threads:
            so.intra_op_num_threads = int(cfg.threads)
        so.inter_op_num_threads = 1
        so.log_severity_level = 3  # onnxruntime's warnings (e.g. unused initialisers) are not the user's
        try:
            self.session = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
        except Exception as exc:  # noqa: BLE001 - onnxruntime raises its own exception types
            raise ValueError(f"predictions.onnx.path={path}: not a loadable ONNX model "
                             f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None
        inputs = self.session.get_inputs()
        if len(inputs) != 1:
            raise ValueError(f"predictions.onnx.path={path}: the graph takes {len(inputs)} inputs "
                             f"({', '.join(i.name for i in inputs)}), expected one image tensor")
        inp = inputs[0]
        self.input_name = inp.name
        types = {"tensor(float)": np.float32, "tensor(float16)": np.float16, "tensor(double)": np.float64}
        if inp.type not in types:
            raise ValueError(f"predictions.onnx.path={path}: input {inp.name} is {inp.type}, expected a float tensor")
        self.input_dtype = types[inp.type]
        shape = list(inp.shape)
        if len(shape) != 4:
            raise ValueError(f"predictions.onnx.path={path}: input {inp.name} has shape {shape}, expected 4-D "
                             f"(1, 3, H, W) or (1, H, W, 3) (predictions.onnx.layout)")
        hw = shape[2:4] if cfg.layout == TensorLayout.nchw else shape[1:3]
        fixed = [d if isinstance(d, int) and d > 0 else None for d in hw]
        if cfg.input_size is not None:
            self.size: Optional[tuple[int, int]] = (int(cfg.input_size[0]), int(cfg.input_size[1]))
            if any(f is not None and f != s for f, s in zip(fixed, self.size)):
                raise ValueError(f"predictions.onnx.input_size={list(self.size)}: the graph's input {inp.name} "
                                 f"is fixed at {shape}")
        else:
            self.size = (fixed[0], fixed[1]) if None not in fixed else None  # None: the frame's size
        names = [o.name for o in self.session.get_outputs()]
        if cfg.output_name is not None and cfg.output_name not in names:
            raise ValueError(f"predictions.onnx.output_name={cfg.output_name}: the graph's outputs are "
                             f"{', '.join(names)}")
        self.output_name = cfg.output_name or names[0]
        self.mean = np.asarray(cfg.mean, np.float32)
        self.std = np.asarray(cfg.std, np.float32)

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        cfg = self.cfg
        if self.size is not None and tuple(rgb.shape[:2]) != self.size:
            rgb = resize_bilinear(np.asarray(rgb, np.uint8), self.size)
        if cfg.channels == ChannelOrder.bgr:
            rgb = rgb[..., ::-1]
        x = (rgb.astype(np.float32) / 255.0 - self.mean) / self.std  # mean/std in the network's order
        x = x.transpose(2, 0, 1) if cfg.layout == TensorLayout.nchw else x
        x = np.ascontiguousarray(x[None], dtype=self.input_dtype)
        out = np.asarray(self.session.run([self.output_name], {self.input_name: x})[0])
        where = f"predictions.onnx: output {self.output_name} of shape {out.shape}"
        if cfg.output == OnnxOutput.ids:
            while out.ndim > 2 and out.shape[0] == 1:
                out = out[0]
            if out.ndim != 2:
                raise ValueError(f"{where}, expected class ids (1, H, W) or (H, W) (predictions.onnx.output=ids)")
            if out.dtype.kind == "f":
                out = np.rint(out)
            return out.astype(np.int64)
        if out.ndim == 4 and out.shape[0] == 1:
            out = out[0]
        if out.ndim != 3:
            raise ValueError(f"{where}, expected (1, C, H, W) or (1, H, W, C) {cfg.output.value}")
        if cfg.output_layout == TensorLayout.nchw:
            out = np.moveaxis(out, 0, 2)
        out = out.astype(np.float32)
        if cfg.output == OnnxOutput.features:  # embeddings: as they are (predictions=features)
            return out
        if cfg.output == OnnxOutput.logits:
            out = np.exp(out - out.max(axis=2, keepdims=True))
            out /= out.sum(axis=2, keepdims=True)
        return out


# --------------------------------------------------------------------------- outputs -> taxonomy

def as_output(raw: Any, what: str) -> np.ndarray:
    """A network's raw output -> (h, w) int64 ids or (h, w, C) float16-rounded float32 scores."""
    try:
        arr = np.asarray(raw)
    except Exception as exc:  # noqa: BLE001 - e.g. a CUDA tensor
        raise ValueError(f"{what}: output of type {type(raw).__name__} is not an array "
                         f"({type(exc).__name__}; return a numpy array or CPU tensor)") from None
    if arr.ndim == 2 and arr.dtype.kind in "iub":
        return arr.astype(np.int64)
    if arr.ndim == 3 and arr.dtype.kind == "f":
        if not np.isfinite(arr).all() or (arr < 0).any():
            raise ValueError(f"{what}: class scores contain NaN/inf or negative values, expected probabilities "
                             f">= 0 (apply a softmax to logits)")
        # float16 is what the cache keeps: round here too, so a cached run gives the same labels
        return arr.astype(np.float16).astype(np.float32)
    raise ValueError(f"{what}: output of shape {arr.shape} dtype {arr.dtype}, expected (H, W) integer class ids "
                     f"or (H, W, C) float class probabilities")


def as_features(raw: Any, what: str, layout: str = "auto") -> np.ndarray:
    """A network's raw embedding output -> (h, w, D) float16 (what the cache keeps; NaN = no
    feature): (h, w, D) or (D, h, w) as ``layout`` (``predictions.layout``: auto, hwd, dhw) says."""
    try:
        arr = np.asarray(raw)
    except Exception as exc:  # noqa: BLE001 - e.g. a CUDA tensor
        raise ValueError(f"{what}: output of type {type(raw).__name__} is not an array "
                         f"({type(exc).__name__}; return a numpy array or CPU tensor)") from None
    if arr.ndim == 4 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim != 3 or arr.dtype.kind != "f":
        raise ValueError(f"{what}: output of shape {arr.shape} dtype {arr.dtype}, expected (h, w, D) or (D, h, w) "
                         f"float embeddings (predictions=features)")
    if layout == "dhw" or (layout == "auto" and arr.shape[0] < min(arr.shape[1:])):
        arr = np.moveaxis(arr, 0, 2)
    return np.ascontiguousarray(arr, np.float16)


def translate(out: np.ndarray, mapping: Optional[ClassMapping], taxonomy: Taxonomy,
              shape: tuple[int, int], what: str) -> tuple[Optional[np.ndarray], Optional[np.ndarray], int]:
    """A network output in its own label space -> the frame's ``(labels, probs, n_unmapped)``.

    Args:
        out: (h, w) int ids or (h, w, C_src) float scores (from :func:`as_output`).
        mapping: source ids -> ``taxonomy`` ids; None = ``out`` already is in ``taxonomy``.
        shape: (H, W) of the frame's depth image (the result's size).
    Returns:
        labels (H, W) int16 (IGNORE = unmapped) or None; probs (H, W, C) float32 or None;
        n_unmapped: pixels whose (argmax) source class maps to ignore.
    """
    C = taxonomy.num_classes
    if out.ndim == 2:
        ids = resize_nearest(out, shape)
        if mapping is not None:
            try:
                labels, n_unmapped = mapping.apply(ids)
            except ValueError as e:
                raise ValueError(f"{what}: {e}") from None
            return labels, None, n_unmapped
        lo, hi = int(ids.min()), int(ids.max())
        if lo < IGNORE or hi >= C:
            raise ValueError(f"{what}: label ids in [{lo}, {hi}], expected {taxonomy.name} ids 0..{C - 1}; "
                             f"pass predictions.mapping= to translate the network's label space")
        return ids.astype(np.int16), None, int(np.count_nonzero(ids == IGNORE))
    cs = out.shape[2]
    if mapping is None:
        if cs != C:
            raise ValueError(f"{what}: {cs} class scores per pixel, expected {C} ({taxonomy.name}); pass "
                             f"predictions.mapping= to translate the network's {cs} classes")
        probs, n_unmapped = out, 0
    else:
        listed = mapping.known[:cs] if cs <= mapping.num_source else None
        if listed is None or not listed.all():
            missing = np.flatnonzero(~listed) if listed is not None else np.arange(mapping.num_source, cs)
            raise ValueError(f"{what}: {cs} class scores per pixel, but mapping {mapping.source} does not list "
                             f"source ids {', '.join(map(str, missing[:10]))}{' ...' if missing.size > 10 else ''}")
        lut = mapping.lut[:cs].astype(np.int64)
        M = np.zeros((cs, C), np.float32)  # source column -> target class (sum of columns)
        kept = np.flatnonzero(lut != IGNORE)
        M[kept, lut[kept]] = 1.0
        probs = (out.reshape(-1, cs) @ M).reshape(out.shape[0], out.shape[1], C)
        n_unmapped = int(np.count_nonzero(lut[np.argmax(out, axis=2)] == IGNORE))
        n_unmapped = int(round(n_unmapped * (shape[0] * shape[1]) / max(out.shape[0] * out.shape[1], 1)))
    return None, np.ascontiguousarray(resize_bilinear(probs, shape), dtype=np.float32), n_unmapped



# --------------------------------------------------------------------------- cache and per-frame source

def _digest(*parts: bytes) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(p)
    return h.hexdigest()


def _canon(obj: Any) -> bytes:
    return json.dumps(obj, sort_keys=True, default=str, separators=(",", ":")).encode()


def model_key(spec: dict, pass_depth: bool) -> tuple[str, dict]:
    """(key, identity) of ``predictions=model``: the ``_target_`` and kwargs, and ``pass_depth``."""
    ident = {"source": "model", "model": spec, "pass_depth": bool(pass_depth), "version": CACHE_VERSION}
    return _digest(_canon(ident))[:20], ident


def onnx_key(cfg: OnnxConfig) -> tuple[str, dict]:
    """(key, identity) of ``predictions=onnx``: the file's sha256 and every preprocessing /
    output key (not ``threads``, which does not change the outputs)."""
    path = Path(cfg.path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"predictions.onnx.path={path} does not exist")
    sha = inputs.record(path, "network") or inputs.sha256_file(path)[1]  # the run's input, its hash cached
    ident = {"source": "onnx", "file": path.name, "sha256": sha, "version": CACHE_VERSION,
             "input_size": None if cfg.input_size is None else [int(v) for v in cfg.input_size],
             "mean": [float(v) for v in cfg.mean], "std": [float(v) for v in cfg.std],
             "channels": cfg.channels.value, "layout": cfg.layout.value, "output": cfg.output.value,
             "output_layout": cfg.output_layout.value, "output_name": cfg.output_name}
    return _digest(_canon(ident))[:20], ident


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", str(name)).strip("._")[:96] or "_"


class _DiskCache:
    """One model's outputs: ``root / key / <scene> / <frame>-<hash>.npz`` and ``root / key / model.json``."""

    def __init__(self, root: Optional[str], key: str, ident: dict):
        self.dir = Path(root).expanduser() / key if root else None
        self.ident = ident
        self._failed = False

    def path(self, scene: str, frame: str, digest: str) -> Optional[Path]:
        if self.dir is None or self._failed:
            return None
        return self.dir / _safe(scene) / f"{_safe(frame)}-{digest[:16]}.npz"

    def load(self, path: Optional[Path]) -> Optional[np.ndarray]:
        if path is None or not path.is_file():
            return None
        try:  # the one checked reader; not a run's input (the network and the frames are)
            with open_npz(path, "a network's cached output (features, ids or probs)", role=None) as z:
                if "features" in z:
                    return z.read("features", ndim=3, kinds="f").astype(np.float16)
                if "ids" in z:
                    return z.read("ids", ndim=2, kinds="iu").astype(np.int64)
                return z.read("probs", ndim=3, kinds="f").astype(np.float32)
        except (ValueError, OSError):  # a torn or foreign file: computed again and replaced
            return None

    def save(self, path: Optional[Path], out: np.ndarray) -> None:
        if path is None:
            return
        if out.dtype == np.float16:  # a feature map (predictions=features)
            arrays = {"features": out}
        elif out.ndim == 2:
            lo, hi = (int(out.min()), int(out.max())) if out.size else (0, 0)
            dtype = next(t for t in (np.uint8, np.int16, np.int32, np.int64)
                         if np.iinfo(t).min <= lo and hi <= np.iinfo(t).max)
            arrays = {"ids": out.astype(dtype)}
        else:
            arrays = {"probs": out.astype(np.float16)}
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            meta = self.dir / "model.json"
            if not meta.is_file():
                _atomic(meta, lambda fh: fh.write(json.dumps(self.ident, indent=1, default=str).encode()))
            _atomic(path, lambda fh: np.savez_compressed(fh, **arrays))  # parallel jobs: never a torn file
        except OSError as exc:
            self._failed = True
            warnings.warn(f"predictions.cache_dir={self.dir.parent}: cannot write the prediction cache "
                          f"({exc.strerror or exc}); going on without it", stacklevel=2)


def _atomic(path: Path, write: Callable) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


class NetworkPredictor:
    """``fn(i, frame) -> frame`` with the network's predictions attached, for
    :meth:`~diffuser_lab.data.frames.LazyFrames.mapped`; builds the network at the first frame
    not in the cache. ``stats`` counts each frame once however often it is visited:
    ``model_calls``, ``cached_frames``, ``label_frames``, ``probability_frames``, ``unmapped_pixels``."""

    def __init__(self, build: Callable[[], Callable], key: str, ident: dict, label: str, *,
                 cache_dir: Optional[str], scene_name: str, pass_depth: bool,
                 mapping: Optional[ClassMapping], taxonomy: Taxonomy, features: Optional[str] = None):
        self._build, self.label, self._model = build, label, None
        self.features = features  # predictions=features: the output's layout (auto, hwd, dhw); None: labels
        self.cache = _DiskCache(cache_dir, key, ident)
        self.scene_name, self.pass_depth = scene_name, pass_depth
        self.mapping, self.taxonomy = mapping, taxonomy
        self.stats = {"model": label, "model_key": key, "model_calls": 0, "cached_frames": 0, "label_frames": 0,
                      "probability_frames": 0, "unmapped_pixels": 0,
                      "cache": None if self.cache.dir is None else str(self.cache.dir)}
        self._seen: set[int] = set()

    def model(self) -> Callable:
        if self._model is None:
            with progress.stage(f"loading {self.label}"):
                self._model = self._build()
        return self._model

    def __call__(self, i: int, f):
        if f.rgb is None:
            raise ValueError(f"frame {f.name}: no colour image for the network ({self.label}); the scene's "
                             f"frames need RGB (e.g. scene.options.color_suffix)")
        rgb = np.ascontiguousarray(f.rgb)
        parts = [str(rgb.shape).encode(), rgb.tobytes()]
        if self.pass_depth:
            depth = np.ascontiguousarray(f.depth, np.float32)
            parts += [b"depth", depth.tobytes()]
        path = self.cache.path(self.scene_name, f.name, _digest(*parts))
        out = self.cache.load(path)
        first = i not in self._seen
        self._seen.add(i)
        what = f"{self.label} on frame {f.name}"
        if out is None:
            model = self.model()
            try:
                raw = model(rgb, depth) if self.pass_depth else model(rgb)
            except Exception as exc:  # noqa: BLE001 - the user's network: name it and the frame
                if isinstance(exc, ValueError) and str(exc).startswith("predictions."):
                    raise
                raise ValueError(f"{what} failed ({type(exc).__name__}: "
                                 f"{str(exc).splitlines()[0] if str(exc) else ''})") from exc
            out = as_output(raw, what) if self.features is None else as_features(raw, what, self.features)
            self.cache.save(path, out)
            self.stats["model_calls"] += 1
        elif first:
            self.stats["cached_frames"] += 1
        if self.features is not None:
            return dataclasses.replace(f, labels=None, probs=None, features=out)
        labels, probs, n_unmapped = translate(out, self.mapping, self.taxonomy, f.shape, what)
        if first:
            self.stats["label_frames" if probs is None else "probability_frames"] += 1
            self.stats["unmapped_pixels"] += int(n_unmapped)
        return dataclasses.replace(f, labels=labels, probs=probs)


def model_predictions(frames: Sequence[Frame], cfg: PredictionsConfig, taxonomy: Taxonomy,
                      scene_name: str = "", features: bool = False) -> LazyFrames:
    """``predictions=model``: frames whose labels or probabilities are the Python callable's
    (lazily, per frame; see the module doc); ``features``: its (h, w, D) / (D, h, w) embeddings
    (``predictions=features predictions.embeddings=model``)."""
    spec = cfg.model if isinstance(cfg.model, dict) else OmegaConf.to_container(cfg.model, resolve=True)
    spec = dict(spec)
    target = check_target(spec)  # a wrong import path stops here, before any frame
    record_model_files(target, spec)
    key, ident = model_key(spec, cfg.pass_depth)
    return _predicted(frames, cfg, taxonomy, scene_name, lambda: build_callable(spec), key, ident,
                      f"model {spec['_target_']}", cfg.pass_depth, features)


def onnx_predictions(frames: Sequence[Frame], cfg: PredictionsConfig, taxonomy: Taxonomy,
                     scene_name: str = "", features: bool = False) -> LazyFrames:
    """``predictions=onnx``: frames whose labels or probabilities are the ONNX network's (lazily,
    per frame; see the module doc); ``features``: its embeddings (``predictions.onnx.output`` is
    then taken as ``features``)."""
    onnx = dataclasses.replace(cfg.onnx, output=OnnxOutput.features) if features else cfg.onnx
    key, ident = onnx_key(onnx)
    return _predicted(frames, cfg, taxonomy, scene_name, lambda: OnnxModel(onnx), key, ident,
                      f"ONNX network {Path(cfg.onnx.path).name}", False, features)


def _predicted(frames: Sequence[Frame], cfg: PredictionsConfig, taxonomy: Taxonomy, scene_name: str,
               build: Callable[[], Callable], key: str, ident: dict, label: str, pass_depth: bool,
               features: bool = False) -> LazyFrames:
    mapping = load_mapping(cfg.mapping, taxonomy) if cfg.mapping and not features else None
    if features:  # a feature map is another cache entry than the same network's labels
        key, ident = _digest(key.encode(), b"features")[:20], {**ident, "features": True}
    pred = NetworkPredictor(build, key, ident, label, cache_dir=cfg.cache_dir, scene_name=scene_name,
                            pass_depth=pass_depth, mapping=mapping, taxonomy=taxonomy,
                            features=cfg.layout if features else None)
    return LazyFrames.mapped(frames, pred, stats=pred.stats, serial=True)  # the network and its cache: one frame at a time
