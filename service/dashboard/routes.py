"""``GET /`` (the job list), ``GET /jobs/{id}`` (one job) and ``GET /static/{name}``: the dashboard's pages.

The pages are static files; their scripts use the public ``/v1`` API with the visitor's API key, so the dashboard
can do nothing a client could not. Every answer carries a Content-Security-Policy that allows this origin only
(and ``blob:`` images and reads, which is how files fetched with an API key are shown, and ``blob:`` workers, which
is how the 3D view sorts splats): the pages make no request elsewhere, and nothing injected into them could.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from fastapi import APIRouter
from fastapi import Path as PathParam
from fastapi.responses import FileResponse

from ..api.errors import ApiError

router = APIRouter(include_in_schema=False)

STATIC = Path(__file__).parent / "static"
# Served files by name: a fixed table, so no request path ever reaches the file system.
MEDIA_TYPES = {
    "app.js": "text/javascript",
    "jobs.js": "text/javascript",
    "job.js": "text/javascript",
    "style.css": "text/css",
    "favicon.svg": "image/svg+xml",
    "viewer.js": "text/javascript",  # built from viewer/ (see its build.mjs): the PlayCanvas engine
    "viewer-license.txt": "text/plain",
}
CSP = (
    "default-src 'none'; script-src 'self'; worker-src blob:; style-src 'self'; img-src 'self' blob:; "
    "connect-src 'self' blob:; form-action 'none'; base-uri 'none'; frame-ancestors 'none'"
)
HEADERS = {
    "Content-Security-Policy": CSP,
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-cache",  # revalidate (ETag) so a new version shows on the next visit
}


def _page(name: str) -> FileResponse:
    return FileResponse(STATIC / name, media_type="text/html; charset=utf-8", headers=HEADERS)


@router.get("/")
def jobs_page() -> FileResponse:
    return _page("index.html")


@router.get("/jobs/{job_id}")
def job_page(job_id: Annotated[str, PathParam(pattern=r"^[A-Za-z0-9_-]{1,64}$")]) -> FileResponse:
    # The script reads the id from the address and asks the API, which answers 404 for another key's job.
    return _page("job.html")


@router.get("/static/{name}")
def static_file(name: str) -> FileResponse:
    media_type = MEDIA_TYPES.get(name)
    if media_type is None:
        raise ApiError(404, "not_found", f"no dashboard file {name!r}")
    return FileResponse(STATIC / name, media_type=media_type, headers=HEADERS)
