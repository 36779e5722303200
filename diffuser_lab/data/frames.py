"""Frames, read lazily: the one lazy frame sequence (:class:`LazyFrames`) and the one frame loop
(:class:`FrameLoop`).

:class:`LazyFrames` is a read-only ``Sequence[Frame]`` whose item i is computed when it is read.

Every frame sequence that is not a plain list is one of these: a source's frames read from disk
(``LazyFrames(names, load)``), frames with their predictions or sensor depth attached
(:meth:`LazyFrames.mapped`), a subset of frames (:meth:`LazyFrames.subset`), a benchmark's
repeated or tiled views. Nothing is cached: reading item i twice computes it twice, so a long
sequence is never held in memory; what is computed per frame must depend on the frame alone (seeds
included), not on the order of access nor on its position in a subset: a subset keeps each frame's
index in the sequence it was cut from (``source_index``), and :meth:`LazyFrames.mapped` hands the
per-frame function that index, so a frame's predictions (or sensor depth) are the same whether it
is read in the whole sequence or in a subset of it (a tile's frames, the frames an online run kept).

Two dicts travel with a sequence: ``info``, the loader's statistics (frames found, skipped,
``depth_unit_checked``) and ``stats``, what the per-frame function counts as frames are read
(unmapped pixels, a network's cached frames). Both are empty unless filled.

:class:`FrameLoop` reads such a sequence in order, each frame once, with a progress line: the batch
pipeline (every frame), the online runner (every frame, a bad one skipped or stopping the run) and
the single-frame protocol (target frames, each with the window of frames around it) iterate their
frames through it; only the current window stays in memory.
"""
from __future__ import annotations

import time
import warnings
from typing import Callable, Iterator, Optional, Sequence

from diffuser_lab import progress

from .scene import Frame

__all__ = ["LazyFrames", "FrameLoop", "first_line", "index_of"]


class LazyFrames(Sequence[Frame]):
    """``frames[i]`` is ``load(i)``, computed on access, for ``i`` in ``range(n)``.

    Args:
        n: the number of frames, or the frames' names (kept as ``names``: a source's frames
            are known by name before any is read).
        load: ``i -> Frame`` for ``0 <= i < n``.
        info: the loader's statistics (kept by reference: a loader may add to it).
        stats: what ``load`` counts as frames are read (kept by reference).
    """

    def __init__(self, n: int | Sequence[str], load: Callable[[int], Frame], *, info: Optional[dict] = None,
                 stats: Optional[dict] = None):
        if isinstance(n, int):
            self.names: Optional[list[str]] = None
            self._n = n
        else:
            self.names = list(n)
            self._n = len(self.names)
        self._load = load
        self.info = info if info is not None else {}
        self.stats = stats if stats is not None else {}
        self.fn: Optional[Callable[[int, Frame], Frame]] = None  # mapped(): the per-frame function
        # the frames' indices in the sequence they were cut from (subset()); None = their positions
        self.source_index: Optional[list[int]] = None

    @classmethod
    def mapped(cls, frames: Sequence[Frame], fn: Callable[[int, Frame], Frame], *, stats: Optional[dict] = None,
               info: Optional[dict] = None) -> "LazyFrames":
        """Item i is ``fn(j, frames[i])`` (predictions attached, depth corrupted, ...) where j is the
        frame's index in the whole sequence (``frames.source_index[i]`` for a subset, else i); ``fn`` is kept
        as the sequence's ``fn`` (e.g. a network predictor, with its model once built)."""
        ids = index_of(frames)
        out = cls(len(frames), (lambda i: fn(i, frames[i])) if ids is None else (lambda i: fn(ids[i], frames[i])),
                  info=info, stats=stats)
        out.fn, out.source_index = fn, ids
        return out

    @classmethod
    def subset(cls, frames: Sequence[Frame], keep: Sequence[int], *, info: Optional[dict] = None) -> "LazyFrames":
        """Item i is ``frames[keep[i]]``; its ``source_index`` is that frame's index in the whole sequence."""
        keep = [int(k) for k in keep]
        names = getattr(frames, "names", None)
        out = cls([names[k] for k in keep] if names is not None else len(keep), lambda i: frames[keep[i]],
                  info=info)
        ids = index_of(frames)
        out.source_index = keep if ids is None else [ids[k] for k in keep]
        return out

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):  # a lazy subset with the same names and statistics
            idx = range(self._n)[i]
            names = [self.names[k] for k in idx] if self.names is not None else len(idx)
            out = LazyFrames(names, lambda k: self._load(idx[k]), info=self.info, stats=self.stats)
            # a slice of a whole sequence is a sequence of its own (its frames counted from 0, as before)
            out.source_index = None if self.source_index is None else [self.source_index[k] for k in idx]
            return out
        if not -self._n <= i < self._n:
            raise IndexError(f"frame index {i} out of range for {self._n} frames")
        return self._load(i % self._n)

    def __repr__(self) -> str:
        return f"LazyFrames({self._n} frames)"


def index_of(frames: Sequence[Frame]) -> Optional[list[int]]:
    """The frames' indices in the sequence they were cut from (a :class:`LazyFrames` subset or
    slice), or None when they are that sequence (their positions are their indices)."""
    return getattr(frames, "source_index", None)


def first_line(exc: BaseException) -> str:
    """An error's first line (its type's name when it has no message)."""
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


class FrameLoop:
    """Iterate ``(index, frame)`` over ``frames`` (a lazy sequence) under a progress line ``label``.

    Args:
        targets: the frame indices to visit, in order (default: every frame).
        window: frames kept around each target (:meth:`window_frames`: the ``window`` frames
            centred on it, kept at ``window`` near the ends of the sequence); 1 = the target alone.
        check: called on each target frame; a ValueError or OSError it (or the loading) raises
            makes the frame bad.
        skip_bad: a bad frame is skipped with one warning line (``"<warn_prefix>frame i skipped:
            <reason>"``) and ``on_skip(index, reason)`` is called; False: the error stops the loop.
        note: called with the frame's index before it is yielded; what it returns (if anything)
            is shown beside the progress bar.

    Attributes:
        read_s: seconds spent loading and checking target frames (their predictions included).
        bar: the progress stage (its ``note`` may be called inside the loop).
    """

    def __init__(self, frames: Sequence[Frame], label: str, *, targets: Optional[Sequence[int]] = None,
                 window: int = 1, check: Optional[Callable[[Frame], None]] = None, skip_bad: bool = False,
                 warn_prefix: str = "", on_skip: Optional[Callable[[int, str], None]] = None):
        self.frames, self.label = frames, label
        self.targets = list(range(len(frames))) if targets is None else list(targets)
        self.window = max(1, int(window))
        self.check, self.skip_bad, self.warn_prefix, self.on_skip = check, skip_bad, warn_prefix, on_skip
        self.read_s = 0.0
        self.bar = progress.Stage()
        self._cache: dict[int, Frame] = {}

    def __len__(self) -> int:
        return len(self.targets)

    def window_of(self, i: int) -> list[int]:
        """The ``window`` frame indices around frame i (kept at ``window`` near the ends)."""
        n = len(self.frames)
        w = min(self.window, n)
        start = min(max(i - w // 2, 0), n - w)
        return list(range(start, start + w))

    def _frame(self, j: int) -> Frame:
        if j not in self._cache:
            self._cache[j] = self.frames[j]
        return self._cache[j]

    def window_frames(self, i: int) -> list[Frame]:
        """The frames of :meth:`window_of` (read once, kept while the window holds them)."""
        return [self._frame(j) for j in self.window_of(i)]

    def __iter__(self) -> Iterator[tuple[int, Frame]]:
        unit = "frame"
        with progress.stage(self.label, total=len(self.targets), unit=unit) as bar:
            self.bar = bar
            for i in self.targets:
                t0 = time.perf_counter()
                keep = set(self.window_of(i)) if self.window > 1 else {i}
                for j in [j for j in self._cache if j not in keep]:  # only the current window in memory
                    del self._cache[j]
                try:
                    f = self._frame(i)
                    if self.check is not None:
                        self.check(f)
                except (ValueError, OSError) as exc:
                    if not self.skip_bad:
                        raise
                    msg = first_line(exc)
                    warnings.warn(f"{self.warn_prefix}frame {i} skipped: {msg}", stacklevel=2)
                    self._cache.pop(i, None)
                    if self.on_skip is not None:
                        self.on_skip(i, msg)
                    bar.update()
                    continue
                self.read_s += time.perf_counter() - t0
                yield i, f
                bar.update()
            self._cache.clear()
