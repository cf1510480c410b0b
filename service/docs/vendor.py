"""Swagger UI's files, as the ``fastapi-offline`` package ships them, with its stylesheet's inline images served as
files of their own: the Content-Security-Policy allows images from this origin only, and not ``data:`` URLs."""

from __future__ import annotations

import base64
import re
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from urllib.parse import unquote_to_bytes

import fastapi_offline

VENDOR = Path(fastapi_offline.__file__).parent / "static"
SCRIPT = VENDOR / "swagger-ui-bundle.js"
ICONS = "/docs/static/icon-{}"
# url("data:...") with CSS escapes inside the quotes, or url(data:...) without quotes
_INLINE = re.compile(r'url\((?:"(data:(?:[^"\\]|\\.)*)"|(data:[^)"]*))\)')
_DATA = re.compile(r"^data:(?P<type>[\w.+/-]+)(?:;[\w=.-]+)*?(?P<base64>;base64)?,(?P<data>.*)$", re.S)
_CSS_ESCAPE = re.compile(r"\\(.)", re.S)


@dataclass(frozen=True)
class Stylesheet:
    text: bytes  # swagger-ui.css with each inline image replaced by the address of its file
    icons: tuple[tuple[str, bytes], ...]  # (media type, bytes) of icon-<index>


@cache
def stylesheet() -> Stylesheet:
    icons: list[tuple[str, bytes]] = []

    def to_file(match: re.Match[str]) -> str:
        url = _CSS_ESCAPE.sub(r"\1", match[1]) if match[1] is not None else match[2]
        data = _DATA.match(url)
        if data is None:  # not a data URL this reads: left as it is, and the policy refuses it
            return match[0]
        payload = base64.b64decode(data["data"]) if data["base64"] else unquote_to_bytes(data["data"])
        icons.append((data["type"], payload))
        return f"url({ICONS.format(len(icons) - 1)})"

    text = _INLINE.sub(to_file, (VENDOR / "swagger-ui.css").read_text(encoding="utf-8"))
    return Stylesheet(text.encode(), tuple(icons))
