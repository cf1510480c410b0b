"""A stand-in for the SymGS API on a local port that answers from a script: client tests get the API's failures
(a 503 with Retry-After, a job that succeeds after it) on cue, without Redis or a worker."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

# status, headers, body
Answer = tuple[int, dict[str, str], bytes]


def answer_json(status: int, body: dict[str, Any], **headers: str) -> Answer:
    return status, {"Content-Type": "application/json", **headers}, json.dumps(body).encode()


def unavailable(retry_after: str) -> Answer:
    """What the API answers while its Redis is out of reach."""
    message = "the job store is not reachable (ConnectionError); try again"
    return answer_json(503, {"error": {"code": "unavailable", "message": message}}, **{"Retry-After": retry_after})


def job(job_id: str, state: str, artifacts: tuple[str, ...] = ()) -> Answer:
    base = f"/v1/jobs/{job_id}"
    return answer_json(200, {
        "id": job_id, "state": state, "progress": 1.0 if state == "succeeded" else 0.5, "params": {}, "queue": "cpu",
        "scene": {"filename": "scene.ply", "bytes": 1, "gaussians": 1, "sh_degree": 0}, "artifacts": list(artifacts),
        "created_at": 0.0, "updated_at": 0.0,
        "links": {"self": base, "events": f"{base}/events", "result": f"{base}/result", "report": f"{base}/report",
                  "scene": f"{base}/scene", "exports": {}},
    })  # fmt: skip


def events(*items: tuple[str, str]) -> Answer:
    """An event stream of (id, state) messages that then ends, as the API's does once a job is final."""
    text = "".join(
        f"id: {event_id}\nevent: state\ndata: "
        + json.dumps({"kind": "state", "state": state, "progress": 1.0 if state == "succeeded" else 0.5, "time": 0.0})
        + "\n\n"
        for event_id, state in items
    )
    return 200, {"Content-Type": "text/event-stream"}, text.encode()


class ScriptedApi:
    def __init__(self, script: dict[str, list[Answer]]) -> None:
        """``script``: "METHOD /path" -> its answers in turn, the last one repeated; anything else is 404."""
        self.script = script
        self.requests: list[tuple[str, dict[str, str]]] = []  # "METHOD /path", headers by lower-case name
        self._lock = threading.Lock()

    def answer(self, request: str, headers: dict[str, str]) -> Answer:
        with self._lock:  # `symgs submit` follows its jobs from one thread each
            self.requests.append((request, headers))
            answers = self.script.get(request)
            if not answers:
                return answer_json(404, {"error": {"code": "not_found", "message": request}})
            return answers.pop(0) if len(answers) > 1 else answers[0]

    def asked(self, request: str) -> list[dict[str, str]]:
        """The headers of each time ``request`` was made."""
        return [headers for made, headers in self.requests if made == request]


@contextmanager
def serving(api: ScriptedApi) -> Iterator[str]:
    """Serve ``api`` on a free local port for the block; yields its base URL."""

    class Handler(BaseHTTPRequestHandler):
        def reply(self) -> None:
            self.rfile.read(int(self.headers.get("Content-Length") or 0))
            asked = {name.lower(): value for name, value in self.headers.items()}
            status, headers, body = api.answer(f"{self.command} {self.path}", asked)
            self.send_response(status)
            for name, value in {**headers, "Content-Length": str(len(body))}.items():
                self.send_header(name, value)
            self.end_headers()
            self.wfile.write(body)

        do_GET = do_POST = reply

        def log_message(self, *args: object) -> None:
            pass  # the tests' output stays the client's

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_port}"
    finally:
        server.shutdown()
        server.server_close()
        thread.join()
