"""Exports for web viewers: `.spz` (v2, v3, v4) and PlayCanvas `.compressed.ply`, round trips through our readers
within each format's precision, the documented byte layout, and choice by extension."""

from __future__ import annotations

import dataclasses
import gzip
import math
import struct
import warnings

import numpy as np
import pytest
import torch

from symgs_core.export import (
    SpzError,
    compressed_ply_order,
    export_scene,
    import_scene,
    read_compressed_ply,
    read_spz,
    write_compressed_ply,
    write_spz,
)
from symgs_core.export.formats import EXPORTS, by_path
from symgs_core.export.glb import write_glb
from symgs_core.ply import OPACITY_LOGIT_MAX, OPACITY_LOGIT_MIN, PlyError, load_scene, ply_bytes
from symgs_core.scene import GaussianScene

C0 = 0.28209479177387814


def scene_for_export(n: int = 1000, degree: int = 3, seed: int = 0, spread: float = 3.0) -> GaussianScene:
    """Attributes inside every format's range: SH within +-1, DC within +-3, log-scales within [-10, 5]."""
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2 - 1
    return GaussianScene(
        means=(torch.rand(n, 3, generator=g) - 0.5) * 2 * spread,
        quats=torch.randn(n, 4, generator=g),
        scales=torch.rand(n, 3, generator=g) * 4 - 6,
        opacities=torch.randn(n, generator=g) * 2,
        sh_dc=torch.rand(n, 3, generator=g) * 4 - 2,
        sh_rest=(torch.rand(n, k, 3, generator=g) - 0.5) * 1.6,
    )


EDGE_SCENES = ("one", "identical", "flat_far")


def edge_scene(kind: str) -> GaussianScene:
    """Scenes a web platform's uploads hold that random ones do not: ``one`` Gaussian (SH degree 3); 20
    ``identical`` ones (degree 1); ``flat_far``, 300 on one plane 3000 units from the origin (degree 2) with
    unnormalised quaternions, negative w, a zero quaternion and saturated opacities."""
    if kind == "one":
        return scene_for_export(n=1, degree=3, seed=11)
    if kind == "identical":
        return scene_for_export(n=1, degree=1, seed=12).select(torch.zeros(20, dtype=torch.long))
    scene = scene_for_export(n=300, degree=2, seed=13, spread=1.0)
    quats = scene.quats * 1000.0
    quats[:, 0] = -quats[:, 0].abs()
    quats[7] = 0.0
    opacities = scene.opacities.clone()
    opacities[:4] = torch.tensor([40.0, -40.0, 1000.0, -1000.0])
    means = scene.means + torch.tensor([-3000.0, 0.0, 0.0])
    means[:, 2] = 0.25
    return scene.with_(means=means, quats=quats, opacities=opacities)


def same_rotation(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """|cos| of the half-angle between rotations [N]: 1 when equal (q and -q are one rotation)."""
    a, b = torch.nn.functional.normalize(a, dim=1), torch.nn.functional.normalize(b, dim=1)
    return (a * b).sum(dim=1).abs()


def assert_within_spz_precision(ours: GaussianScene, scene: GaussianScene, version: int) -> None:
    assert (ours.means - scene.means).abs().max() <= 0.5 / 4096 + 1e-6  # 12 fractional bits
    assert (ours.scales - scene.scales).abs().max() <= 0.5 / 16 + 1e-5
    assert (torch.sigmoid(ours.opacities) - torch.sigmoid(scene.opacities)).abs().max() <= 0.5 / 255 + 1e-5
    assert (ours.sh_dc - scene.sh_dc).abs().max() <= 0.5 / (0.15 * 255) + 1e-5
    # A 1/128 grid, then buckets of 8 (5 bits) for band 1 and of 16 (4 bits) above.
    assert (ours.sh_rest[:, :3] - scene.sh_rest[:, :3]).abs().max() <= 4.5 / 128 + 1e-5
    assert (ours.sh_rest[:, 3:] - scene.sh_rest[:, 3:]).abs().max() <= 8.5 / 128 + 1e-5
    # v2: x, y, z at 8 bits and w recomputed (coarse where w is small); v3/v4: smallest three, 9-bit magnitudes.
    assert same_rotation(ours.quats, scene.quats).min() >= (math.cos(0.1) if version == 2 else math.cos(0.003))


@pytest.mark.parametrize("version", [2, 3, 4])
def test_spz_round_trip_within_the_format_precision(version: int) -> None:
    scene = scene_for_export()
    data = write_spz(scene, version=version)
    assert_within_spz_precision(read_spz(data), scene, version)


def test_spz_layout_v3_is_one_gzip_stream_in_rub_axes_v4_a_plain_header() -> None:
    scene = scene_for_export(n=3, degree=0)
    body = gzip.decompress(write_spz(scene, version=3))
    magic, version, n, degree, frac, flags, _ = struct.unpack_from("<IIIBBBB", body)
    assert (magic, version, n, degree, flags) == (0x5053474E, 3, 3, 0, 0)
    extent = float((scene.means.max(0).values - scene.means.min(0).values).max())
    assert frac == 18 - math.floor(math.log2(extent))  # a step of at most 2^-18 of the extent
    fixed = np.frombuffer(body[16 : 16 + 9], dtype=np.uint8).reshape(3, 3).astype(np.int64)
    value = fixed[:, 0] | fixed[:, 1] << 8 | fixed[:, 2] << 16
    value = np.where(value & 0x800000, value - (1 << 24), value) / (1 << frac)
    expected = scene.means[0].numpy() * np.array([1, -1, -1])  # RUB: y and z flipped
    assert np.allclose(value, expected, atol=0.5 / (1 << frac) + 1e-7)
    v4 = write_spz(scene, version=4)
    assert v4[:4] == b"NGSP" and struct.unpack_from("<I", v4, 4)[0] == 4
    assert struct.unpack_from("<B", v4, 15)[0] == 5  # five non-empty streams: no SH at degree 0


@pytest.mark.parametrize("spread, bits", [(0.1, 21), (0.5, 19), (3.0, 16), (300.0, 12), (5000.0, 10)])
def test_spz_position_step_follows_the_scene_size(spread: float, bits: int) -> None:
    """A step of at most 2^-18 of the extent (the donut is about 0.2 across), never coarser than the reference
    writer's 2^-12 unless the scene's reach needs the integer bits."""
    scene = scene_for_export(n=200, degree=0, spread=spread)
    body = gzip.decompress(write_spz(scene, version=3))
    assert body[13] == bits
    error = (read_spz(write_spz(scene)).means - scene.means).abs().max()
    assert error <= 0.5 / (1 << bits) + 4 * spread * 2**-24  # the step, and float32 rounding at the reach


@pytest.mark.parametrize("version", [2, 3, 4])
def test_spz_round_trips_an_empty_scene(version: int) -> None:
    """The format holds no Gaussians (an archive of none decodes to such a scene): written and read back, its SH
    degree kept, rather than a numpy reshape error."""
    for degree in (0, 3):
        back = read_spz(write_spz(GaussianScene.empty(degree), version=version))
        assert (len(back), back.sh_degree) == (0, degree)


@pytest.mark.parametrize("n", [1, 5])
def test_spz_keeps_a_scene_of_no_extent_at_its_reach(n: int) -> None:
    """One Gaussian, or all at one point: no extent to take a step from, so the finest step the reach allows (the
    rows are all equal: it costs no bytes), not the reference's 2^-12 (an error of 1e-4 on a Gaussian a few
    hundredths across, 22 dB by `symgs evaluate` where the other exports keep it exactly)."""
    scene = scene_for_export(n=1, degree=0, seed=3)
    scene = scene.select(torch.zeros(n, dtype=torch.long))
    body = gzip.decompress(write_spz(scene, version=3))
    reach = float(scene.means.abs().max())
    assert body[13] == min(24, 22 - math.floor(math.log2(reach)))  # reach * 2^bits stays below 2^23
    assert (read_spz(write_spz(scene)).means - scene.means).abs().max() <= 0.5 / (1 << body[13]) + 1e-7


def test_spz_keeps_sh_at_8_bits() -> None:
    scene = scene_for_export(n=300, degree=3, seed=4)
    back = read_spz(write_spz(scene))
    assert (back.sh_rest - scene.sh_rest).abs().max() <= 0.5 / 128 + 1e-6
    coarse = read_spz(write_spz(scene, sh1_bits=5, sh_rest_bits=4))  # the reference tool's choice
    assert (coarse.sh_rest[:, 3:] - scene.sh_rest[:, 3:]).abs().max() > 4 / 128


def test_spz_gives_large_scenes_fewer_fractional_bits_instead_of_wrapping() -> None:
    scene = scene_for_export(n=50, degree=0, spread=5000.0)
    body = gzip.decompress(write_spz(scene, version=3))
    assert body[13] < 12
    assert (read_spz(write_spz(scene)).means - scene.means).abs().max() <= 0.5 / (1 << body[13]) + 1e-3


def test_spz_sh_flip_matches_a_reflection_of_y_and_z() -> None:
    """The stored SH must be the scene rotated 180 degrees about x: colours at (x, -y, -z) directions agree."""
    from symgs_core.sh import eval_sh

    scene = scene_for_export(n=1, degree=3)
    body = gzip.decompress(write_spz(scene, version=3, sh1_bits=8, sh_rest_bits=8))
    stored = (np.frombuffer(body[-45:], dtype=np.uint8).reshape(15, 3) - 128.0) / 128.0
    dirs = torch.nn.functional.normalize(torch.randn(64, 3, generator=torch.Generator().manual_seed(1)), dim=1)
    coeffs = torch.cat([torch.zeros(1, 3), scene.sh_rest[0]])
    flipped = torch.cat([torch.zeros(1, 3), torch.from_numpy(stored).float()])
    rub = dirs * torch.tensor([1.0, -1.0, -1.0])
    stored_colour = eval_sh(flipped[None].expand(64, -1, -1), rub)
    assert torch.allclose(stored_colour, eval_sh(coeffs[None].expand(64, -1, -1), dirs), atol=0.05)


@pytest.mark.parametrize("writer", [write_spz, write_compressed_ply, ply_bytes])
@pytest.mark.parametrize("attribute", ["means", "quats", "scales", "opacities", "sh_dc", "sh_rest"])
def test_writers_refuse_non_finite_attributes(writer, attribute: str, tmp_path) -> None:  # noqa: ANN001
    """As the SOG and glTF writers do: NaN used to be written as arbitrary bytes (a file that reads back, wrong or
    non-finite), an infinite position raised OverflowError; the PLY writer wrote NaN that its own reader refuses. A
    PLY may hold an infinite opacity logit, which its reader clamps, as real files hold them."""
    for value in (float("nan"), float("inf")):
        scene = scene_for_export(n=20, degree=1)
        scene.tensors()[attribute].view(-1)[5] = value
        if writer is ply_bytes and attribute == "opacities" and value == float("inf"):
            (tmp_path / "inf.ply").write_bytes(writer(scene))
            back = load_scene(tmp_path / "inf.ply")
            assert torch.isfinite(back.opacities).all() and back.opacities[5] == back.opacities.max()
            continue
        with pytest.raises(ValueError, match="finite attributes only"):
            writer(scene)


def test_compressed_ply_round_trip_within_chunk_precision() -> None:
    scene = scene_for_export(n=1000, degree=2)
    ours = read_compressed_ply(write_compressed_ply(scene))
    ref = scene.select(compressed_ply_order(scene))
    chunk = torch.arange(len(ref)) // 256
    for c in range(int(chunk.max()) + 1):
        part = chunk == c
        span = ref.means[part].max(0).values - ref.means[part].min(0).values
        bound = span / torch.tensor([2047.0, 1023.0, 2047.0]) * 0.5 + 1e-5
        assert ((ours.means[part] - ref.means[part]).abs() <= bound).all()
    assert (ours.scales - ref.scales).abs().max() <= 4.0 / 1023 * 0.5 + 1e-4
    assert (torch.sigmoid(ours.opacities) - torch.sigmoid(ref.opacities)).abs().max() <= 0.5 / 255 + 1e-5
    assert ((ours.sh_dc - ref.sh_dc) * C0).abs().max() <= 4 * C0 / 255 * 0.5 + 1e-5
    assert (ours.sh_rest - ref.sh_rest).abs().max() <= 8 / 256 + 1e-5
    assert same_rotation(ours.quats, ref.quats).min() >= math.cos(0.003)


def test_compressed_ply_chunks_hold_whole_clusters() -> None:
    """27 tight clusters of 256 on a 3 x 3 x 3 grid, the middle one across every top-level cell of the Morton curve
    (where PlayCanvas' order mixes clusters into one chunk): each chunk holds one cluster, so each position keeps
    its cluster's precision; a smaller cluster of 100 in a corner is the last, short chunk."""
    g = torch.Generator().manual_seed(3)
    grid = torch.stack(torch.meshgrid(*[torch.arange(3.0)] * 3, indexing="ij"), -1).reshape(27, 3)
    label = torch.arange(27).repeat_interleave(256)[torch.randperm(27 * 256, generator=g)]
    scene = scene_for_export(n=27 * 256 + 100, degree=0)
    scene.means[: 27 * 256] = grid[label] + torch.randn(27 * 256, 3, generator=g) * 0.01
    scene.means[27 * 256 :] = 4 + torch.randn(100, 3, generator=g) * 0.01
    order = compressed_ply_order(scene)
    assert torch.equal(order.sort().values, torch.arange(len(scene)))
    assert (order[: 27 * 256] < 27 * 256).all()
    chunks = label[order[: 27 * 256]].reshape(27, 256)
    assert (chunks == chunks[:, :1]).all() and len(chunks[:, 0].unique()) == 27
    ours, ref = read_compressed_ply(write_compressed_ply(scene)), scene.select(order)
    assert (ours.means - ref.means)[: 27 * 256].abs().max() <= 0.1 / 1023


def test_compressed_ply_has_the_playcanvas_header() -> None:
    data = write_compressed_ply(scene_for_export(n=300, degree=1))
    head = data[: data.index(b"end_header\n")].decode()
    assert "element chunk 2" in head and "element vertex 300" in head and "element sh 300" in head
    assert head.count("property uint packed_") == 4 and head.count("property uchar f_rest_") == 9
    with pytest.raises(PlyError) as err:
        read_compressed_ply(data[:-1])
    assert err.value.code == "truncated"


def test_export_chooses_the_format_by_extension(tmp_path) -> None:  # noqa: ANN001
    scene = scene_for_export(n=200, degree=1)
    assert by_path("a/b.compressed.ply").name == "compressed_ply" and by_path("x.PLY").name == "ply"
    for name in ("s.ply", "s.spz", "s.compressed.ply"):
        export_scene(scene, tmp_path / name)
        back = import_scene(tmp_path / name)
        assert len(back) == 200 and back.sh_degree == 1
    assert gzip.decompress((tmp_path / "s.spz").read_bytes())[4] == 3  # version 3 by default
    export_scene(scene, tmp_path / "v4.spz", version=4)
    assert (tmp_path / "v4.spz").read_bytes()[:4] == b"NGSP"
    with pytest.raises(ValueError, match="unsupported export format"):
        export_scene(scene, tmp_path / "s.splat")


def test_readers_refuse_what_is_not_their_format() -> None:
    with pytest.raises(SpzError):
        read_spz(b"not an spz file at all")
    with pytest.raises(SpzError):
        read_spz(gzip.compress(b"\x00" * 40))
    with pytest.raises(PlyError):
        read_compressed_ply(b"ply\nformat ascii 1.0\nend_header\n")


def test_fast_ply_writer_matches_the_reference_writer(tmp_path) -> None:  # noqa: ANN001
    from plyfile import PlyData, PlyElement

    from symgs_core.ply import graphdeco_properties, load_scene, ply_bytes

    scene = scene_for_export(n=300, degree=2)
    flat = ply_bytes(scene)
    names = graphdeco_properties(scene.sh_degree)
    rows = np.frombuffer(flat[flat.index(b"end_header\n") + 11 :], dtype=[(n, "<f4") for n in names])
    reference_ply = PlyData([PlyElement.describe(rows.copy(), "vertex")], text=False, byte_order="<")
    reference_ply.write(str(tmp_path / "reference.ply"))
    reference, ours = (tmp_path / "reference.ply").read_bytes(), ply_bytes(scene)
    assert ours[ours.index(b"end_header\n") :] == reference[reference.index(b"end_header\n") :]
    (tmp_path / "ours.ply").write_bytes(ours)
    back = load_scene(tmp_path / "ours.ply")
    assert all(torch.equal(back.tensors()[k], v) for k, v in scene.tensors().items() if k != "quats")


def test_decompress_command_writes_the_format_the_extension_names(tmp_path, capsys) -> None:  # noqa: ANN001
    from service.cli import main
    from symgs_core.codec import ArchiveContents, encode_archive

    scene = scene_for_export(n=300, degree=1)
    archive = tmp_path / "scene.symgs"
    archive.write_bytes(encode_archive(ArchiveContents(scene, [], torch.zeros(300, 0, dtype=torch.bool), {})))
    for name, read in (("out.spz", read_spz), ("out.compressed.ply", read_compressed_ply)):
        assert main(["decompress", str(archive), "-o", str(tmp_path / name)]) == 0
        assert len(read((tmp_path / name).read_bytes())) == 300
    assert main(["decompress", str(archive), "-o", str(tmp_path / "v4.spz"), "--spz-version", "4"]) == 0
    assert (tmp_path / "v4.spz").read_bytes()[:4] == b"NGSP"
    assert main(["decompress", str(archive), "-o", str(tmp_path / "out.ply")]) == 0
    assert import_scene(tmp_path / "out.ply").means.equal(scene.means)
    assert main(["decompress", str(archive), "-o", str(tmp_path / "out.splat")]) == 2
    assert "unsupported export format" in capsys.readouterr().err


def test_a_scene_in_tiny_units_is_refused_by_spz_and_kept_by_the_compressed_ply(tmp_path, capsys) -> None:  # noqa: ANN001
    """At 1e-9 units no step of 24 bits resolves the scene: `.spz` refuses it as it does one beyond its reach (it
    wrote every Gaussian at one point); the compressed PLY's float32 chunk bounds hold it (it kept 6 points)."""
    from service.cli import main
    from symgs_core.codec import ArchiveContents, encode_archive

    scene = scene_for_export(n=600, degree=1)
    tiny = GaussianScene(
        means=scene.means * 1e-9, quats=scene.quats, scales=scene.scales + math.log(1e-9),
        opacities=scene.opacities, sh_dc=scene.sh_dc, sh_rest=scene.sh_rest,
    )  # fmt: skip
    with pytest.raises(ValueError, match="spz: positions spanning .* do not fit its 24-bit fixed point"):
        write_spz(tiny)
    assert len(read_spz(write_spz(scene))) == 600  # a scene in ordinary units still exports
    back = read_compressed_ply(write_compressed_ply(tiny))
    ref = tiny.select(compressed_ply_order(tiny))
    assert len(torch.unique(back.means, dim=0)) == 600
    assert (back.means - ref.means).abs().max() <= 6e-9 / 1023  # within a chunk's box at 10 bits, at worst
    archive = tmp_path / "tiny.symgs"
    archive.write_bytes(encode_archive(ArchiveContents(tiny, [], torch.zeros(600, 0, dtype=torch.bool), {})))
    assert main(["decompress", str(archive), "-o", str(tmp_path / "t.spz")]) == 2
    assert "do not fit its 24-bit fixed point" in capsys.readouterr().err
    assert main(["decompress", str(archive), "-o", str(tmp_path / "t.compressed.ply")]) == 0


@pytest.mark.parametrize("version", [2, 3, 4])
def test_spz_writes_a_zero_quaternion_as_the_identity(version: int) -> None:
    """The PLY reader's repair, and what the other exports write: v3 and v4 wrote (0, 0, 0, 0) as the smallest three
    with x the largest, which reads back as a half turn about x (by splat-transform too): for an axis-aligned
    Gaussian the same covariance, but not the rotation the scene and every other export hold."""
    scene = scene_for_export(n=20, degree=0)
    quats = scene.quats.clone()
    quats[4] = 0.0
    back = read_spz(write_spz(scene.with_(quats=quats), version=version))
    assert same_rotation(back.quats[4:5], torch.tensor([[1.0, 0.0, 0.0, 0.0]])).item() >= math.cos(0.01)
    kept = torch.arange(20) != 4
    assert same_rotation(back.quats[kept], scene.quats[kept]).min() >= math.cos(0.1 if version == 2 else 0.003)


@pytest.mark.parametrize("extension", [fmt.extension for fmt in EXPORTS])
def test_every_export_takes_saturated_opacities_and_huge_scales_without_a_warning(extension: str, tmp_path) -> None:  # noqa: ANN001
    """Logits of +-1000 are opacities of 1 and 0: written as such and read back as the readers' clamp, with no
    overflow warning on the way (the SOG and glTF writers took exp(1000), which warns, and fails under -W error);
    a log-scale whose exp overflows is the glTF writer's refusal, not a warning before it."""
    scene = scene_for_export(n=300, degree=1)
    opacities = scene.opacities.clamp(-3.0, 3.0)  # inside every reader's clamp
    opacities[:2] = torch.tensor([1000.0, -1000.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        export_scene(scene.with_(opacities=opacities), tmp_path / f"s{extension}")
        if extension == ".glb":
            with pytest.raises(ValueError, match="SCALE overflows float32"):
                write_glb(scene.with_(scales=scene.scales.index_fill(0, torch.tensor([3]), 1000.0)))
    back = import_scene(tmp_path / f"s{extension}")
    extremes = torch.sort(back.opacities).values[[0, -1]]  # SOG and the compressed PLY store their own order
    assert extremes.tolist() == [OPACITY_LOGIT_MIN, OPACITY_LOGIT_MAX]


@pytest.mark.parametrize(("n", "across", "refused"), [(2000, 2e-3, True), (2000, 5e-3, True), (20000, 1e-2, True),
                                                    (2000, 1e-2, False), (20000, 2e-2, False)])
def test_spz_refuses_a_scene_whose_gaussians_are_below_its_smallest_scale(n: int, across: float, refused: bool) -> None:
    """`.spz` stores log-scales from -10 up. Generated objects shrunk until their Gaussians reach that floor were
    written larger and rounder than they are, and rendered at 21, 33 and 32 dB against their own renders; with
    thin axes clipped but each Gaussian's largest well above the floor they render at 48.6 and 44.0 dB."""
    from symgs_core.synthetic import synthetic_scene

    scene = synthetic_scene("global", n=n, seed=0, sh_degree=1).scene
    factor = across / float((scene.means.amax(dim=0) - scene.means.amin(dim=0)).max())
    small = dataclasses.replace(scene, means=scene.means * factor, scales=scene.scales + math.log(factor))
    assert (small.scales.amin(dim=1) < -10).float().mean() > 0.3  # thin axes are clipped in every case
    if refused:
        with pytest.raises(ValueError, match=r"spz: \d+% of the Gaussians are under 3 times its smallest scale"):
            write_spz(small)
    else:
        back = read_spz(write_spz(small))
        assert torch.allclose(back.scales.amax(dim=1), small.scales.amax(dim=1), atol=1 / 16)
