"""Progress reporting and cooperative cancellation shared by the pipeline's stages, and the estimate of the time
left that the CLI, the worker (hence the job's events and the dashboard) derive from it."""

from __future__ import annotations

from collections import deque
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


class Eta:
    """Seconds left, from the job's fraction done over time.

    The rate is the progress made over the last ``window_s`` seconds (all of it while the job is younger), so the
    estimate follows a stage that runs slower or faster than the share of the bar it was given, and the time left is
    ``(1 - fraction) / rate``. No estimate (None) before ``min_elapsed_s`` seconds and ``min_progress`` of progress,
    nor when nothing moved over the whole window. Fractions never move back (a smaller one counts as the largest
    seen). ``now`` is any monotonic clock in seconds; the caller passes it, so the estimate is a pure function of the
    reports it was given.
    """

    def __init__(self, *, window_s: float = 60.0, min_elapsed_s: float = 2.0, min_progress: float = 0.005) -> None:
        if not window_s > 0 or min_elapsed_s < 0 or min_progress < 0:
            raise ValueError(f"bad Eta settings: window {window_s}, min elapsed {min_elapsed_s}, min {min_progress}")
        self.window_s, self.min_elapsed_s, self.min_progress = window_s, min_elapsed_s, min_progress
        self._samples: deque[tuple[float, float]] = deque()  # (time, fraction), oldest first
        self._start: tuple[float, float] | None = None

    def update(self, fraction: float, now: float) -> float | None:
        """Record that ``fraction`` (0..1) of the job was done at ``now``; return the seconds left, or None."""
        fraction = min(max(float(fraction), 0.0), 1.0)
        if self._samples:
            fraction = max(fraction, self._samples[-1][1])
            now = max(now, self._samples[-1][0])
        else:
            self._start = (now, fraction)
        self._samples.append((now, fraction))
        # Keep the newest sample at or before the window's start, so the rate always spans the whole window.
        while len(self._samples) > 1 and self._samples[1][0] <= now - self.window_s:
            self._samples.popleft()
        return self.estimate(now)

    def estimate(self, now: float) -> float | None:
        """The seconds left at ``now`` (at or after the last report) with no new report since: a stage that reports
        rarely is seen slowing down as time passes, not frozen at its last estimate."""
        if self._start is None:
            return None
        t_last, fraction = self._samples[-1]
        now = max(now, t_last)
        if fraction >= 1.0:
            return 0.0
        t0, f0 = self._start
        if now - t0 < self.min_elapsed_s or fraction - f0 < self.min_progress:
            return None
        old = 0
        while old + 1 < len(self._samples) and self._samples[old + 1][0] <= now - self.window_s:
            old += 1
        t_old, f_old = self._samples[old]
        if now <= t_old or fraction <= f_old:
            return None
        return (1.0 - fraction) * (now - t_old) / (fraction - f_old)


def format_seconds(seconds: float | None) -> str:
    """``1:02:03`` / ``2:03`` for a duration in seconds (rounded up), ``-:--`` when unknown."""
    if seconds is None:
        return "-:--"
    total = max(0, int(-(-seconds // 1)))
    hours, rest = divmod(total, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"
