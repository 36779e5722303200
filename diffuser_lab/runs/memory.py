"""A run's peak resident memory (summary.json ``memory``), per job even when a sweep's jobs share
one process: the kernel's high-water mark (``VmHWM``) is reset to the current resident size when a
job starts (``/proc/self/clear_refs``, Linux >= 4.0) and read when it ends. Where that cannot be
done, the process's peak so far (``resource.getrusage``: a later job of the same process reports at
least an earlier one's peak; ``source`` says which)."""
from __future__ import annotations

import resource
from pathlib import Path

__all__ = ["reset_peak", "snapshot"]

_STATUS = Path("/proc/self/status")
_CLEAR = Path("/proc/self/clear_refs")
_state = {"reset": False, "start_kb": 0}


def _status_kb(field: str) -> int:
    try:
        for line in _STATUS.read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return 0


def reset_peak() -> bool:
    """Start a job's measurement: reset the high-water mark to the resident size now; False where the
    platform does not let it (then :func:`snapshot` reports the process's peak so far)."""
    _state["start_kb"] = _status_kb("VmRSS")
    try:
        _CLEAR.write_text("5")
        _state["reset"] = _status_kb("VmHWM") > 0
    except OSError:
        _state["reset"] = False
    return _state["reset"]


def snapshot() -> dict:
    """``{"peak_rss_gb", "start_rss_gb", "source"}``: the peak since :func:`reset_peak` (``VmHWM``) or the
    process's (``ru_maxrss``), and the resident size when the job started, GB (2^30 bytes)."""
    if _state["reset"]:
        peak_kb, source = _status_kb("VmHWM"), "VmHWM since the job's start"
    else:
        peak_kb, source = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, "ru_maxrss of the process"
    return {"peak_rss_gb": round(peak_kb / 2**20, 4), "start_rss_gb": round(_state["start_kb"] / 2**20, 4),
            "source": source}
