"""The one lazy frame sequence: :class:`LazyFrames`, a read-only ``Sequence[Frame]`` whose item i
is computed when it is read.

Every frame sequence that is not a plain list is one of these: a source's frames read from disk
(``LazyFrames(names, load)``), frames with their predictions or sensor depth attached
(:meth:`LazyFrames.mapped`), a subset of frames (:meth:`LazyFrames.subset`), a benchmark's
repeated or tiled views. Nothing is cached: reading item i twice computes it twice, so a long
sequence is never held in memory; what is computed per frame must depend on i alone (seeds
included), not on the order of access.

Two dicts travel with a sequence: ``info``, the loader's statistics (frames found, skipped,
``depth_unit_checked``) and ``stats``, what the per-frame function counts as frames are read
(unmapped pixels, a network's cached frames). Both are empty unless filled.
"""
from __future__ import annotations

from typing import Callable, Optional, Sequence

from .scene import Frame

__all__ = ["LazyFrames"]


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

    @classmethod
    def mapped(cls, frames: Sequence[Frame], fn: Callable[[int, Frame], Frame], *, stats: Optional[dict] = None,
               info: Optional[dict] = None) -> "LazyFrames":
        """Item i is ``fn(i, frames[i])`` (predictions attached, depth corrupted, ...); ``fn`` is kept
        as the sequence's ``fn`` (e.g. a network predictor, with its model once built)."""
        out = cls(len(frames), lambda i: fn(i, frames[i]), info=info, stats=stats)
        out.fn = fn
        return out

    @classmethod
    def subset(cls, frames: Sequence[Frame], keep: Sequence[int], *, info: Optional[dict] = None) -> "LazyFrames":
        """Item i is ``frames[keep[i]]``."""
        keep = list(keep)
        names = getattr(frames, "names", None)
        return cls([names[k] for k in keep] if names is not None else len(keep), lambda i: frames[keep[i]],
                   info=info)

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):  # a lazy subset with the same names and statistics
            idx = range(self._n)[i]
            names = [self.names[k] for k in idx] if self.names is not None else len(idx)
            return LazyFrames(names, lambda k: self._load(idx[k]), info=self.info, stats=self.stats)
        if not -self._n <= i < self._n:
            raise IndexError(f"frame index {i} out of range for {self._n} frames")
        return self._load(i % self._n)

    def __repr__(self) -> str:
        return f"LazyFrames({self._n} frames)"
