"""Uploads in PlayCanvas' compressed PLY layout (SuperSplat's export): read as scenes, checked as any PLY is."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from symgs_core.export import read_compressed_ply, write_compressed_ply
from symgs_core.ply import OPACITY_LOGIT_MAX, PlyError, load_scene, read_scene
from symgs_core.ply_header import CHUNK_RANGES, read_header
from tests.unit.test_export import scene_for_export

C0 = 0.28209479177387814


def test_an_upload_in_the_compressed_layout_reads_as_its_format_decodes_it(tmp_path: Path) -> None:
    scene = scene_for_export(n=600, degree=2)
    data = write_compressed_ply(scene)
    path = tmp_path / "upload.ply"
    path.write_bytes(data)
    read, report = read_scene(path)
    decoded = read_compressed_ply(data)
    assert all(torch.equal(a, b) for a, b in zip(read.tensors().values(), decoded.tensors().values(), strict=True))
    assert (report.layout, report.format, report.count, report.sh_degree) == ("compressed", "binary_little_endian",
                                                                              600, 2)  # fmt: skip
    assert report.ignored == [] and report.repairs == {}
    header = read_header(path)  # what the API checks an upload by, without numpy or torch
    assert (header.layout, header.count, header.sh_degree) == ("compressed", 600, 2)


def _earlier_writer(path: Path) -> None:
    """One chunk as writers before the chunks' colour ranges wrote it (12 ranges, colours in 0..1 as they are),
    the vertex properties in another order than the current writers'."""
    ranges = dict(zip(CHUNK_RANGES, [-1.0, -2.0, -3.0, 1.0, 2.0, 3.0, -5.0, -5.0, -5.0, -1.0, -1.0, -1.0], strict=True))
    order = ["packed_color", "packed_position", "packed_scale", "packed_rotation"]
    lines = ["ply", "format binary_little_endian 1.0", "element chunk 1"]
    lines += [f"property float {name}" for name in reversed(CHUNK_RANGES)]
    lines += ["element vertex 2"] + [f"property uint {name}" for name in order]
    chunk = np.array([[ranges[name] for name in reversed(CHUNK_RANGES)]], dtype="<f4")
    top = (2047 << 21) | (0 << 11) | 2047  # x and z at their maxima, y at its minimum
    half = (1023 << 21) | (511 << 11) | 1023
    rotation = (0 << 30) | (511 << 20) | (511 << 10) | 511  # w largest, the others near 0: the identity
    vertex = np.array([[(255 << 24) | (0 << 16) | (255 << 8) | 255, top, top, rotation],
                       [(0 << 24) | (255 << 16) | (0 << 8) | 0, 0, half, rotation]], dtype="<u4")  # fmt: skip
    path.write_bytes(("\n".join([*lines, "end_header"]) + "\n").encode() + chunk.tobytes() + vertex.tobytes())


def test_an_earlier_writers_chunks_without_colour_ranges_read_by_property_name(tmp_path: Path) -> None:
    path = tmp_path / "old.compressed.ply"
    _earlier_writer(path)
    scene = load_scene(path)
    assert torch.equal(scene.means, torch.tensor([[1.0, -2.0, 3.0], [-1.0, -2.0, -3.0]]))
    assert torch.allclose(scene.scales[0], torch.tensor([-1.0, -5.0, -1.0]))
    middle = [-5 + 4 * 1023 / 2047, -5 + 4 * 511 / 1023, -5 + 4 * 1023 / 2047]
    assert torch.allclose(scene.scales[1], torch.tensor(middle))
    assert torch.allclose(scene.sh_dc * C0 + 0.5, torch.tensor([[1.0, 0.0, 1.0], [0.0, 1.0, 0.0]]), atol=1e-6)
    assert scene.opacities[0] == pytest.approx(OPACITY_LOGIT_MAX) and scene.opacities[1] == -scene.opacities[0]
    assert torch.allclose(scene.quats, torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2), atol=2e-3)


def _header_swap(data: bytes, old: bytes, new: bytes) -> bytes:
    head, body = data.split(b"end_header\n", 1)
    assert old in head
    return head.replace(old, new, 1) + b"end_header\n" + body


@pytest.mark.parametrize(
    ("change", "code"),
    [
        (lambda d: d[:-1], "truncated"),
        (lambda d: d + b"\0", "trailing_data"),
        (lambda d: _header_swap(d, b"element chunk 2", b"element chunk 1"), "malformed"),
        (lambda d: _header_swap(d, b"uint packed_scale", b"float packed_scale"), "unsupported_format"),
        (lambda d: _header_swap(d, b"property float max_b", b"property float max_q"), "missing_property"),
        (lambda d: _header_swap(d, b"binary_little_endian", b"binary_big_endian"), "unsupported_format"),
        (lambda d: _header_swap(d, b"element sh 300", b"element sh 299"), "malformed"),
        (lambda d: _header_swap(d, b"property uchar f_rest_8", b"property uchar f_rest_9"), "bad_sh_count"),
    ],
)
def test_a_broken_compressed_upload_is_refused_with_a_code(tmp_path: Path, change, code: str) -> None:  # noqa: ANN001
    path = tmp_path / "broken.ply"
    path.write_bytes(change(write_compressed_ply(scene_for_export(n=300, degree=1))))
    with pytest.raises(PlyError) as err:
        read_header(path)
    assert err.value.code == code
    with pytest.raises(PlyError) as err:
        load_scene(path)
    assert err.value.code == code


def test_a_compressed_uploads_values_are_checked_as_any_plys(tmp_path: Path) -> None:
    data = bytearray(write_compressed_ply(scene_for_export(n=300, degree=0)))
    start = data.index(b"end_header\n") + len(b"end_header\n")
    data[start : start + 4] = np.array([math.nan], dtype="<f4").tobytes()  # the first chunk's min_x
    path = tmp_path / "nan.ply"
    path.write_bytes(bytes(data))
    with pytest.raises(PlyError) as err:
        load_scene(path)
    assert err.value.code == "non_finite"
    path.write_bytes(write_compressed_ply(scene_for_export(n=300, degree=0)))
    with pytest.raises(PlyError) as err:
        read_scene(path, max_gaussians=299)
    assert err.value.code == "too_many_gaussians"


def test_symgs_compresses_a_compressed_upload_and_names_its_layout(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    from service.cli import main
    from symgs_core.synthetic import synthetic_scene

    path = tmp_path / "supersplat.compressed.ply"
    path.write_bytes(write_compressed_ply(synthetic_scene("global", n=800, seed=2).scene))
    archive = tmp_path / "out.symgs"
    fast = ["--preset", "fast", "--resolution", "32", "--eval-resolution", "32", "--quiet"]
    assert main(["compress", str(path), "-o", str(archive), *fast]) == 0
    assert main(["decompress", str(archive), "-o", str(tmp_path / "back.ply")]) == 0
    assert len(load_scene(tmp_path / "back.ply")) == len(load_scene(path))
    capsys.readouterr()
    assert main(["info", str(path)]) == 0
    assert "binary_little_endian (PlayCanvas compressed)" in capsys.readouterr().out
