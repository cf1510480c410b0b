"""What every stage of a job reads and none changes: its settings, device and inputs (``Job``), and the reporter that
carries its progress, its cancellation and the seconds each stage took (``Reporter``)."""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import cached_property
from pathlib import Path
from typing import Any, TypeVar

import torch

from ..config import PRESETS, CompressConfig, PresetSpec
from ..progress import Cancelled, ProgressEvent, ProgressFn, StopFn
from .checkpoint import settings_digest

# Share of the job's progress bar each stage takes; the mirror levels share theirs.
STAGE_SHARES = {
    "load": (0.0, 0.02),
    "views": (0.02, 0.06),
    "codec": (0.06, 0.35),
    "refine": (0.35, 0.45),
    "levels": (0.45, 0.88),
    "encode": (0.88, 0.93),
    "evaluate": (0.93, 1.0),
}


class Reporter:
    """Progress events on the job's bar, the cancellation check before each, and the seconds per stage."""

    def __init__(self, progress: ProgressFn | None, should_stop: StopFn | None) -> None:
        self.progress, self.should_stop = progress, should_stop
        self.seconds: dict[str, float] = {}
        self.reached = 0.0  # the bar never moves back, though a stage may run its steps twice (mirrors on and off)

    def __call__(self, stage: str, within: float, message: str, level: int | None = None) -> None:
        if self.should_stop is not None and self.should_stop():
            raise Cancelled()
        lo, hi = STAGE_SHARES[stage]
        if self.progress is not None:
            self.reached = max(self.reached, lo + (hi - lo) * min(max(within, 0.0), 1.0))
            self.progress(ProgressEvent(stage, level, self.reached, message))

    def timed(self, stage: str, seconds: float) -> None:
        self.seconds[stage] = self.seconds.get(stage, 0.0) + seconds


@dataclass(frozen=True)
class Job:
    """One compression job's fixed inputs. ``images``: the posed photographs' dataset (None: the upload's own renders
    are the reference); ``checkpoint_dir``: where level decisions are saved for a rerun to resume after (None: not
    saved); ``charts``: whether the pictures include the two charts drawn from the report alone."""

    config: CompressConfig
    device: torch.device
    reporter: Reporter
    images: Path | None = None
    checkpoint_dir: Path | None = None
    charts: bool = True

    @property
    def preset(self) -> PresetSpec:
        return PRESETS[self.config.preset]

    @property
    def photographs(self) -> bool:
        return self.images is not None

    @cached_property
    def settings_digest(self) -> bytes:
        """What every checkpoint of the job matches besides its scene (``checkpoint.settings_digest``), read once."""
        return settings_digest(self.config, self.images)


State = TypeVar("State")


def grown(prior: Any, next_state: type[State], **more: Any) -> State:
    """``next_state`` made of every field of ``prior`` (the state it extends) and ``more``."""
    return next_state(**{f.name: getattr(prior, f.name) for f in fields(prior)}, **more)
