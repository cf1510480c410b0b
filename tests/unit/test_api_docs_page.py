"""``/docs`` loads nothing from another host and carries the dashboard's Content-Security-Policy, while Swagger's
Authorize box takes the API key; ``/redoc`` (whose styles that policy refuses) leads to it."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.dashboard.routes import CSP
from worker.settings import Settings


@pytest.fixture(scope="module")
def client() -> TestClient:
    # No connection to Redis is made for these pages.
    return TestClient(create_app(Settings(redis_url="redis://127.0.0.1:1/0", storage="unused", auth="none")))


def test_the_docs_page_loads_only_shipped_files_under_the_dashboards_policy(client: TestClient) -> None:
    page = client.get("/docs")
    assert page.status_code == 200 and page.headers["content-security-policy"] == CSP
    assert "http" not in page.text and "//" not in page.text.replace("<!doctype", "")
    assert re.findall(r"<script\b[^>]*>\s*[^<\s]", page.text) == [], "inline script"
    assets = re.findall(r'(?:src|href)="([^"]+)"', page.text)
    shipped = {f"/docs/static/{name}" for name in ("swagger-ui-bundle.js", "swagger-ui.css", "swagger.js")}
    assert shipped <= set(assets)
    for asset in assets:
        answer = client.get(asset)
        assert answer.status_code == 200 and answer.headers["content-security-policy"] == CSP, asset
    start = client.get("/docs/static/swagger.js").text
    assert '"/openapi.json"' in start and "validatorUrl: null" in start
    # The stylesheet's inline images (data: URLs, which the policy refuses) are files of their own.
    css = client.get("/docs/static/swagger-ui.css").text
    icons = re.findall(r"url\((/docs/static/icon-\d+)\)", css)
    assert "data:" not in css and len(icons) >= 8
    for icon in set(icons):
        answer = client.get(icon)
        assert answer.status_code == 200 and answer.headers["content-type"].startswith("image/"), icon


def test_redoc_leads_to_the_docs_and_no_other_file_is_served(client: TestClient) -> None:
    redoc = client.get("/redoc", follow_redirects=False)
    assert redoc.status_code == 307 and redoc.headers["location"] == "/docs"
    assert client.get("/docs/static/..%2Fstatic%2Fswagger.html").status_code == 404
    assert client.get("/docs/oauth2-redirect").status_code == 404
