"""Oversized, malformed and hostile uploads are refused with the right status and code, and the service stays
healthy: the next job still succeeds."""

from __future__ import annotations

import io
import json
import tarfile
import zipfile
from pathlib import Path

import httpx
import pytest

from tests.integration.conftest import LIMITS, TINY, finished, wait_for


def _post(api: httpx.Client, scene: bytes, *, images: bytes | None = None, params: str | None = None) -> httpx.Response:
    files = {"scene": ("scene.ply", scene)}
    if images is not None:
        files["images"] = ("images.zip", images)
    data = {"params": params} if params is not None else None
    return api.post("/v1/jobs", files=files, data=data)


def _zip(entries: dict[str, bytes], symlinks: dict[str, str] | None = None) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in entries.items():
            zf.writestr(name, data)
        for name, target in (symlinks or {}).items():
            info = zipfile.ZipInfo(name)
            info.external_attr = (0o120777 << 16)  # a symbolic link
            zf.writestr(info, target)
    return buffer.getvalue()


def _png(width: int, height: int) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.new("RGB", (width, height), (200, 30, 30)).save(buffer, format="PNG")
    return buffer.getvalue()


def _nerf(extra: dict[str, bytes] | None = None, size: int = 32) -> dict[str, bytes]:
    pose = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]
    frames = [{"file_path": f"./train/r_{i}", "transform_matrix": pose} for i in range(2)]
    meta = json.dumps({"camera_angle_x": 0.69, "frames": frames}).encode()
    entries = {"lego/transforms_train.json": meta, **{f"lego/train/r_{i}.png": _png(size, size) for i in range(2)}}
    return {**entries, **(extra or {})}


def _tar(build) -> bytes:  # noqa: ANN001 - build(tarfile.TarFile)
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tf:
        build(tf)
    return buffer.getvalue()


def _tar_link(kind: bytes) -> bytes:
    def build(tf: tarfile.TarFile) -> None:
        info = tarfile.TarInfo("lego/transforms_train.json")
        info.type, info.linkname = kind, "/etc/passwd"
        tf.addfile(info)

    return _tar(build)


def _tar_bomb() -> bytes:
    def build(tf: tarfile.TarFile) -> None:
        info = tarfile.TarInfo("lego/zeros.bin")
        info.size = 3 << 20
        tf.addfile(info, io.BytesIO(bytes(info.size)))

    return _tar(build)


def _header_swap(ply: bytes, old: bytes, new: bytes) -> bytes:
    end = ply.index(b"end_header")
    assert old in ply[:end]
    return ply[:end].replace(old, new) + ply[end:]


def _rest_header(ply: bytes, count: int) -> bytes:
    end = ply.index(b"end_header")
    lines = [line for line in ply[:end].split(b"\n") if not line.startswith(b"property float f_rest_")]
    at = lines.index(b"property float opacity")
    rest = [f"property float f_rest_{i}".encode() for i in range(count)]
    return b"\n".join(lines[:at] + rest + lines[at:]) + ply[end:]


def _faces_first(ply: bytes, count: int) -> bytes:
    """A face element before the vertices: a list element, counted at its smallest size (an empty list each)."""
    return _header_swap(
        ply, b"element vertex 20", f"element face {count}\nproperty list uchar int vertex_indices\n".encode()
        + b"element vertex 20",
    )  # fmt: skip


CASES = {
    # name: (build(ply) -> (scene, images, params), status, code)
    "not a ply": (lambda ply: (b"solid cube\nfacet normal 0 0 1\n", None, None), 422, "not_ply"),
    "empty file": (lambda ply: (b"", None, None), 422, "not_ply"),
    "wrong f_rest count": (lambda ply: (_rest_header(ply, 10), None, None), 422, "bad_sh_count"),
    "missing opacity": (lambda ply: (_header_swap(ply, b"property float opacity", b"property float alpha"), None, None),
                        422, "missing_property"),  # fmt: skip
    "header claims more Gaussians than the file holds": (
        lambda ply: (_header_swap(ply, b"element vertex 20", b"element vertex 40"), None, None), 422, "truncated"),
    "a list element claiming 1e12 entries": (lambda ply: (_faces_first(ply, 10**12), None, None), 422, "truncated"),
    "header declares fewer Gaussians than the file holds": (
        lambda ply: (_header_swap(ply, b"element vertex 20", b"element vertex 19"), None, None), 422, "trailing_data"),
    "bytes after the last Gaussian": (lambda ply: (ply + bytes(16), None, None), 422, "trailing_data"),
    "too many Gaussians": (
        lambda ply: (_header_swap(ply, b"element vertex 20", b"element vertex 99999"), None, None),
        413, "too_many_gaussians"),  # fmt: skip
    "binary garbage header": (lambda ply: (b"ply\n\xff\xfe\x00\nend_header\n", None, None), 422, "malformed"),
    "upload above the size cap": (lambda ply: (bytes(int(LIMITS["SYMGS_MAX_UPLOAD_BYTES"]) + 1), None, None),
                                  413, "upload_too_large"),  # fmt: skip
    "params not JSON": (lambda ply: (ply, None, "{preset: small"), 422, "bad_params"),
    "params out of range": (lambda ply: (ply, None, '{"iterations": -5}'), 422, "bad_params"),
    "params with an unknown field": (lambda ply: (ply, None, '{"rm": "-rf"}'), 422, "bad_params"),
    "params not an object": (lambda ply: (ply, None, "[1, 2]"), 422, "bad_params"),
    "params with a boolean for a count": (lambda ply: (ply, None, '{"iterations": true}'), 422, "bad_params"),
    "params with a string for a number": (lambda ply: (ply, None, '{"seed": "7"}'), 422, "bad_params"),
    "zip with ../ path": (lambda ply: (ply, _zip({**_nerf(), "../../evil.txt": b"x"}), None), 422, "unsafe_entry"),
    "zip with absolute path": (lambda ply: (ply, _zip({**_nerf(), "/etc/cron.d/x": b"x"}), None), 422, "unsafe_entry"),
    "zip with a symlink entry": (lambda ply: (ply, _zip(_nerf(), {"lego/link": "/etc/passwd"}), None),
                                 422, "unsafe_entry"),  # fmt: skip
    "zip bomb": (lambda ply: (ply, _zip({**_nerf(), "lego/zeros.bin": bytes(8 << 20)}), None),
                 413, "archive_too_large"),  # fmt: skip
    "zip with too many entries": (lambda ply: (ply, _zip({**_nerf(), **{f"lego/f{i}": b"" for i in range(60)}}), None),
                                  413, "too_many_entries"),  # fmt: skip
    "tar.gz bomb": (lambda ply: (ply, _tar_bomb(), None), 413, "archive_too_large"),
    "tar with a symlink": (lambda ply: (ply, _tar_link(tarfile.SYMTYPE), None), 422, "unsafe_entry"),
    "tar with a hard link": (lambda ply: (ply, _tar_link(tarfile.LNKTYPE), None), 422, "unsafe_entry"),
    "images not an archive": (lambda ply: (ply, b"just some text", None), 422, "bad_archive"),
    "truncated zip": (lambda ply: (ply, _zip(_nerf())[:-30], None), 422, "bad_archive"),
    "archive without a dataset": (lambda ply: (ply, _zip({"notes/readme.txt": b"hello"}), None), 422, "bad_dataset"),
    "image above the pixel cap": (lambda ply: (ply, _zip(_nerf(size=200)), None), 413, "image_too_large"),
    "corrupt image": (lambda ply: (ply, _zip(_nerf({"lego/train/r_9.png": b"\x89PNG broken"})), None),
                      422, "bad_image"),  # fmt: skip
}


@pytest.mark.parametrize("case", list(CASES))
def test_hostile_upload_is_refused(case: str, api_a: httpx.Client, small_ply: bytes) -> None:
    build, status, code = CASES[case]
    scene, images, params = build(small_ply)
    response = _post(api_a, scene, images=images, params=params)
    assert response.status_code == status, response.text
    assert response.json()["error"]["code"] == code, response.text


def test_request_shape_errors(api_a: httpx.Client, small_ply: bytes) -> None:
    not_multipart = api_a.post("/v1/jobs", content=small_ply, headers={"content-type": "application/octet-stream"})
    assert (not_multipart.status_code, not_multipart.json()["error"]["code"]) == (422, "not_multipart")
    no_scene = api_a.post("/v1/jobs", files={"images": ("a.zip", b"PK")})
    assert (no_scene.status_code, no_scene.json()["error"]["code"]) == (422, "missing_scene")
    extra = api_a.post("/v1/jobs", files={"scene": ("s.ply", small_ply), "script": ("x.sh", b"#!/bin/sh")})
    assert (extra.status_code, extra.json()["error"]["code"]) == (422, "unknown_field")


def test_a_body_cut_before_its_closing_boundary_is_refused(api_a: httpx.Client, small_ply: bytes) -> None:
    """A multipart body that ends inside its last part is refused, not stored as it is: here the images, a tar whose
    end, cut off, is only padding, so it would read as a whole dataset."""
    images = io.BytesIO()
    with tarfile.open(fileobj=images, mode="w") as tf:
        for name, data in _nerf().items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    files = {"scene": ("s.ply", small_ply), "images": ("lego.tar", images.getvalue())}
    request = httpx.Request("POST", "http://x/", files=files, data={"params": json.dumps(TINY)})
    body, content_type = request.read(), request.headers["content-type"]
    for cut in (body[: body.rindex(b"\r\n--")], body[:-1000]):
        response = api_a.post("/v1/jobs", content=cut, headers={"content-type": content_type})
        assert response.status_code == 422, response.text
        assert response.json()["error"]["code"] == "bad_multipart", response.text
    empty = api_a.post("/v1/jobs", content=b"", headers={"content-type": content_type})
    assert (empty.status_code, empty.json()["error"]["code"]) == (422, "missing_scene")


def test_service_stays_healthy_and_accepts_a_dataset(
    api_a: httpx.Client, small_ply: bytes, scene_path: Path, stack  # noqa: ANN001
) -> None:
    assert api_a.get("/healthz").json() == {"status": "ok"}
    assert api_a.get("/readyz").status_code == 200
    staging = list((stack.root / "storage" / "staging").iterdir())
    assert staging == [], "refused uploads must leave nothing behind"

    accepted = _post(api_a, small_ply, images=_zip(_nerf()), params=json.dumps({**TINY, "iterations": 5000}))
    assert accepted.status_code == 202, accepted.text
    job = accepted.json()
    assert job["images"] == {"layout": "nerf_synthetic", "images": 2, "bytes": sum(len(v) for v in _nerf().values())}
    api_a.delete(f"/v1/jobs/{job['id']}")

    after = _post(api_a, scene_path.read_bytes(), params=json.dumps(TINY))
    assert after.status_code == 202, after.text
    assert wait_for(api_a, after.json()["id"], finished)["state"] == "succeeded"
