"""The one frame loop: a scene's frames read lazily, each once, in sequence order, with a progress line.

The batch pipeline (every frame), the online runner (every frame, a bad one skipped or stopping
the run) and the single-frame protocol (target frames, each with the window of frames around it)
read their frames through :class:`FrameLoop`; a frame is loaded (and its 2D predictions made)
only when the loop reaches it, and only the current window stays in memory.
"""
from __future__ import annotations

import time
import warnings
from typing import Callable, Iterator, Optional, Sequence

from diffuser_lab import progress

from .scene import Frame


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
