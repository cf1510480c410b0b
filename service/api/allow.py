"""Methods a path takes, from the application's own route table: ``OPTIONS`` (204), a method the path does not take
(405), both with ``Allow`` naming every method that path takes, and ``HEAD`` wherever ``GET`` is served.

Starlette answers a method a path does not take with the methods of the first route whose path matches, so a path
served by two routes (GET and DELETE of a job) would name only one of them; and FastAPI's routes take HEAD only where
declared, which HTTP asks of every GET resource.
"""

from __future__ import annotations

import json

from starlette.routing import BaseRoute, Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from .errors import error_body

_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE")


def _serves(routes: list[BaseRoute], scope: Scope, method: str) -> bool:
    return any(r.matches({**scope, "method": method})[0] == Match.FULL for r in routes)


class AllowedMethods:
    """ASGI middleware answering OPTIONS, 405 and HEAD from the application's own route table."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        method, routes = scope["method"], scope["app"].routes
        if method != "OPTIONS" and _serves(routes, scope, method):
            await self.app(scope, receive, send)
            return
        if method == "HEAD" and _serves(routes, scope, "GET"):
            await self.app({**scope, "method": "GET"}, receive, _headers_only(send))
            return
        methods = [m for m in _METHODS if _serves(routes, scope, "GET" if m == "HEAD" else m)]
        if not methods:
            await self.app(scope, receive, send)  # no such path: the application's 404
            return
        allow = ", ".join([*methods, "OPTIONS"]).encode()
        if method == "OPTIONS":
            await send({"type": "http.response.start", "status": 204, "headers": [(b"allow", allow)]})
            await send({"type": "http.response.body", "body": b""})
            return
        body = json.dumps(error_body("method_not_allowed", f"{method} is not a method of this path")).encode()
        headers = [(b"allow", allow), (b"content-type", b"application/json"),
                   (b"content-length", str(len(body)).encode())]  # fmt: skip
        await send({"type": "http.response.start", "status": 405, "headers": headers})
        await send({"type": "http.response.body", "body": body})


def _headers_only(send: Send) -> Send:
    """``send`` for a HEAD answered by its GET route: the GET's status and headers, none of its body."""

    async def sending(message: Message) -> None:
        if message["type"] == "http.response.body":
            message = {**message, "body": b""}
        await send(message)

    return sending
