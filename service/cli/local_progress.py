"""Progress of a job run in this process (``symgs compress``, ``symgs train``): a bar with the time left on a
terminal, plain lines otherwise (logs, CI, ``2> file``), where a bar would print nothing until the end.

The pipeline reports at its own pace, sometimes minutes apart inside one step; a ticker thread keeps the time left
(and, as plain lines, the sign of life) moving in between."""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from symgs_core.progress import Eta, format_seconds

if TYPE_CHECKING:
    from symgs_core.progress import ProgressEvent

LINE_EVERY_S = 10.0  # plain lines: one per stage or level change, else one this often


class LocalProgress:
    """The pipeline's ``progress`` callback, as a context manager that owns the display."""

    def __init__(
        self, console: Console, *, quiet: bool = False, line_every_s: float = LINE_EVERY_S, command: str = "compress"
    ) -> None:
        self.console, self.quiet, self.line_every_s, self.command = console, quiet, line_every_s, command
        self.eta = Eta()
        self.bar: Progress | None = None
        self._lock = threading.Lock()
        self._halt = threading.Event()
        self._ticker: threading.Thread | None = None
        self._start = time.monotonic()
        self._event: ProgressEvent | None = None
        self._line_at: tuple[str, int | None, float] | None = None  # stage, level and time of the last line

    def __enter__(self) -> LocalProgress:
        self._start = time.monotonic()
        if self.quiet:
            return self
        if self.console.is_terminal:
            self.bar = Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                TextColumn("{task.percentage:>3.0f}%"),
                TimeElapsedColumn(),
                TextColumn("left {task.fields[left]}"),
                console=self.console,
            )
            self.bar.__enter__()
            self.task = self.bar.add_task(self.command, total=1.0, left=format_seconds(None))
        self._ticker = threading.Thread(target=self._tick, name="progress-ticker", daemon=True)
        self._ticker.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._halt.set()
        if self._ticker is not None:
            self._ticker.join()
        if self.bar is not None:
            self.bar.__exit__(None, None, None)

    def __call__(self, event: ProgressEvent) -> None:
        now = time.monotonic()
        with self._lock:
            left = self.eta.update(event.fraction, now)
            self._event = event
            if self.bar is not None:
                label = f"{event.stage} L{event.level}" if event.level is not None else event.stage
                self.bar.update(self.task, completed=event.fraction, description=f"{label}: {event.message}"[:60],
                                left=format_seconds(left))  # fmt: skip
            elif not self.quiet:
                last = self._line_at
                due = last is None or (event.stage, event.level) != last[:2] or now - last[2] >= self.line_every_s
                if due or event.fraction >= 1:
                    self._line(event, now, left)

    def _tick(self) -> None:
        while not self._halt.wait(1.0):
            now = time.monotonic()
            with self._lock:
                if self._event is None:
                    continue
                left = self.eta.estimate(now)
                if self.bar is not None:
                    self.bar.update(self.task, left=format_seconds(left))
                elif self._line_at is not None and now - self._line_at[2] >= self.line_every_s:
                    self._line(self._event, now, left)

    def _line(self, event: ProgressEvent, now: float, left: float | None) -> None:
        self._line_at = (event.stage, event.level, now)
        label = f"{event.stage} L{event.level}" if event.level is not None else event.stage
        self.console.file.write(
            f"{self.command}: {label} {event.fraction * 100:3.0f}%  elapsed {format_seconds(now - self._start)}  "
            f"left {format_seconds(left)}  {event.message}\n"
        )
        self.console.file.flush()
