"""The OpenAPI document is complete, and the API process never loads torch."""

from __future__ import annotations

import subprocess
import sys

import pytest

from service.api.app import create_app
from symgs_core.export.formats import EXPORTS
from worker.settings import Settings

ROUTES = {
    ("post", "/v1/jobs"), ("get", "/v1/jobs"), ("get", "/v1/jobs/{job_id}"), ("delete", "/v1/jobs/{job_id}"),
    ("post", "/v1/jobs/{job_id}:cancel"), ("get", "/v1/jobs/{job_id}/events"), ("get", "/v1/jobs/{job_id}/result"),
    ("get", "/v1/jobs/{job_id}/report"), ("get", "/v1/jobs/{job_id}/charts/{name}.png"), ("get", "/v1/presets"),
    ("get", "/v1/jobs/{job_id}/scene"),
    ("get", "/healthz"), ("get", "/readyz"), ("get", "/metrics"),
} | {("get", f"/v1/jobs/{{job_id}}/{fmt.artifact}") for fmt in EXPORTS}  # every row of the export table  # fmt: skip


@pytest.fixture(scope="module")
def doc() -> dict:
    # No connection is made until a request arrives.
    return create_app(Settings(redis_url="redis://127.0.0.1:1/0", storage="unused")).openapi()


def test_every_route_is_documented(doc: dict) -> None:
    operations = {(method, path) for path, item in doc["paths"].items() for method in item}
    assert operations == ROUTES
    for method, path in ROUTES:
        op = doc["paths"][path][method]
        assert op.get("summary") and op.get("description"), (method, path)
        success = [code for code in op["responses"] if code.startswith("2")]
        assert success, (method, path)
        for code in success:
            content = op["responses"][code].get("content")
            assert content or code == "204", (method, path, code)
        if path.startswith("/v1/"):
            assert "401" in op["responses"] and "ErrorResponse" in str(op["responses"]["401"]), (method, path)


def test_models_and_examples(doc: dict) -> None:
    schemas = doc["components"]["schemas"]
    for name in ("Job", "JobPage", "JobParams", "JobEvent", "Report", "ErrorResponse", "Readiness", "Health"):
        assert schemas[name].get("examples"), name
    create = doc["paths"]["/v1/jobs"]["post"]
    body = create["requestBody"]["content"]["multipart/form-data"]["schema"]
    assert body["required"] == ["scene"] and set(body["properties"]) == {"scene", "images", "params"}
    assert create["responses"]["202"]["content"]["application/json"]["schema"]["$ref"].endswith("/Job")
    assert {"413", "422"} <= set(create["responses"])
    get = doc["paths"]["/v1/jobs/{job_id}"]["get"]["responses"]["200"]
    assert get["content"]["application/json"]["schema"]["$ref"].endswith("/Job")
    assert "text/event-stream" in doc["paths"]["/v1/jobs/{job_id}/events"]["get"]["responses"]["200"]["content"]
    assert doc["components"]["securitySchemes"]["HTTPBearer"]["scheme"] == "bearer"


def test_api_process_never_imports_torch() -> None:
    """Neither the app nor the command line that serves it (the API image has no torch)."""
    code = (
        "import sys, service.api.app, service.cli\n"
        "service.api.app.create_app()\n"
        "service.cli.parser.build_parser()\n"
        "heavy = sorted(m for m in ('torch', 'numba', 'scipy', 'matplotlib') if m in sys.modules)\n"
        "assert not heavy, f'imported {heavy}'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
