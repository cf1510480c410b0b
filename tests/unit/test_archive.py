"""Round trips of the `.symgs` archive, its codec table, and a pinned encoding.

Pinned encoding: ``test_encoding_is_pinned`` fixes the SHA-256 of the archive of ``pinned_contents()``, and
``test_golden_archive_decodes`` fixes a file written by format version 1 that every later build must still read.
When the first fails:
  * if the golden still decodes, the writer's bytes changed without a format change (a new zstandard release,
    another compression level, a layout choice): confirm that nothing in the format was meant to change, then
    print the new hash with
      python -c "import hashlib; from tests.unit.test_archive import pinned_archive; \
print(hashlib.sha256(pinned_archive()).hexdigest())"
    and replace ``PINNED_SHA256``;
  * if the format changed on purpose, bump ``container.FORMAT_VERSION``, keep a reader for version 1 so the golden
    still decodes, and re-pin the hash as above.
"""

from __future__ import annotations

import base64
import hashlib
import json
import zlib

import numpy as np
import pytest
import torch

from symgs_core.cameras import COORDINATE_CONVENTION
from symgs_core.codec import (
    FORMAT_VERSION,
    MAGIC,
    SECTION_NAMES,
    ArchiveContents,
    ArchiveError,
    EncodedSection,
    archive_codec,
    archive_codec_names,
    decode_archive,
    encode_archive,
    expand_archive,
    expanded_count,
    read_header,
    register_archive_codec,
    register_section_codec,
)
from symgs_core.codec.floats import FLOAT32
from symgs_core.codec.masks import MASKS
from symgs_core.mirror import Plane, expand, expand_planes
from symgs_core.scene import SH_REST_COUNT, GaussianScene

# -0.0, the smallest subnormal, and the largest float32 magnitudes an archive holds (just below 1e30).
SPECIAL = torch.tensor([0x80000000, 0x00000001, 0x7149F2C9, 0xF149F2C9], dtype=torch.int64)


def random_contents(n: int, sh_degree: int, levels: int, seed: int = 0, special: bool = True) -> ArchiveContents:
    """Random stored set with signed zeros, subnormals and the largest magnitudes sprinkled in when ``special``."""
    g = torch.Generator().manual_seed(seed)

    def attr(*shape: int) -> torch.Tensor:
        values = torch.randn(*shape, generator=g) * 3.0
        if special and values.numel():
            flat = values.view(-1)
            picks = torch.randint(0, flat.numel(), (len(SPECIAL),), generator=g)
            flat.view(torch.int32)[picks] = SPECIAL.to(torch.int32)
        return values

    k = SH_REST_COUNT[sh_degree]
    stored = GaussianScene(attr(n, 3), attr(n, 4), attr(n, 3), attr(n), attr(n, 3), attr(n, k, 3))
    planes = [
        Plane.from_tensor(torch.randn(3, generator=g, dtype=torch.float64), float(i) - 0.5) for i in range(levels)
    ]
    bits = torch.rand(n, levels, generator=g) < 0.4
    meta = {"source": "random.ply", "input_count": n, "nested": {"list": [1, 2.5, None, True], "s": "\u00e9"}}
    return ArchiveContents(stored, planes, bits, meta)


def assert_same_bits(a: GaussianScene, b: GaussianScene) -> None:
    for name, value in a.tensors().items():
        other = b.tensors()[name]
        assert other.dtype == torch.float32 and other.shape == value.shape, name
        assert torch.equal(value.view(torch.int32), other.view(torch.int32)), name


@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
@pytest.mark.parametrize("levels", [0, 1, 3])
@pytest.mark.parametrize("n", [0, 1, 33])
def test_round_trip_is_bit_exact(sh_degree: int, levels: int, n: int) -> None:
    contents = random_contents(n, sh_degree, levels, seed=n * 16 + sh_degree * 4 + levels)
    back = decode_archive(encode_archive(contents))
    assert_same_bits(contents.stored, back.stored)
    assert back.planes == contents.planes  # floats survive the JSON header exactly
    assert back.bits.dtype == torch.bool and torch.equal(back.bits, contents.bits)
    assert back.meta == contents.meta


@pytest.mark.parametrize("levels", [0, 1, 2, 4])
def test_expanded_archive_equals_expanded_input(levels: int) -> None:
    contents = random_contents(40, 2, levels, seed=levels, special=False)
    expected = expand_planes(contents.stored, contents.planes, contents.bits)
    got = expand_archive(decode_archive(encode_archive(contents)))
    assert len(got) == expanded_count(contents.bits)
    assert_same_bits(expected, got)


def test_expanded_count_counts_every_copy() -> None:
    contents = random_contents(25, 0, 3, special=False)
    _, origin = expand(
        contents.stored,
        torch.tensor([p.normal for p in contents.planes], dtype=torch.float32),
        torch.tensor([p.offset for p in contents.planes], dtype=torch.float32),
        contents.bits,
    )
    assert expanded_count(contents.bits) == len(origin)
    assert expanded_count(torch.zeros(0, 3, dtype=torch.bool)) == 0


def test_baseline_archive_has_no_planes_and_an_empty_mask() -> None:
    contents = random_contents(50, 1, 0)
    data = encode_archive(contents)
    header = read_header(data)
    assert header["planes"] == []
    bits = {s["name"]: s for s in header["sections"]}["bits"]
    assert bits["raw_length"] == 0
    assert len(expand_archive(decode_archive(data))) == 50


def test_permuted_contents_expand_to_the_same_scene_reordered() -> None:
    contents = random_contents(30, 1, 2, special=False)
    perm = torch.randperm(30, generator=torch.Generator().manual_seed(3))
    moved = contents.permuted(perm)
    assert_same_bits(contents.stored.select(perm), moved.stored)
    assert torch.equal(moved.bits, contents.bits[perm])
    assert expanded_count(moved.bits) == expanded_count(contents.bits)


def test_header_records_format_and_scene_facts() -> None:
    contents = random_contents(7, 3, 2)
    data = encode_archive(contents)
    assert data[:8] == MAGIC
    assert int.from_bytes(data[8:12], "little") == FORMAT_VERSION
    header = read_header(data)
    assert header["count"] == 7 and header["sh_degree"] == 3 and header["codec"] == "lossless"
    assert header["coordinate_convention"] == COORDINATE_CONVENTION
    assert [s["name"] for s in header["sections"]] == list(SECTION_NAMES)
    raw = {s["name"]: s["raw_length"] for s in header["sections"]}
    assert raw["sh_rest"] == 7 * 15 * 3 * 4 and raw["quats"] == 7 * 4 * 4 and raw["opacities"] == 7 * 4
    header_len = int.from_bytes(data[12:16], "little")
    body = 20 + header_len
    for s in header["sections"]:
        payload = data[body + s["offset"] : body + s["offset"] + s["length"]]
        assert zlib.crc32(payload) == s["crc32"]
    last = header["sections"][-1]
    assert body + last["offset"] + last["length"] == len(data)


def test_lossless_archive_compresses_smooth_attributes() -> None:
    # Values on a coarse grid (as a quantising trainer or SOG leaves them) must cost far less than raw float32.
    n = 4000
    g = torch.Generator().manual_seed(0)
    grid = lambda *s: torch.randint(-8, 8, s, generator=g).float() / 4  # noqa: E731
    stored = GaussianScene(grid(n, 3), grid(n, 4), grid(n, 3), grid(n), grid(n, 3), grid(n, 3, 3))
    contents = ArchiveContents(stored, [], torch.zeros(n, 0, dtype=torch.bool))
    size = len(encode_archive(contents))
    assert size < 0.2 * n * 26 * 4, size  # 4 bits of entropy per value: 0.125 of float32 at best


@pytest.mark.parametrize("dtype", ["float32", "float16"])
def test_a_large_float_section_tries_its_layouts_in_parallel_to_the_same_bytes(dtype, monkeypatch) -> None:  # noqa: ANN001
    from symgs_core.codec import floats

    rng = np.random.default_rng(6)
    n = floats.PARALLEL_VALUES // 3 + 1
    # Columns that favour different layouts: a grid (rows), a smooth walk and noise (byte planes).
    values = np.stack([rng.integers(-8, 8, n) / 4, np.cumsum(rng.normal(0, 1e-3, n)), rng.normal(0, 1, n)], axis=1)
    values = values.astype(np.float32)
    codec = floats.FloatZstd(dtype)
    parallel = codec.encode(values)
    monkeypatch.setattr(floats, "PARALLEL_VALUES", values.size + 1)
    serial = codec.encode(values)
    assert parallel == serial
    sizes = [len(floats.zstd_compress(np.ascontiguousarray(floats._arrange(values.astype(dtype), layout)).tobytes(),
                                      codec.level)) for layout in floats.LAYOUTS]  # fmt: skip
    assert parallel.params["layout"] == floats.LAYOUTS[sizes.index(min(sizes))]
    back = codec.decode(parallel.payload, values.shape, parallel.params, parallel.raw_length)
    assert np.array_equal(back, values.astype(dtype).astype(np.float32))


def test_float16_codec_rounds_to_half_and_refuses_overflow() -> None:
    contents = random_contents(20, 1, 1, special=False)
    back = decode_archive(encode_archive(contents, codec="float16"))
    for name, value in contents.stored.tensors().items():
        assert torch.equal(back.stored.tensors()[name], value.half().float()), name
    assert torch.equal(back.bits, contents.bits)
    big = contents.stored.with_(means=contents.stored.means * 1e5)
    with pytest.raises(ValueError, match="float16 range"):
        encode_archive(ArchiveContents(big, contents.planes, contents.bits), codec="float16")


def test_encoder_rejects_what_it_cannot_store_exactly() -> None:
    contents = random_contents(5, 0, 1)
    with pytest.raises(ValueError, match="unknown archive codec 'zz'"):
        encode_archive(contents, codec="zz")
    with pytest.raises(ValueError, match="float32"):
        encode_archive(ArchiveContents(contents.stored.map(lambda t: t.double()), contents.planes, contents.bits))
    for meta in ({"t": (1, 2)}, {"x": float("nan")}, {1: "int key"}, {"o": object()}):
        with pytest.raises(ValueError, match="meta must be plain JSON"):
            encode_archive(ArchiveContents(contents.stored, contents.planes, contents.bits, meta))
    with pytest.raises(ValueError, match="shrink meta"):
        encode_archive(ArchiveContents(contents.stored, contents.planes, contents.bits, {"x": "a" * (1 << 20)}))
    with pytest.raises(ValueError, match=r"bool tensor of shape \(5, 1\)"):
        ArchiveContents(contents.stored, contents.planes, contents.bits.int())
    with pytest.raises(ValueError, match=r"bool tensor of shape \(5, 2\)"):
        ArchiveContents(contents.stored, contents.planes * 2, contents.bits)


class _RawFloats:
    """A toy section codec as a quantising codec would plug in: float32 bytes, uncompressed, scaled by a param."""

    name = "test-raw-scaled"
    kind = "float32"

    def encode(self, values: np.ndarray, *, classes: np.ndarray | None = None,
               neighbours: object = None) -> EncodedSection:  # fmt: skip
        return EncodedSection((values * 2).astype("<f4").tobytes(), values.nbytes, {"scale": 2.0})

    def check(self, shape: tuple[int, ...], params: dict, raw_length: int) -> None:
        if params != {"scale": 2.0} or raw_length != 4 * int(np.prod(shape)):
            raise ArchiveError("bad_header", f"{self.name}: params {params}, raw length {raw_length}")

    def decode(self, payload: bytes, shape: tuple[int, ...], params: dict, raw_length: int, *,
               classes: np.ndarray | None = None, neighbours: object = None) -> np.ndarray:  # fmt: skip
        if len(payload) != raw_length:
            raise ArchiveError("corrupt_section", f"{self.name}: {len(payload)} bytes, expected {raw_length}")
        return (np.frombuffer(payload, "<f4") / params["scale"]).astype(np.float32).reshape(shape)


def test_registered_codec_plugs_into_the_container() -> None:
    codecs = dict(archive_codec("lossless").sections) | {"sh_dc": _RawFloats()}
    register_archive_codec("test-raw-dc", codecs)
    assert "test-raw-dc" in archive_codec_names()
    contents = random_contents(12, 1, 2, special=False)
    data = encode_archive(contents, codec="test-raw-dc")
    sections = {s["name"]: s for s in read_header(data)["sections"]}
    assert sections["sh_dc"]["codec"] == "test-raw-scaled" and sections["sh_dc"]["length"] == 12 * 3 * 4
    assert_same_bits(contents.stored, decode_archive(data).stored)


def test_registry_refuses_inconsistent_codecs() -> None:
    with pytest.raises(ValueError, match="covers sections"):
        register_archive_codec("test-partial", {"means": FLOAT32})
    with pytest.raises(ValueError, match="cannot hold section 'bits'"):
        register_archive_codec("test-kinds", {name: FLOAT32 for name in SECTION_NAMES})
    with pytest.raises(ValueError, match="already taken"):
        impostor = _RawFloats()
        impostor.name = FLOAT32.name
        register_section_codec(impostor)
    assert archive_codec("lossless").sections["bits"] is MASKS


# --------------------------------------------------------------------------------------------- pinned encoding


def pinned_contents() -> ArchiveContents:
    """A small deterministic archive from exact binary fractions (no RNG, no transcendental functions)."""
    n = 24
    i = torch.arange(n, dtype=torch.float32)[:, None]

    def grid(cols: int, a: int, b: int, m: int) -> torch.Tensor:
        j = torch.arange(cols, dtype=torch.float32)[None, :]
        return ((i * a + j * b) % m - m // 2) / 8

    stored = GaussianScene(
        means=grid(3, 5, 3, 17),
        quats=grid(4, 3, 7, 11) + torch.tensor([1.0, 0.0, 0.0, 0.0]),
        scales=grid(3, 2, 5, 9) - 4,
        opacities=grid(1, 7, 0, 13)[:, 0],
        sh_dc=grid(3, 11, 1, 19),
        sh_rest=grid(9, 13, 2, 23).reshape(n, 3, 3) / 4,
    )
    planes = [Plane((1.0, 0.0, 0.0), 0.25), Plane((0.0, 0.6, 0.8), -0.5)]
    rows = torch.arange(n)
    bits = torch.stack([rows < 10, (rows % 6) < 2], dim=1)
    meta = {"source": "pinned", "input_count": 40, "sh_degree": 1}
    return ArchiveContents(stored, planes, bits, meta)


def pinned_archive() -> bytes:
    return encode_archive(pinned_contents())


PINNED_SHA256 = "47af5a40a22bb0e70aa56f2749a2e13bbab50aafdb99be59a50a293d7453f3ab"

# The archive of pinned_contents() as format version 1 wrote it (base64).
GOLDEN_V1 = (
    "iVNZTUdTDQoBAAAAqQQAAETqi317ImNvdW50IjoyNCwic2hfZGVncmVlIjoxLCJjb29yZGluYXRlX2NvbnZlbnRpb24iOiJvcGVuY3Y6IHdv"
    "cmxkLXRvLWNhbWVyYSBleHRyaW5zaWNzLCBjYW1lcmEgeCByaWdodCwgeSBkb3duLCB6IGZvcndhcmQiLCJjb2RlYyI6Imxvc3NsZXNzIiwi"
    "cGxhbmVzIjpbeyJub3JtYWwiOlsxLjAsMC4wLDAuMF0sIm9mZnNldCI6MC4yNX0seyJub3JtYWwiOlswLjAsMC42LDAuOF0sIm9mZnNldCI6"
    "LTAuNX1dLCJzZWN0aW9ucyI6W3sibmFtZSI6Im1lYW5zIiwiY29kZWMiOiJmMzItenN0ZCIsIm9mZnNldCI6MCwibGVuZ3RoIjo3MSwicmF3"
    "X2xlbmd0aCI6Mjg4LCJjcmMzMiI6MjgwNzg0NjY2MywicGFyYW1zIjp7ImxheW91dCI6ImNvbHVtbi1ieXRlcyJ9fSx7Im5hbWUiOiJxdWF0"
    "cyIsImNvZGVjIjoiZjMyLXpzdGQiLCJvZmZzZXQiOjcxLCJsZW5ndGgiOjgxLCJyYXdfbGVuZ3RoIjozODQsImNyYzMyIjo3MjA0NjkyNjQs"
    "InBhcmFtcyI6eyJsYXlvdXQiOiJjb2x1bW4tYnl0ZXMifX0seyJuYW1lIjoic2NhbGVzIiwiY29kZWMiOiJmMzItenN0ZCIsIm9mZnNldCI6"
    "MTUyLCJsZW5ndGgiOjQyLCJyYXdfbGVuZ3RoIjoyODgsImNyYzMyIjo2OTk5NjM1NSwicGFyYW1zIjp7ImxheW91dCI6ImNvbHVtbi1ieXRl"
    "cyJ9fSx7Im5hbWUiOiJvcGFjaXRpZXMiLCJjb2RlYyI6ImYzMi16c3RkIiwib2Zmc2V0IjoxOTQsImxlbmd0aCI6NDEsInJhd19sZW5ndGgi"
    "Ojk2LCJjcmMzMiI6NDA5MzEzODE5OCwicGFyYW1zIjp7ImxheW91dCI6ImJ5dGVzIn19LHsibmFtZSI6InNoX2RjIiwiY29kZWMiOiJmMzIt"
    "enN0ZCIsIm9mZnNldCI6MjM1LCJsZW5ndGgiOjgxLCJyYXdfbGVuZ3RoIjoyODgsImNyYzMyIjozMzk3MjYwNTgwLCJwYXJhbXMiOnsibGF5"
    "b3V0IjoiY29sdW1uLWJ5dGVzIn19LHsibmFtZSI6InNoX3Jlc3QiLCJjb2RlYyI6ImYzMi16c3RkIiwib2Zmc2V0IjozMTYsImxlbmd0aCI6"
    "ODksInJhd19sZW5ndGgiOjg2NCwiY3JjMzIiOjE5OTI4MTc4MDksInBhcmFtcyI6eyJsYXlvdXQiOiJjb2x1bW4tYnl0ZXMifX0seyJuYW1l"
    "IjoiYml0cyIsImNvZGVjIjoibWFzay16c3RkIiwib2Zmc2V0Ijo0MDUsImxlbmd0aCI6MTcsInJhd19sZW5ndGgiOjgsImNyYzMyIjozOTcw"
    "MjI0MTkwLCJwYXJhbXMiOnt9fV0sIm1ldGEiOnsic291cmNlIjoicGlubmVkIiwiaW5wdXRfY291bnQiOjQwLCJzaF9kZWdyZWUiOjF9fSi1"
    "L/1gIADtAQBEAgAAgMCAYCAAIGCAwIAAAEBAv74+P78APz4/v74/vj4/vz4/vwog8KJ66DkUUJ4WsQFEkIVDAarVBXXbKLUv/WCAAD0CAGQC"
    "AADAQJDAAGCg0CCAsIAgwADAIIA+Pz4/vgA+v74+P7++v74+P74OoFCDZRYPYMPMAx6D6kmeExQGf8PqxZXJ4D66o/oIKLUv/WAgAAUBAIAA"
    "AJCIgHBgjIR4aHhojITABQCEQwVQcE8Fs3RnQQEsKLUv/SBgBQEAkAAAQAAggADAwACAIABAvz6+PwUAgAEwnLMwTC5tAiwotS/9YCAAPQIA"
    "lAIAAJCAQCDAgACAwCBAgJAAYAAAYL8+vz++Pz6/P78/vr8+Pz6/P78/vgsgwKLTA0w4uUBwgBCuucjACUcMqAkYblhQoA0otS/9YGACfQIA"
    "RAIAALCAgCAggICwAJAAQGDAoACgwGBAAJAAsL49vj6+Pr0+AL4jqHHXuvU3sJM6EUwR6MJ9/f8/A0QeyCVpQpJpNiUNj+RJOoSoVZX5ASi1"
    "L/0gCEEAAAD/wAAAwwww"
)


def test_encoding_is_pinned() -> None:
    assert hashlib.sha256(pinned_archive()).hexdigest() == PINNED_SHA256


def test_golden_archive_decodes() -> None:
    data = base64.b64decode(GOLDEN_V1)
    expected = pinned_contents()
    back = decode_archive(data)
    assert_same_bits(expected.stored, back.stored)
    assert back.planes == expected.planes and torch.equal(back.bits, expected.bits) and back.meta == expected.meta
    assert json.loads(data[20 : 20 + int.from_bytes(data[12:16], "little")])["codec"] == "lossless"
