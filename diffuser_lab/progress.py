"""Progress of a run on the terminal: which stage it is in and how far that stage got.

What it shows (on stderr, through tqdm): one line per stage that takes longer than
:data:`DELAY` seconds. Stages with a known length show a bar: the scene's camera views and
their rendering, the frames' 2D predictions + evidence, the diffusion iterations (updated every
:func:`~diffuser_lab.method.diffusion.progress_chunk` iterations), the single-frame protocol's target
frames::

    frames: simulated 2D predictions + evidence:  40%|████      | 12/30 [00:02<00:03, 5.9frame/s]
    diffusion (jacobi, numba, 3,133,968 points):  31%|███       | 62/200 [00:06<00:13, residual 2.1e-03]

Stages done in one call (loading the scene, sampling its surface, reading a mesh, the voxel
grid, the kNN graph, labelling the original points, writing records) show their elapsed time,
refreshed twice a second; a first run, whose numba kernels are not cached yet, says so::

    kNN graph (k=24, 3,133,968 points) [compiling kernels, first run only] [00:07]

A stage that ends within :data:`DELAY` seconds prints nothing. One that lasted longer leaves
one finished line (``frames: simulated 2D predictions + evidence: 240/240 frame [00:03]``) when
it is a top-level stage, and is erased when it ran inside another one (the views rendered while
loading the scene, the graph and diffusion of each target frame of the single-frame protocol);
a stage that fails is erased, so the error message starts its own line. Warnings and console
log records printed while a bar is shown are written above it. The run's result table (stdout)
comes after every bar is closed, so it is never mixed with them.

When: only when stderr is a terminal, and the run is neither one job of a Hydra multirun (its
jobs print a line each) nor timed by ``diffuser-lab-bench`` (:func:`quiet`); so never in log
files, pipes, CI or under pytest. ``DIFFUSER_LAB_PROGRESS=0`` turns it off;
``DIFFUSER_LAB_PROGRESS=1`` forces it on whatever stderr is, with no delay (for tests and
debugging). Disabled, a stage costs an environment look-up and an ``isatty()``, each update a
method call, and no thread is started; nothing a run computes depends on whether progress is
shown (results are bit-identical).

Use::

    from . import progress

    with progress.stage("rendering views", total=len(poses), unit="view") as p:
        for T in poses:
            ...
            p.update()          # or p.set(i + 1); p.note("residual 1e-3") sets the text after it
"""
from __future__ import annotations

import contextlib
import logging
import os
import sys
import threading
import warnings
from typing import Iterator, Optional

__all__ = ["stage", "enabled", "quiet", "Stage", "DELAY", "COMPILING", "say"]

DELAY = 1.0
"""Seconds a stage runs before its line appears (0 when forced on with DIFFUSER_LAB_PROGRESS=1)."""
TICK = 0.5
"""Seconds between refreshes of a shown line while no update comes (elapsed time of one-call stages)."""
COMPILING = " [compiling kernels, first run only]"
"""Appended to a stage's name when its compiled kernels are not in numba's cache yet."""
ENV = "DIFFUSER_LAB_PROGRESS"

_RUNNING_FMT = {
    True: "{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}, {rate_fmt}{postfix}]",
    False: "{desc} [{elapsed}{postfix}]",
}
_DONE_FMT = {True: "{desc}: {n_fmt}/{total_fmt} {unit} [{elapsed}{postfix}]", False: "{desc} [{elapsed}{postfix}]"}

_active: list = []  # the shown-or-pending tqdm bars of the open stages, outermost first
_quiet = 0  # open quiet() blocks
_patched: dict = {}  # what the outermost stage replaced (warnings.showwarning, handler emits)


def _mode() -> str:
    v = os.environ.get(ENV, "").strip().lower()
    if v in ("0", "false", "no", "off"):
        return "off"
    if v in ("1", "true", "yes", "on", "force"):
        return "on"
    return "auto"


def _in_multirun() -> bool:
    if "hydra" not in sys.modules:  # never import Hydra just to ask
        return False
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    except Exception:  # noqa: BLE001 - no Hydra job: not a multirun
        return False


def enabled() -> bool:
    """Whether stages are shown now (see the module doc): forced, or stderr is a terminal, this
    is not a Hydra multirun job and no :func:`quiet` block is open."""
    mode = _mode()
    if mode != "auto":
        return mode == "on"
    if _quiet:
        return False
    try:
        tty = sys.stderr is not None and sys.stderr.isatty()
    except (AttributeError, ValueError):  # replaced or closed stream
        tty = False
    return tty and not _in_multirun()


@contextlib.contextmanager
def quiet() -> Iterator[None]:
    """No stages shown inside (unless forced on): for code that times what it runs
    (``diffuser-lab-bench``), where the refreshes would be part of the measurement."""
    global _quiet
    _quiet += 1
    try:
        yield
    finally:
        _quiet -= 1


class Stage:
    """What :func:`stage` yields. All methods do nothing when progress is off."""

    __slots__ = ("_bar",)

    def __init__(self, bar=None):
        self._bar = bar

    @property
    def enabled(self) -> bool:
        """Whether this stage is shown (callers may do extra bookkeeping only then)."""
        return self._bar is not None

    def update(self, n: int = 1) -> None:
        """Advance by ``n`` (frames, iterations, ...)."""
        if self._bar is not None:
            self._bar.update(n)

    def set(self, n: int) -> None:
        """Set the count to ``n``."""
        bar = self._bar
        if bar is not None and n != bar.n:
            bar.update(n - bar.n)

    def note(self, text: str) -> None:
        """Short text after the counts (e.g. the residual); shown with the next update."""
        if self._bar is not None:
            self._bar.set_postfix_str(text, refresh=False)


_OFF = Stage()


def _shown(bar) -> bool:
    """Whether ``bar`` is on the screen: drawn by an update (tqdm's clock) or by :func:`_tick`."""
    return getattr(bar, "_ticked", False) or getattr(bar, "last_print_t", 0.0) >= bar.start_t + bar.delay


def _above_bars(write) -> None:
    """Run ``write()`` (printing a line) with the shown bars cleared, then redraw them."""
    shown = [b for b in _active if _shown(b)]
    if not shown:
        write()
        return
    with shown[0].get_lock():
        for b in shown:
            b.clear(nolock=True)
        try:
            write()
        finally:
            for b in shown:
                b.refresh(nolock=True)


def _patch_output() -> None:
    """While stages are open: warnings and console log records are printed above the bars."""
    show = warnings.showwarning

    def showwarning(*args, **kwargs):
        _above_bars(lambda: show(*args, **kwargs))

    warnings.showwarning = showwarning
    _patched["warnings"] = (show, showwarning)
    emits = []
    for logger in {logging.getLogger(), logging.getLogger("diffuser_lab")}:
        for h in logger.handlers:
            if type(h) is logging.StreamHandler and getattr(h, "stream", None) in (sys.stdout, sys.stderr):
                orig = h.emit

                def emit(record, _orig=orig):
                    _above_bars(lambda: _orig(record))

                h.emit = emit
                emits.append(h)
    _patched["emits"] = emits


def _unpatch_output() -> None:
    show, ours = _patched.pop("warnings", (None, None))
    if ours is not None and warnings.showwarning is ours:  # unless someone replaced it since
        warnings.showwarning = show
    for h in _patched.pop("emits", []):
        h.__dict__.pop("emit", None)


def _tick(bar, stop: threading.Event) -> None:
    """Refresh ``bar`` every :data:`TICK` s once its delay is over (elapsed time, no updates)."""
    while not stop.wait(TICK):
        now = bar._time()
        # tqdm's own clock (last_print_t) is left alone: its rate estimate reads it
        if now >= bar.start_t + bar.delay and now - bar.last_print_t >= TICK and not bar.disable:
            with bar.get_lock():
                if stop.is_set() or bar.disable:
                    return
                bar.refresh(nolock=True)
                bar._ticked = True


@contextlib.contextmanager
def stage(name: str, total: Optional[int] = None, unit: str = "it") -> Iterator[Stage]:
    """One stage of a run: shown as ``name`` with a bar over ``total`` ``unit``s, or with its
    elapsed time when ``total`` is None (see the module doc for when and how)."""
    if not enabled():
        yield _OFF
        return
    from tqdm import tqdm

    forced = _mode() == "on"
    top = not _active
    counted = total is not None
    bar = tqdm(total=total, desc=name, unit=unit, file=sys.stderr, leave=top, dynamic_ncols=True,
               delay=0.0 if forced else DELAY, mininterval=0.1 if forced else 0.2,
               bar_format=_RUNNING_FMT[counted])
    if top:
        _patch_output()
    _active.append(bar)
    stop = threading.Event()
    ticker = threading.Thread(target=_tick, args=(bar, stop), name="diffuser-lab-progress", daemon=True)
    ticker.start()
    ok = False
    try:
        yield Stage(bar)
        ok = True
    finally:
        stop.set()
        ticker.join()
        _active.remove(bar)
        if top:
            _unpatch_output()
        if ok and top:
            bar.bar_format = _DONE_FMT[counted]
        else:
            bar.leave = False  # a failed stage leaves no line: the error message starts its own
        if _shown(bar):
            bar.last_print_t = max(bar.last_print_t, bar.start_t + bar.delay)  # close() then finishes the line
        bar.close()


def say(line: str, file=None) -> None:
    """One line on stdout in one write (a sweep's and a search's lines): jobs that run side by side
    share the launcher's stdout, and print() writes the text and its newline separately (two jobs'
    lines then interleave mid-line)."""
    f = file or sys.stdout
    f.write(line + "\n")
    f.flush()
