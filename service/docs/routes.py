"""``GET /docs`` (Swagger UI on the API's OpenAPI document) and ``GET /docs/static/{name}``; ``/redoc`` leads there.

FastAPI's own pages load Swagger UI and ReDoc from a CDN (floating major versions, no integrity hashes) and start
them with an inline script, while Swagger's Authorize box takes the API key. This page is a static file that loads
the script and style the ``fastapi-offline`` package ships, pinned with it (``vendor``), and starts them from a file
of ours, so it carries the dashboard's Content-Security-Policy: this origin only, no inline script or style. ReDoc
cannot run under that policy (its styled-components insert style elements, with no way to give them a nonce), so
it is not served.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse, RedirectResponse, Response

from ..api.errors import ApiError
from ..dashboard.routes import HEADERS
from .vendor import ICONS, SCRIPT, stylesheet

router = APIRouter(include_in_schema=False)

STATIC = Path(__file__).parent / "static"


@router.get("/docs")
def docs_page() -> FileResponse:
    return FileResponse(STATIC / "swagger.html", media_type="text/html; charset=utf-8", headers=HEADERS)


@router.get("/redoc")
def redoc_page() -> RedirectResponse:
    return RedirectResponse("/docs", status_code=307, headers=HEADERS)


# Served files by name: a fixed set, so no request path ever reaches the file system.
@router.get("/docs/static/{name}")
def static_file(name: str) -> Response:
    if name == "swagger.js":
        return FileResponse(STATIC / name, media_type="text/javascript", headers=HEADERS)
    if name == SCRIPT.name:
        return FileResponse(SCRIPT, media_type="text/javascript", headers=HEADERS)
    sheet = stylesheet()
    if name == "swagger-ui.css":
        return Response(sheet.text, media_type="text/css", headers=HEADERS)
    icons = {ICONS.format(i).rsplit("/", 1)[1]: icon for i, icon in enumerate(sheet.icons)}
    if name in icons:
        media_type, data = icons[name]
        return Response(data, media_type=media_type, headers=HEADERS)
    raise ApiError(404, "not_found", f"no docs file {name!r}")
