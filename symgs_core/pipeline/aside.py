"""Work only the report reads, started as soon as its inputs exist and run beside the stages at idle priority.

A job's cores are not busy all the time: between renders the codec's choices and the level loop run Python that
holds one core, and the other waits. The archives that say where the size went (the input's own float32 archive,
the plain state in the final codec, the pruned state) decide nothing, so they need not wait for the stages either:
they run on a thread of the job's own at the lowest scheduling priority, coding their streams on that thread alone
(``codec.section.coding_alone``), and take what the stages leave idle. Their bytes are the same wherever they are
written. A job that fails or is cancelled drops what was set aside, unread.
"""

from __future__ import annotations

import os
import sys
import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, TypeVar

from ..codec.section import coding_alone

T = TypeVar("T")
IDLE_NICENESS = 19  # the lowest priority the scheduler knows: set-aside work runs on cores the job leaves idle


class Aside:
    """Results by name, computed one after another, in the order they were ``start``-ed, on one idle-priority thread
    (one at a time: each archive holds a copy of the scene while it is written, and the job's own peak is near)."""

    def __init__(self) -> None:
        self._started: dict[str, Future] = {}
        self._queue: deque[tuple[Future, Callable[..., Any], tuple]] = deque()
        self._lock = threading.Lock()
        self._running = False

    def start(self, name: str, fn: Callable[..., Any], *args: Any) -> None:
        """Queue ``fn(*args)`` under ``name`` (replacing any result under it that was not read)."""
        future: Future = Future()
        self._started[name] = future
        with self._lock:
            self._queue.append((future, fn, args))
            if not self._running:
                self._running = True
                threading.Thread(target=self._work, name="aside", daemon=True).start()

    def result(self, name: str, fn: Callable[..., T], *args: Any) -> T:
        """What ``name`` computed (its exception raised here), waiting for it; ``fn(*args)`` now, on the calling
        thread, where nothing was started under ``name``. Either way the result is read once."""
        future = self._started.pop(name, None)
        return fn(*args) if future is None else future.result()

    def _work(self) -> None:
        """Run the queue until it is empty, then end (a later ``start`` begins another thread)."""
        _idle_priority()
        while True:
            with self._lock:
                if not self._queue:
                    self._running = False
                    return
                future, fn, args = self._queue.popleft()
            if not future.set_running_or_notify_cancel():
                continue
            try:
                with coding_alone():
                    future.set_result(fn(*args))
            except BaseException as exc:  # noqa: BLE001  # carried to the reader of the result
                future.set_exception(exc)


def _idle_priority() -> None:
    """This thread alone at the lowest priority (Linux schedules threads by their own niceness); elsewhere, or where
    the system refuses, it stays at the job's."""
    if sys.platform.startswith("linux"):
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), IDLE_NICENESS)
        except OSError:
            pass
