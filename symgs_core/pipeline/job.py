"""What every stage of a job reads and none changes: its settings, device and inputs (``Job``), and the reporter that
carries its progress, its cancellation and the seconds each stage took (``Reporter``)."""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import torch

from ..config import PRESETS, CompressConfig, PresetSpec
from ..progress import Cancelled, ProgressEvent, ProgressFn, StopFn
from .checkpoint import settings_digest

if TYPE_CHECKING:
    from .encode import FitProgress

# Seconds per million Gaussians each stage takes on 2 cores (BENCHMARKS "Scale": the default preset at 1M on the Xeon
# host, and the preset that fits nothing; a fine-tune's step on the training photographs: 60 photographs at 800 px and
# 1M Gaussians there). The progress bar gives each stage a share in proportion to its time, so that the bar's pace,
# from which the time left is estimated (``progress.Eta``), holds from stage to stage: with one set of shares for
# every job, one with photographs at 250k spent a tenth of the bar on a fine-tune that took 10 minutes, and its
# estimate swung from an hour to 18 hours and back as detection and the next fine-tune followed.
STAGE_SECONDS = {"load": 0.5, "views": 0.2, "codec": 134.0, "encode": 31.0, "evaluate": 7.0}
FIXED_SECONDS = {"codec": 10.0, "encode": 11.0}  # a preset that fits nothing: one encode, no stage archives
STEP_SECONDS = 1.0  # one step of a fine-tune on the training photographs
LEVEL_SECONDS = 38.0  # one mirror level's detection and its memberships' first renders
# The part of a fine-tune's share that its steps take, the encode that judges it the rest: 1,600 steps take about ten
# times one encode's time.
TUNE_SHARE = 0.9
STAGES = ("load", "views", "codec", "refine", "levels", "encode", "evaluate")


def stage_shares(config: CompressConfig, photographs: bool) -> dict[str, tuple[float, float]]:
    """Each stage's share (start, end) of the job's bar, in proportion to the time it takes (``STAGE_SECONDS``); a
    stage the job skips has none. The levels' share is twice a level's time: the first level takes half of it
    (``level_share``)."""
    fitted = PRESETS[config.preset].fitted
    seconds = dict(STAGE_SECONDS) if fitted else {**STAGE_SECONDS, **FIXED_SECONDS}
    tuning = STEP_SECONDS * config.iterations if photographs and fitted else 0.0
    seconds["refine"] = tuning if config.quantized else 0.0
    level = LEVEL_SECONDS + (tuning + seconds["codec"] if tuning else 0.0)
    seconds["levels"] = 2.0 * level if config.use_mirrors and config.max_levels and fitted else 0.0
    total, start, shares = sum(seconds.values()), 0.0, {}
    for stage in STAGES:
        end = min(start + seconds[stage] / total, 1.0)
        shares[stage], start = (start, end), end
    return shares


def level_share(level: int, within: float) -> float:
    """Where ``within`` (0..1) of mirror level ``level`` lies on the levels' share of the bar: each level takes half
    of what the levels before it left, for a job seldom tries as many levels as it may, and the bar never moves
    back."""
    return 1.0 - 0.5**level * (1.0 - 0.5 * min(max(within, 0.0), 1.0))


class Reporter:
    """Progress events on the job's bar (``shares``: each stage's, by default the default preset's without
    photographs), the cancellation check before each, and the seconds per stage."""

    def __init__(self, progress: ProgressFn | None, should_stop: StopFn | None,
                 shares: dict[str, tuple[float, float]] | None = None) -> None:  # fmt: skip
        self.progress, self.should_stop = progress, should_stop
        self.shares = shares or stage_shares(CompressConfig.for_preset(), photographs=False)
        self.seconds: dict[str, float] = {}
        self.reached = 0.0  # the bar never moves back, though a stage may run its steps twice (mirrors on and off)

    def __call__(self, stage: str, within: float, message: str, level: int | None = None) -> None:
        if self.should_stop is not None and self.should_stop():
            raise Cancelled()
        lo, hi = self.shares[stage]
        if self.progress is not None:
            self.reached = max(self.reached, lo + (hi - lo) * min(max(within, 0.0), 1.0))
            self.progress(ProgressEvent(stage, level, self.reached, message))

    def part(self, stage: str, lo: float, hi: float, what: str, level: int | None = None) -> FitProgress:
        """Report ``what`` at ``lo`` of ``stage``'s share; the progress of a step that runs from there to ``hi`` (a
        codec fit's, 0..1 of it), its messages under ``what``."""
        self(stage, lo, what, level)
        return lambda within, message: self(stage, lo + (hi - lo) * within, f"{what}: {message}", level)

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
