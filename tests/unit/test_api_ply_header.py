"""The API's PLY header check agrees with the full reader on what it accepts, and refuses what it must."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from service.api.errors import ApiError
from service.api.submission import check_scene
from symgs_core.export import save_scene
from symgs_core.ply import PlyError, read_scene
from symgs_core.scene import GaussianScene


def check_ply(path: Path, max_gaussians: int):  # noqa: ANN201 - PlyHeader
    return check_scene(path, max_gaussians=max_gaussians, name=path.name)


def _scene(n: int, k: int) -> GaussianScene:
    g = torch.Generator().manual_seed(n + k)
    return GaussianScene(
        means=torch.randn(n, 3, generator=g), quats=torch.randn(n, 4, generator=g),
        scales=torch.randn(n, 3, generator=g), opacities=torch.randn(n, generator=g),
        sh_dc=torch.randn(n, 3, generator=g), sh_rest=torch.randn(n, k, 3, generator=g),
    )  # fmt: skip


@pytest.mark.parametrize("k, degree", [(0, 0), (3, 1), (8, 2), (15, 3)])
def test_accepts_what_the_reader_reads(tmp_path: Path, k: int, degree: int) -> None:
    path = tmp_path / "s.ply"
    save_scene(_scene(37, k), path)
    header = check_ply(path, 1000)
    assert (header.format, header.count, header.sh_degree) == ("binary_little_endian", 37, degree)
    assert read_scene(path)[1].count == 37


def _edit(path: Path, old: bytes, new: bytes) -> None:
    data = path.read_bytes()
    end = data.index(b"end_header")
    assert old in data[:end]
    path.write_bytes(data[:end].replace(old, new, 1) + data[end:])


@pytest.mark.parametrize(
    "old, new, status, code",
    [
        (b"element vertex 37", b"element vertex 38", 422, "truncated"),
        (b"element vertex 37", b"element vertex 1001", 413, "too_many_gaussians"),
        (b"element vertex 37", b"element vertex 0", 422, "trailing_data"),
        (b"element vertex 37", b"element vertex 20", 422, "trailing_data"),
        (b"element vertex", b"element face 1000000000000\nproperty list uchar int vertex_indices\nelement vertex",
         422, "truncated"),
        (b"element vertex 37", b"element vertex -3", 422, "malformed"),
        (b"property float f_rest_8\n", b"", 422, "bad_sh_count"),
        (b"property float f_rest_3\n", b"property float f_rest_30\n", 422, "bad_sh_count"),
        (b"property float rot_3\n", b"", 422, "missing_property"),
        (b"property float opacity", b"property uchar opacity", 422, "unsupported_format"),
        (b"property float x", b"property list uchar float x", 422, "unsupported_format"),
        (b"binary_little_endian", b"binary_middle_endian", 422, "unsupported_format"),
        (b"element vertex", b"element face 5\nproperty float q\nelement vertex", 422, "truncated"),
        (b"property float y\n", b"property float y\nproperty float y\n", 422, "malformed"),
        (b"format", b"formatting", 422, "malformed"),
    ],
)
def test_refuses_bad_headers(tmp_path: Path, old: bytes, new: bytes, status: int, code: str) -> None:
    path = tmp_path / "s.ply"
    save_scene(_scene(37, 3), path)
    _edit(path, old, new)
    with pytest.raises(ApiError) as caught:
        check_ply(path, 1000)
    assert (caught.value.status, caught.value.code) == (status, code), caught.value.message
    if code in ("truncated", "bad_sh_count", "missing_property"):  # the full reader agrees
        with pytest.raises(PlyError) as full:
            read_scene(path)
        assert full.value.code == code


def test_header_counts_are_checked_against_the_file_size(tmp_path: Path) -> None:
    path = tmp_path / "s.ply"
    save_scene(_scene(37, 3), path)
    path.write_bytes(path.read_bytes()[:-1])  # one byte short of 37 rows
    with pytest.raises(ApiError) as caught:
        check_ply(path, 1000)
    assert caught.value.code == "truncated"


def test_ascii_and_not_ply(tmp_path: Path) -> None:
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]  # fmt: skip
    rows = np.arange(2 * len(names), dtype=np.float32).reshape(2, -1)
    header = "ply\nformat ascii 1.0\nelement vertex 2\n" + "".join(f"property float {n}\n" for n in names)
    body = "\n".join(" ".join(str(v) for v in row) for row in rows) + "\n"
    path = tmp_path / "a.ply"
    path.write_text(header + "end_header\n" + body)
    assert check_ply(path, 10).count == 2
    path.write_text(header.replace("vertex 2", "vertex 2000") + "end_header\n" + body)
    with pytest.raises(ApiError, match="claims 2000"):
        check_ply(path, 10_000)
    for junk in (b"", b"PLY\n", b"ply\nformat ascii 1.0\n" + b"comment x\n" * 10_000):
        path.write_bytes(junk)
        with pytest.raises(ApiError) as caught:
            check_ply(path, 10)
        assert caught.value.code == "not_ply"


def test_empty_scene_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "empty.ply"
    save_scene(_scene(0, 0), path)
    with pytest.raises(ApiError) as caught:
        check_ply(path, 10)
    assert (caught.value.status, caught.value.code) == (422, "empty_scene")


def test_lenient_header_lines_are_accepted_as_the_reader_reads_them(tmp_path: Path) -> None:
    """A comment naming end_header, UTF-8 in a comment, trailing whitespace on the magic line: the upload is checked
    and the worker reads it, the body starting right after the end_header line."""
    path = tmp_path / "s.ply"
    save_scene(_scene(37, 3), path)
    data = path.read_bytes()
    path.write_bytes(
        data.replace(b"ply\n", b"ply \r\ncomment see end_header docs\ncomment Cr\xc3\xa9\xc3\xa9 par\n", 1)
        .replace(b"\nend_header\n", b"\nend_header \r\n", 1)
    )  # fmt: skip
    body = len(data) - data.index(b"end_header\n") - len(b"end_header\n")
    header = check_ply(path, 1000)
    assert (header.count, header.comments) == (37, ("see end_header docs", "Créé par"))
    assert header.size == path.stat().st_size - body
    scene, report = read_scene(path)
    assert report.count == 37 and torch.equal(scene.means, _scene(37, 3).means)
