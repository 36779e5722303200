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

**Read-ahead.** A loop over a :class:`LazyFrames` decodes the frames it will need next on a pool of
threads (:class:`concurrent.futures.ThreadPoolExecutor`; Pillow's decoders, zlib and numpy release the
GIL), at most ``read_ahead`` frames ahead of the one in use, and hands them out in order: the frames and
everything computed from them are those of one thread (each frame is computed from its index alone, the
rule above); an error is raised when the loop reaches its frame, as it would be in one thread. The depth
is the run's ``scene.read_ahead`` (:func:`read_ahead`; null: twice the cores this process may use;
0 = one thread). A per-frame function that keeps state (a network, its cache) is made ``serial``
(:meth:`LazyFrames.mapped`): one thread at a time runs it, the decoding around it still overlaps.

**Parts a loop does not read.** :meth:`LazyFrames.without` gives the frames without some of their
parts (``rgb``): a source that declares the part optional does not read it (a ScanNet export's
1296x968 colour JPEG is two thirds of its decoding); the batch pipeline asks for colour only when
its predictions or records read it.

**Poses up front.** A source that knows its poses before reading its images gives them
(``poses=``, world-to-camera); they follow the frames through :meth:`~LazyFrames.mapped`,
:meth:`~LazyFrames.subset` and slices, so :func:`keyframes` picks frames without decoding any.

**A capture followed as it is written** (``scene.options.follow``, docs/online.md): the source hands a
:class:`Follow` (``follow=``) whose ``poll`` adds each frame once its files (or messages) are complete;
the sequence's length is the frames complete so far, and grows (through :meth:`~LazyFrames.mapped` and
:meth:`~LazyFrames.without`; a subset or a slice is fixed). :class:`FrameLoop` over such a sequence waits
for its frames and picks them by the follow policy (:meth:`Follow.schedule`) until the capture is closed
or no frame came for ``follow_timeout`` seconds; after that the sequence is a fixed one.
"""
from __future__ import annotations

import collections
import contextlib
import dataclasses
import os
import threading
import time
import warnings
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, Iterable, Iterator, Optional, Sequence

import numpy as np

from diffuser_lab import progress

from .scene import Frame

__all__ = ["LazyFrames", "FrameLoop", "Follow", "KeyframeRule", "first_line", "index_of", "poses_of", "follow_of",
           "without", "keyframes", "read_ahead", "cores", "OPTIONAL_PARTS", "FOLLOW_POLICIES"]

OPTIONAL_PARTS = ("rgb",)
"""The frame parts a loop may do without (:meth:`LazyFrames.without`)."""


def cores() -> int:
    """The CPU cores this process may run on (its affinity mask; ``os.cpu_count()`` where there is none)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


_READ_AHEAD: list[Optional[int]] = [None]  # the run's scene.read_ahead (None: from the cores)


@contextlib.contextmanager
def read_ahead(depth: Optional[int]) -> Iterator[None]:
    """The frame loops started inside read ``depth`` frames ahead (the run's ``scene.read_ahead``;
    None: :func:`default_read_ahead`; 0: one thread)."""
    old = _READ_AHEAD[0]
    _READ_AHEAD[0] = depth
    try:
        yield
    finally:
        _READ_AHEAD[0] = old


def default_read_ahead() -> int:
    """Frames read ahead when the run does not say: twice the cores (a frame waiting for each core
    while each core decodes one), 0 on one core."""
    n = cores()
    return 2 * n if n > 1 else 0


class LazyFrames(Sequence[Frame]):
    """``frames[i]`` is ``load(i)``, computed on access, for ``i`` in ``range(n)``.

    Args:
        n: the number of frames, or the frames' names (kept as ``names``: a source's frames
            are known by name before any is read).
        load: ``i -> Frame`` for ``0 <= i < n``; with ``parts``, ``(i, skip) -> Frame`` where ``skip``
            (a frozenset of those parts) are left out (None) and not read.
        info: the loader's statistics (kept by reference: a loader may add to it).
        stats: what ``load`` counts as frames are read (kept by reference).
        poses: the frames' (4, 4) world-to-camera poses when known without reading them (kept as
            ``poses``; :func:`keyframes`), else None.
        parts: the optional parts (:data:`OPTIONAL_PARTS`) ``load`` can leave out.
        follow: a capture followed as it is written (:class:`Follow`): the sequence is its frames complete
            so far (``n`` and ``poses`` are not used: its ``names`` and ``poses`` are), kept as ``follow``.

    Item i may be read from several threads at once (:class:`FrameLoop`'s read-ahead): ``load``
    must be safe to call so (it reads files; state it keeps goes behind a lock).
    """

    def __init__(self, n: int | Sequence[str], load: Callable[..., Frame], *, info: Optional[dict] = None,
                 stats: Optional[dict] = None, poses: Optional[Sequence[np.ndarray]] = None,
                 parts: Iterable[str] = (), follow: Optional["Follow"] = None):
        if isinstance(n, int):
            self.names: Optional[list[str]] = None
            self._size = n
        else:
            self.names = list(n)
            self._size = len(self.names)
        self._load = load
        self.follow = follow
        self.info = info if info is not None else {}
        self.stats = stats if stats is not None else {}
        self.fn: Optional[Callable[[int, Frame], Frame]] = None  # mapped(): the per-frame function
        # the frames' indices in the sequence they were cut from (subset()); None = their positions
        self.source_index: Optional[list[int]] = None
        self.poses: Optional[list[np.ndarray]] = None if poses is None else list(poses)
        if follow is not None:  # the frames complete so far: the follow's own lists, grown as it polls
            self.names, self.poses = follow.names, follow.poses
        elif self.poses is not None and len(self.poses) != self._n:
            raise ValueError(f"{len(self.poses)} poses for {self._n} frames")
        self._parts = frozenset(parts)  # what load can leave out
        self._skip: frozenset = frozenset()  # what this sequence's frames leave out (without())
        self._derive: Optional[Callable[[frozenset], "LazyFrames"]] = None  # without() of a derived sequence

    @property
    def _n(self) -> int:
        return len(self.follow.names) if self.follow is not None else self._size

    @classmethod
    def mapped(cls, frames: Sequence[Frame], fn: Callable[[int, Frame], Frame], *, stats: Optional[dict] = None,
               info: Optional[dict] = None, serial: bool = False) -> "LazyFrames":
        """Item i is ``fn(j, frames[i])`` (predictions attached, depth corrupted, ...) where j is the
        frame's index in the whole sequence (``frames.source_index[i]`` for a subset, else i); ``fn`` is kept
        as the sequence's ``fn`` (e.g. a network predictor, with its model once built). ``serial``: ``fn``
        keeps state (a network, its cache): one thread at a time runs it (``frames[i]`` is still read
        beside it by the others)."""
        if serial and not getattr(fn, "_serial", False):
            fn = _serialised(fn)
        ids = index_of(frames)
        out = cls(len(frames), (lambda i: fn(i, frames[i])) if ids is None else (lambda i: fn(ids[i], frames[i])),
                  info=info, stats=stats, poses=poses_of(frames), follow=follow_of(frames))
        out.fn, out.source_index = fn, ids
        out._derive = lambda skip: cls.mapped(without(frames, *skip), fn, stats=out.stats, info=out.info)
        return out

    @classmethod
    def subset(cls, frames: Sequence[Frame], keep: Sequence[int], *, info: Optional[dict] = None) -> "LazyFrames":
        """Item i is ``frames[keep[i]]``; its ``source_index`` is that frame's index in the whole sequence."""
        keep = [int(k) for k in keep]
        names = getattr(frames, "names", None)
        poses = poses_of(frames)
        out = cls([names[k] for k in keep] if names is not None else len(keep), lambda i: frames[keep[i]],
                  info=info, poses=None if poses is None else [poses[k] for k in keep])
        ids = index_of(frames)
        out.source_index = keep if ids is None else [ids[k] for k in keep]
        out._derive = lambda skip: cls.subset(without(frames, *skip), keep, info=out.info)
        return out

    def without(self, *parts: str) -> "LazyFrames":
        """These frames without ``parts`` (of :data:`OPTIONAL_PARTS`: None in every frame), not read
        where the source can leave them out; the same names, poses, indices and statistics."""
        bad = [p for p in parts if p not in OPTIONAL_PARTS]
        if bad:
            raise ValueError(f"frame parts {bad}: expected some of {', '.join(OPTIONAL_PARTS)}")
        skip = frozenset(parts) | self._skip
        if skip == self._skip:
            return self
        if self._derive is not None:
            return self._derive(skip)
        out = LazyFrames(self.names if self.names is not None else self._n, self._load, info=self.info,
                         stats=self.stats, poses=self.poses, parts=self._parts, follow=self.follow)
        out.fn, out.source_index, out._skip = self.fn, self.source_index, skip
        return out

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):  # a lazy subset with the same names and statistics
            idx = range(self._n)[i]
            names = [self.names[k] for k in idx] if self.names is not None else len(idx)
            out = LazyFrames(names, lambda k: self[idx[k]], info=self.info, stats=self.stats,
                             poses=None if self.poses is None else [self.poses[k] for k in idx])
            # a slice of a whole sequence is a sequence of its own (its frames counted from 0, as before)
            out.source_index = None if self.source_index is None else [self.source_index[k] for k in idx]
            out._derive = lambda skip: self.without(*skip)[i]
            return out
        if not -self._n <= i < self._n:
            raise IndexError(f"frame index {i} out of range for {self._n} frames")
        i %= self._n
        if not self._skip:
            return self._load(i, skip=frozenset()) if self._parts else self._load(i)
        f = self._load(i, skip=self._skip & self._parts) if self._parts else self._load(i)
        left = [p for p in self._skip if getattr(f, p) is not None]  # parts the source read anyway
        return dataclasses.replace(f, **{p: None for p in left}) if left else f

    def __repr__(self) -> str:
        return f"LazyFrames({self._n} frames)"


def index_of(frames: Sequence[Frame]) -> Optional[list[int]]:
    """The frames' indices in the sequence they were cut from (a :class:`LazyFrames` subset or
    slice), or None when they are that sequence (their positions are their indices)."""
    return getattr(frames, "source_index", None)


def poses_of(frames: Sequence[Frame]) -> Optional[list[np.ndarray]]:
    """The frames' (4, 4) world-to-camera poses without reading their images: a list's own, a
    :class:`LazyFrames`' ``poses`` (None when its source does not know them up front)."""
    if isinstance(frames, LazyFrames):
        return frames.poses
    if isinstance(frames, (list, tuple)):
        return [f.T_cw for f in frames]
    return None


def follow_of(frames: Sequence[Frame]) -> Optional["Follow"]:
    """The :class:`Follow` of a sequence that grows as a recorder writes its capture, else None."""
    return getattr(frames, "follow", None)


def without(frames: Sequence[Frame], *parts: str) -> Sequence[Frame]:
    """``frames`` without ``parts`` (:meth:`LazyFrames.without`); a list is returned as it is (its
    frames are in memory already)."""
    return frames.without(*parts) if isinstance(frames, LazyFrames) and parts else frames


def _serialised(fn: Callable[[int, Frame], Frame]) -> Callable[[int, Frame], Frame]:
    """``fn`` behind a lock (one thread at a time), keeping its attributes (a predictor's ``stats``)."""
    lock = threading.Lock()

    class Serial:
        _serial = True

        def __call__(self, i: int, f: Frame) -> Frame:
            with lock:
                return fn(i, f)

        def __getattr__(self, name):
            return getattr(fn, name)

    return Serial()


def keyframes(frames: Sequence[Frame], translation: Optional[float], rotation_deg: Optional[float]) -> list[int]:
    """The indices of the frames a keyframe rule keeps: the first frame, then each frame whose camera
    moved at least ``translation`` metres or turned at least ``rotation_deg`` degrees since the last
    frame kept (a None threshold is not used; both None: every frame). The poses come from
    :func:`poses_of` when the source knows them (nothing is decoded), else from reading the frames
    (through :class:`FrameLoop`)."""
    n = len(frames)
    if translation is None and rotation_deg is None:
        return list(range(n))
    poses = poses_of(frames)
    if poses is None:
        poses = [f.T_cw for _, f in FrameLoop(frames, "keyframes: reading the poses")]
    rule = KeyframeRule(translation, rotation_deg)
    return [i for i, T in enumerate(np.asarray(poses, np.float64).reshape(n, 4, 4)) if rule.add(T)]  # loop over frames


class KeyframeRule:
    """The keyframe rule (:func:`keyframes`) one frame at a time, so a capture followed as it is written
    marks its keyframes as they come: :meth:`add` says whether a frame is one. A threshold that is None
    is not used; both None: the rule is off (:attr:`on`) and every frame is one. A pose that is not
    finite is none (and does not move the reference)."""

    def __init__(self, translation: Optional[float], rotation_deg: Optional[float]):
        self.translation, self.rotation_deg = translation, rotation_deg
        self._cos_min = np.cos(np.deg2rad(rotation_deg)) if rotation_deg is not None else None
        self._last: Optional[tuple[np.ndarray, np.ndarray]] = None  # the last keyframe's R and camera centre

    @property
    def on(self) -> bool:
        return self.translation is not None or self.rotation_deg is not None

    def add(self, T_cw: np.ndarray) -> bool:
        """The next frame's (4, 4) world-to-camera pose -> whether it is a keyframe: the first one, then
        one whose camera moved ``translation`` metres or turned ``rotation_deg`` degrees since the last."""
        T = np.asarray(T_cw, np.float64)
        if not np.isfinite(T).all():
            return False
        R, t = T[:3, :3], T[:3, 3]
        centre = -np.einsum("ji,j->i", R, t)  # the camera centre: -R^T t
        moved = self._last is None or not self.on
        if not moved:
            R0, c0 = self._last
            moved = self.translation is not None and np.linalg.norm(centre - c0) >= self.translation - 1e-9
            if not moved and self._cos_min is not None:  # the angle of R R0^T: trace = 1 + 2 cos(angle)
                moved = (np.einsum("ij,ij->", R, R0) - 1.0) / 2.0 <= self._cos_min + 1e-9
        if moved:
            self._last = (R, centre)
        return moved


FOLLOW_POLICIES = ("all", "newest")
"""How a followed capture's frames are taken when they come faster than the map takes them
(``scene.options.follow_policy``; :meth:`Follow.schedule`)."""


class Follow:
    """A capture followed as a recorder writes it (``scene.options.follow``): its frames complete so far,
    grown by the source's ``poll``; a :class:`LazyFrames` made with ``follow=`` is these frames.

    Args:
        poll: ``() -> bool``, the source's: calls :meth:`add` for each frame that became complete (in
            sequence order, each once) and says whether the capture is closed (nothing more will come).
        what: the capture (error lines).
        timeout: seconds without a new complete frame (from the first :meth:`wait` on) after which the
            capture counts as finished.
        policy: one of :data:`FOLLOW_POLICIES` (:meth:`schedule`).
        step, limit: every ``step``-th complete frame is kept, at most ``limit`` (None: no limit); the
            capture is finished at the limit (``frame_step``, ``max_frames``).

    Attributes:
        poll: the source's ``poll``.
        names, poses, items: per frame kept, its name, (4, 4) world-to-camera pose (NaN where the source
            could not read it: no keyframe) and what the source reads it from.
        rule: the run's :class:`KeyframeRule` (the scene's keyframe keys; None: no keyframes).
        ended: None while followed, then why it ended: ``closed``, ``idle`` or ``max_frames``.
        waiting: what the source still waits for before its first frame (said when none came).
        info: summary.json's ``follow``: the policy and timeout, frames found complete and kept, frames
            used, skipped as ``behind`` or ``bad``, keyframes taken from a backlog, why it ended, seconds waited.
    """

    POLL_S = 0.01  # between two polls while waiting for a frame

    def __init__(self, poll: Callable[[], bool], what: str, *, timeout: float, policy: str = "newest", step: int = 1,
                 limit: Optional[int] = None):
        if policy not in FOLLOW_POLICIES:
            raise ValueError(f"follow policy {policy!r}: expected one of {', '.join(FOLLOW_POLICIES)}")
        self.poll, self.what, self.timeout, self.policy = poll, what, float(timeout), policy
        self.step, self.limit = max(1, int(step)), limit
        self.names: list[str] = []
        self.poses: list[np.ndarray] = []
        self.items: list = []
        self.rule: Optional[KeyframeRule] = None
        self.ended: Optional[str] = None
        self.waiting = ""
        self._keyframe: list[bool] = []
        self._last_new: Optional[float] = None  # when the last new frame was found (the first wait starts the clock)
        self.info = {"policy": policy, "timeout_s": self.timeout, "frames_found": 0, "frames": 0, "used": 0,
                     "skipped_behind": 0, "skipped_bad": 0, "keyframes_from_backlog": 0, "ended": None,
                     "wait_s": 0.0}

    def add(self, name: str, T_cw: np.ndarray, item) -> bool:
        """A frame became complete: kept (True) unless ``step`` or ``limit`` leave it out."""
        found = self.info["frames_found"]
        self.info["frames_found"] = found + 1
        self._last_new = time.monotonic()
        if found % self.step or (self.limit is not None and len(self.names) >= self.limit):
            return False
        self.names.append(str(name))
        self.poses.append(np.asarray(T_cw, np.float64))
        self.items.append(item)
        self.info["frames"] = len(self.names)
        return True

    def count(self, what: str) -> None:
        """One more frame ``used`` or ``skipped_bad`` (the frame loop's)."""
        self.info[what] += 1

    def is_keyframe(self, j: int) -> bool:
        """Whether frame ``j`` is a keyframe of :attr:`rule` (none without a rule, or with the rule off)."""
        if self.rule is None or not self.rule.on:
            return False
        while len(self._keyframe) <= j:  # loop over the frames not yet ruled on (one each)
            self._keyframe.append(self.rule.add(self.poses[len(self._keyframe)]))
        return self._keyframe[j]

    def wait(self, n: int) -> int:
        """Poll until more than ``n`` frames are complete or the capture ended (closed, idle for
        ``timeout`` seconds, at ``limit``); the number complete. One ValueError when it ended with none."""
        t0 = time.monotonic()
        if self._last_new is None:
            self._last_new = t0
        while self.ended is None and len(self.names) <= n:  # loop over polls
            closed = self.poll()
            if len(self.names) > n:
                break
            if self.limit is not None and len(self.names) >= self.limit:
                self._end("max_frames")
            elif closed:
                self._end("closed")
            elif time.monotonic() - self._last_new >= self.timeout:
                self._end("idle")
            else:
                time.sleep(self.POLL_S)
        self.info["wait_s"] = round(self.info["wait_s"] + time.monotonic() - t0, 3)
        return len(self.names)

    def _end(self, why: str) -> None:
        self.ended = self.info["ended"] = why
        if not self.names:
            raise ValueError(f"{self.what}: " + ("closed without a complete frame" if why == "closed" else
                             f"no complete frame within scene.options.follow_timeout={self.timeout:g} s") +
                             (f" (waiting for {self.waiting})" if self.waiting else ""))

    def schedule(self, behind: Callable[[int], None]) -> Iterator[int]:
        """The frame indices to take, each as it becomes complete (waiting while none is): policy ``all``
        every frame in order; ``newest``: when more than one frame waits, the newest first, then the waiting
        keyframes (:meth:`is_keyframe`, oldest first); the other waiting frames are skipped (``behind(j)``)."""
        i, kept = 0, collections.deque()
        while True:  # loop over the frames taken
            if kept:
                yield kept.popleft()
                continue
            n = self.wait(i)
            if n <= i:
                return
            if self.policy == "newest" and n - i > 1:
                for j in range(i, n - 1):  # loop over the backlog: keyframes kept, the rest skipped
                    if self.is_keyframe(j):
                        kept.append(j)
                        self.info["keyframes_from_backlog"] += 1
                    else:
                        self.info["skipped_behind"] += 1
                        behind(j)
                yield n - 1
                i = n
            else:
                yield i
                i += 1


def first_line(exc: BaseException) -> str:
    """An error's first line (its type's name when it has no message)."""
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


class FrameLoop:
    """Iterate ``(index, frame)`` over ``frames`` (a lazy sequence) under a progress line ``label``,
    the frames it will need next read ahead on a pool of threads (module doc).

    Args:
        targets: the frame indices to visit, in order (default: every frame).
        window: frames kept around each target (:meth:`window_frames`: the ``window`` frames
            centred on it, kept at ``window`` near the ends of the sequence); 1 = the target alone.
        check: called on each target frame; a ValueError or OSError it (or the loading) raises
            makes the frame bad.
        skip_bad: a bad frame is skipped with one warning line (``"<warn_prefix>frame i skipped:
            <reason>"``) and ``on_skip(index, reason)`` is called; False: the error stops the loop.
        read_ahead: frames read ahead of the one in use (None: the run's, :func:`read_ahead`;
            0: each frame read when it is needed, in this thread). A list of frames is never read ahead.

    A capture still followed (:class:`Follow`: ``frames.follow``, not ended; every frame, window 1) is
    iterated as its frames become complete, in the order :meth:`Follow.schedule` takes them, each read when
    it is taken; a frame the policy skips is handed to ``on_skip(index, "behind")`` without a warning.

    Attributes:
        read_s: seconds this thread spent loading (or waiting for) and checking target frames
            (their predictions included): with read-ahead, only what the other threads did not hide.
        bar: the progress stage (its ``note`` may be called inside the loop).
    """

    def __init__(self, frames: Sequence[Frame], label: str, *, targets: Optional[Sequence[int]] = None,
                 window: int = 1, check: Optional[Callable[[Frame], None]] = None, skip_bad: bool = False,
                 warn_prefix: str = "", on_skip: Optional[Callable[[int, str], None]] = None,
                 read_ahead: Optional[int] = None):
        self.frames, self.label = frames, label
        self._every = targets is None
        self.targets = list(range(len(frames))) if targets is None else list(targets)
        self.window = max(1, int(window))
        self.check, self.skip_bad, self.warn_prefix, self.on_skip = check, skip_bad, warn_prefix, on_skip
        depth = read_ahead if read_ahead is not None else _READ_AHEAD[0]
        self.read_ahead = 0 if not isinstance(frames, LazyFrames) else (
            default_read_ahead() if depth is None else max(0, int(depth)))
        self.read_s = 0.0
        self.bar = progress.Stage()
        self._cache: dict[int, Frame] = {}
        self._pending: dict[int, tuple[int, Future]] = {}  # frame index -> (its place in the schedule, its read)
        self._seq = 0
        self._keep: set[int] = set()
        self._schedule: Optional[Iterator[int]] = None
        self._pool: Optional[ThreadPoolExecutor] = None

    def __len__(self) -> int:
        return len(self.targets)

    def window_of(self, i: int) -> list[int]:
        """The ``window`` frame indices around frame i (kept at ``window`` near the ends)."""
        n = len(self.frames)
        w = min(self.window, n)
        start = min(max(i - w // 2, 0), n - w)
        return list(range(start, start + w))

    def _reads(self) -> Iterator[int]:
        """The frame indices in the order the loop will first need them: each target, then the rest of
        its window (what a frame kept from the last window does not need again)."""
        held: set[int] = set()
        for i in self.targets:  # loop over targets: the cache the loop keeps, replayed
            need = [i] + [j for j in self.window_of(i) if j != i] if self.window > 1 else [i]
            held &= set(need)
            for j in need:
                if j not in held:
                    held.add(j)
                    yield j

    def _fill(self) -> None:
        """Schedule reads until ``read_ahead`` are pending."""
        while self._schedule is not None and len(self._pending) < self.read_ahead:
            j = next(self._schedule, None)
            if j is None:
                self._schedule = None
                return
            if j not in self._pending:
                self._seq += 1
                self._pending[j] = (self._seq, self._pool.submit(self.frames.__getitem__, j))

    def _frame(self, j: int) -> Frame:
        if j in self._cache:
            return self._cache[j]
        got = self._pending.pop(j, None)
        if got is None:
            f = self.frames[j]
        else:
            # reads scheduled before this one for frames the loop no longer holds: the caller went on
            # without them (a target it left without reading its window); dropped, read again if asked
            for k in [k for k, (seq, _) in self._pending.items() if seq < got[0] and k not in self._keep]:
                self._pending.pop(k)[1].cancel()
            f = got[1].result()
        self._cache[j] = f
        self._fill()
        return f

    def window_frames(self, i: int) -> list[Frame]:
        """The frames of :meth:`window_of` (read once, kept while the window holds them)."""
        return [self._frame(j) for j in self.window_of(i)]

    def _behind(self, j: int) -> None:
        if self.on_skip is not None:
            self.on_skip(j, "behind")
        self.bar.update()

    def __iter__(self) -> Iterator[tuple[int, Frame]]:
        unit = "frame"
        follow = follow_of(self.frames)
        live = follow if follow is not None and follow.ended is None and self._every and self.window == 1 else None
        threads = min(self.read_ahead, cores())
        if live is None and self.read_ahead > 0 and threads > 0 and len(self.targets) > 1:
            self._pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="frames")
            self._schedule = self._reads()
        try:
            with progress.stage(self.label, total=None if live else len(self.targets), unit=unit) as bar:
                self.bar = bar
                for i in (live.schedule(self._behind) if live else self.targets):
                    t0 = time.perf_counter()
                    self._keep = set(self.window_of(i)) if self.window > 1 else {i}
                    for j in [j for j in self._cache if j not in self._keep]:  # only the current window in memory
                        del self._cache[j]
                    self._fill()
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
                        if live:
                            live.count("skipped_bad")
                        if self.on_skip is not None:
                            self.on_skip(i, msg)
                        bar.update()
                        continue
                    self.read_s += time.perf_counter() - t0
                    if live:
                        live.count("used")
                    yield i, f
                    bar.update()
        finally:
            self._cache.clear()
            if self._pool is not None:
                for _, fut in self._pending.values():
                    fut.cancel()
                self._pending.clear()
                self._schedule = None
                self._pool.shutdown(wait=True, cancel_futures=True)
                self._pool = None
