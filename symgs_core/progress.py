"""Progress reporting and cooperative cancellation shared by the pipeline's stages."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class ProgressEvent:
    """One progress report. ``fraction`` is the whole job's progress in [0, 1]."""

    stage: str  # load | views | detect | optimize | evaluate | encode | report | done
    level: int | None
    fraction: float
    message: str


ProgressFn = Callable[[ProgressEvent], None]
StopFn = Callable[[], bool]


class Cancelled(Exception):
    """Raised inside the pipeline when its ``should_stop`` callback answers True."""
