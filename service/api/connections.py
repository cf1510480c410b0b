"""The API's HTTP connections (``symgs serve`` gives uvicorn this protocol): a deadline for each request's head, a
limit on a body's silence, and a bound on the connections still waiting for their head.

uvicorn waits for a request's head as long as the client takes, before any key is checked: clients that each sent
one header line every 30 s held 1,100 connections, exhausted a 1,024-descriptor API and locked every real client out.
Here a head must arrive whole within ``SYMGS_HEADER_TIMEOUT`` seconds of the connection (or of the first byte of the
next request on a kept-alive one), a body may not stall for ``SYMGS_BODY_TIMEOUT`` seconds while the server waits for
it, and at most ``SYMGS_MAX_PENDING_CONNECTIONS`` connections wait for a head at once: one more closes the one that
has waited longest without its whole head in its socket, so that a flood makes way for a client that sends its head at
once (asyncio accepts a burst of connections in one turn of its loop and reads them in the next, so the longest waiting
may be a client whose head has come but not yet been read).
"""

from __future__ import annotations

import asyncio
import socket
from typing import Any

from uvicorn.protocols.http.h11_impl import H11Protocol

from worker.gateway import get_settings

_HEAD_PEEK = 64 * 1024  # past h11's default limit on a head (16 KiB) in uvicorn


class GuardedH11Protocol(H11Protocol):
    def __init__(self, *args: Any, **kwargs: Any) -> None:  # noqa: ANN401 - uvicorn's own signature
        super().__init__(*args, **kwargs)
        settings = get_settings()
        self.header_timeout, self.body_timeout = settings.header_timeout, settings.body_timeout
        self.max_pending = settings.max_pending_connections
        self.head_since: float | None = None  # when this connection began waiting for a head; None otherwise
        self._head_timer: asyncio.TimerHandle | None = None
        self._body_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._await_head()
        waiting = [c for c in self.connections if isinstance(c, GuardedH11Protocol) and c.head_since is not None]
        if len(waiting) > self.max_pending:
            for connection in sorted(waiting, key=lambda c: c.head_since or 0.0):
                if not connection._head_unread():
                    connection._head_late()
                    break

    def connection_lost(self, exc: Exception | None) -> None:
        self.head_since = None
        for timer in (self._head_timer, self._body_timer):
            if timer is not None:
                timer.cancel()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self.head_since is None and self._between_requests():  # the next request on a kept-alive connection
            self._await_head()
        super().data_received(data)
        if self.head_since is not None and not self._between_requests():  # its head arrived: a request runs
            self.head_since = None
            if self._head_timer is not None:
                self._head_timer.cancel()
        if self._awaiting_body():
            if self._body_timer is not None:
                self._body_timer.cancel()
            self._body_timer = self.loop.call_later(self.body_timeout, self._body_silent)

    def _between_requests(self) -> bool:
        return self.cycle is None or self.cycle.response_complete

    def _awaiting_body(self) -> bool:
        return self.cycle is not None and self.cycle.more_body and not self.cycle.response_complete

    def _head_unread(self) -> bool:
        """Whether a whole head waits in this connection's socket, read by no one yet (a peek: it stays there)."""
        sock = self.transport.get_extra_info("socket")
        fileno = -1 if sock is None else sock.fileno()
        if fileno < 0:  # closed already
            return False
        try:
            peek = socket.socket(fileno=fileno)  # the transport's descriptor, borrowed: detached, never closed, below
        except OSError:
            return False
        try:
            return b"\r\n\r\n" in peek.recv(_HEAD_PEEK, socket.MSG_PEEK | socket.MSG_DONTWAIT)
        except OSError:  # nothing there yet, or the peer gone
            return False
        finally:
            peek.detach()

    def _await_head(self) -> None:
        self.head_since = self.loop.time()
        self._head_timer = self.loop.call_later(self.header_timeout, self._head_late)

    def _head_late(self) -> None:
        if self.head_since is not None:
            self.head_since = None  # no longer waiting: the next connection in this loop turn closes another one
            self.transport.close()

    def _body_silent(self) -> None:
        if not self._awaiting_body():
            return
        if self.flow.read_paused:  # the application has not read what came: the client is not the one waiting
            self._body_timer = self.loop.call_later(self.body_timeout, self._body_silent)
            return
        self.transport.close()
