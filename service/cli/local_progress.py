"""Progress of a job run in this process (``symgs compress``): a bar with the time left on a terminal, plain lines
otherwise (logs, CI, ``2> file``), where a bar would print nothing until the end."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from symgs_core.progress import Eta, format_seconds

if TYPE_CHECKING:
    from symgs_core.progress import ProgressEvent

LINE_EVERY_S = 10.0  # plain lines: one per stage or level change, else at most this often


class LocalProgress:
    """The pipeline's ``progress`` callback, as a context manager that owns the display."""

    def __init__(self, console: Console, *, quiet: bool = False, line_every_s: float = LINE_EVERY_S) -> None:
        self.console, self.quiet, self.line_every_s = console, quiet, line_every_s
        self.eta = Eta()
        self.bar: Progress | None = None
        self._start = time.monotonic()
        self._last_line: tuple[str, int | None, float] | None = None

    def __enter__(self) -> LocalProgress:
        self._start = time.monotonic()
        if not self.quiet and self.console.is_terminal:
            self.bar = Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                TextColumn("{task.percentage:>3.0f}%"),
                TimeElapsedColumn(),
                TextColumn("left {task.fields[left]}"),
                console=self.console,
            )
            self.bar.__enter__()
            self.task = self.bar.add_task("compress", total=1.0, left=format_seconds(None))
        return self

    def __exit__(self, *exc: object) -> None:
        if self.bar is not None:
            self.bar.__exit__(None, None, None)

    def __call__(self, event: ProgressEvent) -> None:
        now = time.monotonic()
        left = self.eta.update(event.fraction, now)
        if self.quiet:
            return
        label = f"{event.stage} L{event.level}" if event.level is not None else event.stage
        if self.bar is not None:
            self.bar.update(
                self.task, completed=event.fraction, description=f"{label}: {event.message}"[:60],
                left=format_seconds(left),
            )  # fmt: skip
            return
        key = (event.stage, event.level)
        last = self._last_line
        if last is not None and key == last[:2] and now - last[2] < self.line_every_s and event.fraction < 1:
            return
        self._last_line = (*key, now)
        self.console.file.write(
            f"compress: {label} {event.fraction * 100:3.0f}%  elapsed {format_seconds(now - self._start)}  "
            f"left {format_seconds(left)}  {event.message}\n"
        )
        self.console.file.flush()
