"""Receive ``POST /v1/jobs`` multipart bodies straight to disk, part by part, with a cap on the whole body.

Parts: ``scene`` (file, required) -> ``scene.ply``; ``images`` (file, optional) -> ``images.archive``;
``params`` (JSON text, optional, at most 64 KiB). Nothing is held in memory beyond one buffer of file data.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, MultipartState, parse_options_header
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect, Request

from worker.gateway import StorageError

from .errors import ApiError

MAX_PARAMS_BYTES = 64 << 10
DRAIN_BYTES = 64 << 20  # past the cap, read on this much (discarding it) so the client sees the 413 answer
_FLUSH_BYTES = 1 << 20
_FILES = {"scene": "scene.ply", "images": "images.archive"}


@dataclass
class Upload:
    scene: Path
    scene_filename: str
    scene_bytes: int
    images: Path | None
    params: str | None  # the JSON text, not yet validated


class _Receiver:
    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.name: str | None = None
        self.filename: str | None = None
        self.headers: dict[bytes, bytes] = {}
        self._field, self._value = b"", b""
        self.file: BinaryIO | None = None
        self.pending: list[bytes] = []
        self.pending_bytes = 0
        self.sizes: dict[str, int] = {}
        self.filenames: dict[str, str] = {}
        self.params: bytearray | None = None
        self.error: ApiError | None = None

    # python-multipart callbacks; errors are kept and raised by the caller (raising inside the parser loses them)
    def on_part_begin(self) -> None:
        self.headers, self.name, self.filename = {}, None, None

    def on_header_field(self, data: bytes, start: int, end: int) -> None:
        self._field += data[start:end]

    def on_header_value(self, data: bytes, start: int, end: int) -> None:
        self._value += data[start:end]

    def on_header_end(self) -> None:
        self.headers[self._field.lower()] = self._value
        self._field, self._value = b"", b""

    def on_headers_finished(self) -> None:
        _, options = parse_options_header(self.headers.get(b"content-disposition", b""))
        name = options.get(b"name", b"").decode("utf-8", "replace")
        if name in self.sizes or (name == "params" and self.params is not None):
            self.fail(ApiError(422, "bad_multipart", f"the part {name!r} appears twice"))
            return
        self.name = name
        if name in _FILES:
            self.filenames[name] = Path(options.get(b"filename", b"").decode("utf-8", "replace")).name[:200]
            self.sizes[name] = 0
            self.file = open(self.folder / _FILES[name], "xb")  # noqa: SIM115 - closed in on_part_end/close
        elif name == "params":
            self.params = bytearray()
        else:
            expected = "expected scene, images, params"
            self.fail(ApiError(422, "unknown_field", f"unknown form part {name[:40]!r}; {expected}"))

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        if self.error is not None:
            return
        if self.name in _FILES:
            self.sizes[self.name] += end - start
            self.pending.append(data[start:end])
            self.pending_bytes += end - start
        elif self.name == "params" and self.params is not None:
            self.params += data[start:end]
            if len(self.params) > MAX_PARAMS_BYTES:
                self.fail(ApiError(413, "params_too_large", f"params exceeds {MAX_PARAMS_BYTES} bytes"))

    def on_part_end(self) -> None:
        self.flush()
        if self.file is not None:
            self.file.close()
            self.file = None

    def fail(self, error: ApiError) -> None:
        if self.error is None:
            self.error = error

    def flush(self) -> None:
        if self.file is not None and self.pending:
            self.file.write(b"".join(self.pending))
        self.pending.clear()
        self.pending_bytes = 0

    def close(self) -> None:
        if self.file is not None:
            self.file.close()
            self.file = None


async def receive_upload(request: Request, folder: Path, *, max_bytes: int) -> Upload:
    """Parse the multipart body into ``folder``; ApiError 413 past ``max_bytes`` (the whole body), 422 when the
    body is not multipart, lacks the scene, or has parts other than scene, images and params."""
    content_type = request.headers.get("content-type", "")
    kind, options = parse_options_header(content_type)
    if kind != b"multipart/form-data" or b"boundary" not in options:
        raise ApiError(422, "not_multipart", "send the job as multipart/form-data with a 'scene' part")
    receiver = _Receiver(folder)
    callbacks = {name: getattr(receiver, name) for name in dir(receiver) if name.startswith("on_")}
    parser = MultipartParser(options[b"boundary"], callbacks)  # type: ignore[arg-type]
    declared = request.headers.get("content-length", "")
    too_large = declared.isdigit() and int(declared) > max_bytes
    over_limit = ApiError(413, "upload_too_large", f"the upload exceeds the limit of {max_bytes} bytes")
    if too_large and request.headers.get("expect", "").lower() == "100-continue":
        raise over_limit  # the client waits for this answer before it sends the body: nothing to drain
    total = 0
    try:
        async for chunk in request.stream():
            total += len(chunk)
            too_large = too_large or total > max_bytes
            if too_large:
                if total > max_bytes + DRAIN_BYTES:
                    break
                continue
            if receiver.error is None:
                parser.write(chunk)
            if receiver.pending_bytes >= _FLUSH_BYTES:
                await run_in_threadpool(receiver.flush)
        if not too_large and receiver.error is None:
            parser.finalize()
            receiver.flush()
            if parser.state not in (MultipartState.START, MultipartState.END):  # START: an empty body, no scene
                # python-multipart's finalize does not check this: a body cut short would pass with its last part cut
                receiver.fail(ApiError(422, "bad_multipart", "the multipart body ends before its closing boundary"))
    except FormParserError as exc:
        raise ApiError(422, "bad_multipart", f"the multipart body is malformed ({exc})") from None
    except ClientDisconnect:
        raise ApiError(400, "client_disconnected", "the client went away during the upload") from None
    except OSError as exc:  # the staging disk: full, read-only, gone
        raise StorageError(f"staging the upload: {type(exc).__name__}: {exc}") from exc
    finally:
        receiver.close()
    if too_large:
        raise over_limit
    if receiver.error is not None:
        raise receiver.error
    if "scene" not in receiver.sizes:
        raise ApiError(422, "missing_scene", "the 'scene' part (a .ply file) is required")
    return Upload(
        scene=folder / _FILES["scene"],
        scene_filename=receiver.filenames.get("scene") or "scene.ply",
        scene_bytes=receiver.sizes["scene"],
        images=folder / _FILES["images"] if "images" in receiver.sizes else None,
        params=receiver.params.decode("utf-8", "replace") if receiver.params is not None else None,
    )
