"""Which diffusion iterations a run records (``record.interval``) and which of them also get a
labelled point cloud in run.mcap (``record.clouds``).

The default schedule is log-spaced, 1-2-5 steps: 1, 2, 5, 10, 20, 50, 100, 200, 500, ... and the
last iteration, dense where Z changes fast (the first few iterations move most labels) and sparse
where it barely moves: 8 states for the 200 iterations of the demo, 10 for 1,000, 13 for 10,000,
so what a run keeps grows with the log of its iterations. ``record.interval=n`` records every n-th.
"""
from __future__ import annotations

from typing import Optional

_STEPS = (1, 2, 5)


def is_log_step(iteration: int) -> bool:
    """True for 1, 2, 5, 10, 20, 50, 100, ... (a 1, 2 or 5 followed by zeros)."""
    if iteration < 1:
        return False
    while iteration % 10 == 0:
        iteration //= 10
    return iteration in _STEPS


def recorded(iteration: int, interval: Optional[int], max_iter: int) -> bool:
    """Whether ``iteration`` (1-based) is on the schedule: the first, the last (``max_iter``; an
    earlier converged last one is recorded when the run ends) and the log steps or every
    ``interval``-th."""
    if iteration == 1 or iteration == max_iter:
        return True
    return is_log_step(iteration) if interval is None else iteration % interval == 0


def schedule(max_iter: int, interval: Optional[int] = None) -> list[int]:
    """Every iteration :func:`recorded` would record in a run of ``max_iter`` iterations."""
    return [i for i in range(1, max_iter + 1) if recorded(i, interval, max_iter)]


def with_cloud(iteration: int, clouds: str, last: bool) -> bool:
    """Whether a recorded iteration also gets the labelled foxglove.PointCloud: ``clouds='all'``
    every one; ``'decades'`` 100, 1000, ... and the last (a cloud holds positions, 18 bytes a
    point, ~11 compressed: what a Z state costs in 8-bit shares and more; the early ones are left
    out, /evidence/bayesian shows the labels the diffusion starts from)."""
    if clouds == "all" or last:
        return True
    if iteration < 100:
        return False
    while iteration % 10 == 0:
        iteration //= 10
    return iteration == 1


def describe(interval: Optional[int]) -> str:
    """The schedule in words, for ``diffuser-lab-inspect``."""
    if interval is None or interval <= 0:
        return "1-2-5 log steps"
    if interval == 1:
        return "every iteration"
    suffix = "th" if 10 <= interval % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(interval % 10, "th")
    return f"every {interval}{suffix}"


__all__ = ["recorded", "schedule", "with_cloud", "is_log_step", "describe"]
