"""``OPTIONS`` on any path the API serves: 204 with ``Allow`` naming every method that path takes.

Starlette answers OPTIONS with 405 and the methods of the first route whose path matches, so a path served by two
routes (GET and DELETE of a job) would name only one of them.
"""

from __future__ import annotations

from starlette.routing import Match
from starlette.types import ASGIApp, Receive, Scope, Send

_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE")


class AllowedMethods:
    """ASGI middleware answering OPTIONS from the application's own route table."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "OPTIONS":
            await self.app(scope, receive, send)
            return
        routes = scope["app"].routes
        methods = [m for m in _METHODS if any(r.matches({**scope, "method": m})[0] == Match.FULL for r in routes)]
        if not methods:
            await self.app(scope, receive, send)  # no such path: the application's 404
            return
        allow = ", ".join([*methods, "OPTIONS"]).encode()
        await send({"type": "http.response.start", "status": 204, "headers": [(b"allow", allow)]})
        await send({"type": "http.response.body", "body": b""})
