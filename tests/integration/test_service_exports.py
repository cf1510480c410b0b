"""A finished job's exports over HTTP, one download per row of the export table, and the uploaded scene: what the
dashboard's viewer and web platforms fetch. The job's `.sog`, read by PlayCanvas ``splat-transform``, renders at
30 dB or more against the job's own archive decoded (skipped without Node.js)."""

from __future__ import annotations

from pathlib import Path

import httpx

from symgs_core.export.formats import EXPORTS
from tests.npm_tools import convert, splat_transform
from tests.unit.test_export_web_tools import FIDELITY_DB, render_psnr


def test_every_export_downloads_with_its_media_type(done_job: dict, api_a: httpx.Client, stack) -> None:  # noqa: ANN001
    from symgs_core.pipeline import decompress

    job_id = done_job["id"]
    assert set(done_job["links"]["exports"]) == {fmt.name for fmt in EXPORTS}
    assert {fmt.artifact for fmt in EXPORTS} <= set(done_job["artifacts"])
    paths = httpx.get(f"{stack.api_url}/openapi.json", timeout=10).json()["paths"]
    decoded = decompress(api_a.get(f"/v1/jobs/{job_id}/result").content)
    for fmt in EXPORTS:
        href = done_job["links"]["exports"][fmt.name]
        assert href == f"/v1/jobs/{job_id}/{fmt.artifact}" and f"/v1/jobs/{{job_id}}/{fmt.artifact}" in paths
        response = api_a.get(href)
        assert response.status_code == 200, (fmt.name, response.text[:200])
        assert response.headers["content-type"].split(";")[0] == fmt.media_type
        assert f'filename="{job_id}{fmt.extension}"' in response.headers["content-disposition"]
        # The worker wrote exactly what the format's writer makes of the archive's decode.
        assert response.content == fmt.write(decoded), fmt.name
    glb = api_a.get(done_job["links"]["exports"]["glb"]).content
    assert glb[:4] == b"glTF" and b'"extensionsUsed":["KHR_gaussian_splatting"]' in glb


def test_splat_transform_reads_the_job_sog_at_archive_fidelity(
    done_job: dict, api_a: httpx.Client, tmp_path: Path
) -> None:
    from symgs_core.pipeline import decompress
    from symgs_core.ply import load_scene

    tool = splat_transform()
    (tmp_path / "job.sog").write_bytes(api_a.get(done_job["links"]["exports"]["sog"]).content)
    convert(tool, tmp_path / "job.sog", tmp_path / "read_back.ply")
    decoded = decompress(api_a.get(done_job["links"]["result"]).content)
    read_back = load_scene(tmp_path / "read_back.ply")
    assert len(read_back) == len(decoded) and read_back.sh_degree == decoded.sh_degree
    assert render_psnr(read_back, decoded) >= FIDELITY_DB


def test_uploaded_scene_is_served_to_its_owner_only(
    done_job: dict, api_a: httpx.Client, api_b: httpx.Client, scene_path: Path
) -> None:
    href = done_job["links"]["scene"]
    assert href == f"/v1/jobs/{done_job['id']}/scene"
    response = api_a.get(href)
    assert response.status_code == 200 and response.content == scene_path.read_bytes()
    assert response.headers["content-type"] == "application/x-ply"
    other = api_b.get(href)
    assert other.status_code == 404 and other.json()["error"]["code"] == "not_found"
    assert api_a.get("/v1/jobs/0123456789abcdef0123456789abcdef/scene").status_code == 404
