"""A large upload generated as it is sent, and the resident memory of the process receiving it (from /proc): shared
by the upload-memory test and ``benchmarks/bench_upload.py``."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx

from symgs_core.ply_header import DC, GEOMETRY, NORMALS, ROTATIONS, SCALES

BOUNDARY = "symgs-upload-stream-boundary"
CHUNK = 1 << 20
PROPERTIES = [*GEOMETRY, *NORMALS, *DC, *(f"f_rest_{i}" for i in range(45)), "opacity", *SCALES, *ROTATIONS]


class Body:
    """``POST /v1/jobs`` multipart: params, then a scene of about ``scene_bytes``: a valid PLY header of an SH-3 scene
    whose Gaussians are all zero bytes, produced one chunk at a time."""

    def __init__(self, scene_bytes: int, params: dict | None = None) -> None:
        row = 4 * len(PROPERTIES)
        self.count = scene_bytes // row
        lines = ["ply", "format binary_little_endian 1.0", f"element vertex {self.count}"]
        self.header = ("\n".join([*lines, *(f"property float {p}" for p in PROPERTIES), "end_header"]) + "\n").encode()
        self.zeros = self.count * row
        self.head = (
            f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="params"\r\n\r\n{json.dumps(params or {})}\r\n'
            f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="scene"; filename="big.ply"\r\n'
            "Content-Type: application/octet-stream\r\n\r\n"
        ).encode()
        self.tail = f"\r\n--{BOUNDARY}--\r\n".encode()
        self.scene_bytes = len(self.header) + self.zeros
        self.length = len(self.head) + self.scene_bytes + len(self.tail)

    def __iter__(self) -> Iterator[bytes]:
        yield self.head + self.header
        left, block = self.zeros, bytes(CHUNK)
        while left:
            piece = block if left >= CHUNK else bytes(left)
            left -= len(piece)
            yield piece
        yield self.tail

    def headers(self, key: str | None) -> dict[str, str]:
        auth = {"Authorization": f"Bearer {key}"} if key else {}
        return {"Content-Type": f"multipart/form-data; boundary={BOUNDARY}", "Content-Length": str(self.length), **auth}


def status_kib(pid: int, field: str) -> int:
    """A ``/proc/<pid>/status`` figure in KiB (VmRSS, VmHWM, ...)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise KeyError(field)


class RssSampler(threading.Thread):
    """The largest VmRSS of ``pid`` seen every ``every_s`` until stopped."""

    def __init__(self, pid: int, every_s: float = 0.02) -> None:
        super().__init__(daemon=True)
        self.pid, self.every_s = pid, every_s
        self.peak_kib = 0
        self._halt = threading.Event()

    def run(self) -> None:
        while not self._halt.is_set():
            self.peak_kib = max(self.peak_kib, status_kib(self.pid, "VmRSS"))
            self._halt.wait(self.every_s)

    def stop(self) -> int:
        self._halt.set()
        self.join()
        return self.peak_kib


def upload(api_url: str, key: str | None, pid: int, scene_bytes: int, params: dict | None = None) -> dict:
    """Post one streamed upload while sampling the API process ``pid``; the response and the figures."""
    body = Body(scene_bytes, params)
    before = status_kib(pid, "VmRSS")
    sampler = RssSampler(pid)
    sampler.start()
    t0 = time.perf_counter()
    try:
        response = httpx.post(f"{api_url}/v1/jobs", content=iter(body), headers=body.headers(key), timeout=600)
    finally:
        peak = sampler.stop()
    seconds = time.perf_counter() - t0
    return {
        "status": response.status_code,
        "job": response.json(),
        "body_bytes": body.length,
        "scene_bytes": body.scene_bytes,
        "gaussians": body.count,
        "seconds": seconds,
        "mb_per_s": body.length / seconds / 1e6,
        "rss_before_mib": before / 1024,
        "rss_peak_mib": peak / 1024,
        "hwm_mib": status_kib(pid, "VmHWM") / 1024,
    }
