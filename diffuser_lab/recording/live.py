"""``record.live``: where run.rrd's content is also streamed as the run goes."""
from __future__ import annotations

from typing import Any, Optional

from diffuser_lab.config import live_is_off, live_is_valid

__all__ = ["live_target"]


def live_target(value: Any) -> Optional[str]:
    """record.live -> None (off), "spawn", a gRPC URL as Rerun's GrpcSink takes it (scheme
    rerun://, rerun+http:// or rerun+https://, host[:port], path /proxy), or "bad" (the accepted
    values: :func:`diffuser_lab.config.live_is_valid`)."""
    if live_is_off(value):
        return None
    if not live_is_valid(value):
        return "bad"
    return str(value).strip()
