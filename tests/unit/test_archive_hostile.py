"""Corrupt, truncated and hostile `.symgs` files: the reader answers ArchiveError with the right code, quickly.

Hostile headers are re-framed with a valid CRC (the layout is rebuilt here from the documented prefix), so each
case reaches the validation it targets instead of stopping at the checksum.
"""

from __future__ import annotations

import copy
import json
import math
import struct
import time
import tracemalloc
import zlib
from collections.abc import Callable
from datetime import timedelta
from typing import Any

import numpy as np
import pytest
import torch
import zstandard
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from symgs_core.codec import (
    MAGIC,
    ArchiveContents,
    ArchiveError,
    DecodeLimits,
    decode_archive,
    encode_archive,
    expand_archive,
)
from symgs_core.codec.archive import decode_memory
from symgs_core.codec.container import FORMAT_VERSION
from symgs_core.codec.entropy import encode_table
from symgs_core.codec.floats import FLOAT32
from symgs_core.codec.masks import write_varints
from symgs_core.mirror import Plane
from tests.tools.fuzz_archive import claiming
from tests.unit.test_archive import random_contents

QUICK = settings(max_examples=200, deadline=timedelta(seconds=2), suppress_health_check=[HealthCheck.too_slow])


def small_archive() -> bytes:
    return encode_archive(random_contents(5, 1, 2, seed=11))


DATA = small_archive()


def split(data: bytes) -> tuple[dict[str, Any], bytes]:
    header_len = int.from_bytes(data[12:16], "little")
    text = zstandard.ZstdDecompressor().decompress(data[20 : 20 + header_len])
    return json.loads(text), data[20 + header_len :]


def frame(text: bytes, body: bytes, version: int = FORMAT_VERSION) -> bytes:
    """A frame of header ``text`` (versions 2 and 3: zstd-compressed, as the writer does; 1: plain)."""
    packed = zstandard.ZstdCompressor(level=19).compress(text) if version >= 2 else text
    return MAGIC + struct.pack("<III", version, len(packed), zlib.crc32(packed)) + packed + body


def reframe(header: dict[str, Any], body: bytes) -> bytes:
    # Compact separators as the writer uses; NaN and Infinity come out as the literals a strict reader refuses.
    return frame(json.dumps(header, separators=(",", ":")).encode(), body)


def with_payload(data: bytes, name: str, payload: bytes, raw_length: int | None = None) -> bytes:
    """``data`` with section ``name`` replaced by ``payload`` and the table (offsets, CRCs) made consistent."""
    header, body = split(data)
    payloads = []
    for s in header["sections"]:
        payloads.append(payload if s["name"] == name else body[s["offset"] : s["offset"] + s["length"]])
    offset = 0
    for s, p in zip(header["sections"], payloads, strict=True):
        s.update(offset=offset, length=len(p), crc32=zlib.crc32(p))
        if s["name"] == name and raw_length is not None:
            s["raw_length"] = raw_length
        offset += len(p)
    return reframe(header, b"".join(payloads))


def code_of(data: bytes, limits: DecodeLimits | None = None) -> str:
    with pytest.raises(ArchiveError) as info:
        decode_archive(data, limits=limits or DecodeLimits())
    return info.value.code


def test_helpers_rebuild_a_valid_archive() -> None:
    header, body = split(DATA)
    assert reframe(header, body) == DATA
    means = body[: header["sections"][0]["length"]]
    assert with_payload(DATA, "means", means) == DATA


def test_every_truncation_is_reported_as_truncated() -> None:
    for length in range(len(DATA)):
        assert code_of(DATA[:length]) == "truncated", length


def test_every_single_bit_flip_is_caught() -> None:
    header_end = 20 + int.from_bytes(DATA[12:16], "little")
    for byte in range(len(DATA)):
        if byte < 8:
            expected = {"bad_magic"}
        elif byte < 12:  # or another version this build reads, whose header this one is not
            expected = {"unsupported_version", "bad_header"}
        elif byte < 16:  # header length: too long for the limit or the file, or a different CRC span
            expected = {"limit_exceeded", "truncated", "bad_checksum"}
        else:  # the header CRC, the header, or a section payload
            expected = {"bad_checksum"}
        for bit in range(8):
            flipped = bytearray(DATA)
            flipped[byte] ^= 1 << bit
            if byte == 8 and flipped[8] == 4:  # version 6 less its bit 1: 4 reads one without new fields alike
                read, written = decode_archive(bytes(flipped)), decode_archive(DATA)
                pairs = zip(read.stored.tensors().values(), written.stored.tensors().values())
                assert all(torch.equal(a, b) for a, b in pairs) and torch.equal(read.bits, written.bits)
                continue
            assert code_of(bytes(flipped)) in expected, (byte, bit, header_end)


def test_appended_bytes_are_trailing_data() -> None:
    assert code_of(DATA + b"\0") == "trailing_data"


@QUICK
@given(st.binary(max_size=4096))
def test_random_bytes_are_refused(data: bytes) -> None:
    code_of(data)


@QUICK
@given(st.binary(max_size=2048), st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1))
def test_random_bytes_behind_a_valid_magic_are_refused(tail: bytes, length: int, crc: int) -> None:
    code_of(MAGIC + struct.pack("<III", 1, length, crc) + tail)


@QUICK
@given(st.binary(max_size=2048), st.binary(max_size=512))
def test_random_headers_with_valid_checksums_are_refused(text: bytes, body: bytes) -> None:
    code_of(frame(text, body))


@QUICK
@given(
    st.recursive(
        st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
        lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
        max_leaves=30,
    )
)
def test_random_json_headers_are_refused(value: Any) -> None:
    _, body = split(DATA)
    code_of(frame(json.dumps(value).encode(), body))


@QUICK
@given(st.data())
def test_overwritten_spans_are_refused(data: st.DataObject) -> None:
    start = data.draw(st.integers(0, len(DATA) - 1))
    junk = data.draw(st.binary(min_size=1, max_size=64))
    corrupted = DATA[:start] + junk + DATA[start + len(junk) :]
    if corrupted != DATA:
        code_of(corrupted)


def _leaves(obj: Any, path: tuple = ()) -> list[tuple]:
    if isinstance(obj, dict):
        return [path] + [p for k, v in obj.items() for p in _leaves(v, (*path, k))]
    if isinstance(obj, list):
        return [path] + [p for i, v in enumerate(obj) for p in _leaves(v, (*path, i))]
    return [path]


HOSTILE_VALUES = st.one_of(
    st.integers(-(2**70), 2**70),
    st.sampled_from([0, -1, 1, 2**31, 2**32, 2**63, 10**30]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20),
    st.none(),
    st.booleans(),
    st.lists(st.integers(-5, 5), max_size=4),
    st.dictionaries(st.text(max_size=5), st.integers(), max_size=3),
)


QUANTIZED = encode_archive(random_contents(40, 2, 2, seed=5, special=False), codec="quantized")


def assert_finite(contents: ArchiveContents) -> None:
    """What every accepted archive decodes to: finite values, before and after expansion through the levels."""
    for scene in (contents.stored, expand_archive(contents)):
        for name, value in scene.tensors().items():
            assert torch.isfinite(value).all(), name


@QUICK
@given(st.data(), st.sampled_from([DATA, QUANTIZED]))
def test_any_header_field_replaced_by_a_hostile_value_is_refused_or_harmless(
    data: st.DataObject, archive: bytes
) -> None:
    header, body = split(archive)
    path = data.draw(st.sampled_from([p for p in _leaves(header) if p]))
    value = data.draw(HOSTILE_VALUES)
    hostile = copy.deepcopy(header)
    target = hostile
    for key in path[:-1]:
        target = target[key]
    original = target[path[-1]]
    target[path[-1]] = value
    try:
        back = decode_archive(reframe(hostile, body))
    except ArchiveError:
        return
    # Accepted only where any value of the right type is legitimate, or where nothing changed.
    free = path[0] in ("meta", "codec") or path[-1] == "layout" or (path[0] == "planes" and path[-1] == "offset")
    # Quantiser parameters may take other values, as long as what they decode to is finite.
    free = free or (path[0] == "sections" and "params" in path and path[-1] != "morton")
    # A normal component may change as long as the normal stays unit length (``Plane``'s tolerance).
    free = free or (path[0] == "planes" and "normal" in path
                    and abs(math.hypot(*hostile["planes"][path[1]]["normal"]) - 1.0) < 1e-4)  # fmt: skip
    assert free or value == original, (path, value)
    assert back.meta == hostile["meta"]
    assert_finite(back)


def _set(path: tuple, value: Any) -> Callable[[dict], None]:
    def apply(header: dict) -> None:
        target = header
        for key in path[:-1]:
            target = target[key]
        target[path[-1]] = value

    return apply


def _section(name: str, key: str, value: Any) -> Callable[[dict], None]:
    def apply(header: dict) -> None:
        next(s for s in header["sections"] if s["name"] == name)[key] = value

    return apply


def _shift(name: str, delta: int) -> Callable[[dict], None]:
    def apply(header: dict) -> None:
        next(s for s in header["sections"] if s["name"] == name)["offset"] += delta

    return apply


HOSTILE_HEADERS: list[tuple[str, Callable[[dict], None], str]] = [
    ("huge count", _set(("count",), 10**12), "limit_exceeded"),
    ("negative count", _set(("count",), -1), "bad_header"),
    ("bool count", _set(("count",), True), "bad_header"),
    ("string count", _set(("count",), "5"), "bad_header"),
    ("count off by one", _set(("count",), 6), "bad_header"),
    ("float count", _set(("count",), 5.0), "bad_header"),
    ("sh degree 4", _set(("sh_degree",), 4), "bad_header"),
    ("sh degree mismatch", _set(("sh_degree",), 2), "bad_header"),
    ("NaN normal", _set(("planes", 0, "normal", 0), float("nan")), "bad_header"),
    ("infinite offset", _set(("planes", 1, "offset"), float("inf")), "bad_header"),
    ("non-unit normal", _set(("planes", 0, "normal"), [1.0, 1.0, 0.0]), "bad_header"),
    ("short normal", _set(("planes", 0, "normal"), [1.0, 0.0]), "bad_header"),
    ("string normal", _set(("planes", 0, "normal"), "up"), "bad_header"),
    ("plane extra key", _set(("planes", 0, "d"), 1), "bad_header"),
    ("too many planes", _set(("planes",), [{"normal": [1.0, 0.0, 0.0], "offset": 0.0}] * 33), "limit_exceeded"),
    ("planes not a list", _set(("planes",), {}), "bad_header"),
    ("negative offset", _section("quats", "offset", -1), "bad_header"),
    ("overlapping sections", _shift("scales", -1), "bad_header"),
    ("gap between sections", _shift("scales", 1), "bad_header"),
    ("absurd length", _section("means", "length", 2**62), "limit_exceeded"),
    ("absurd raw length", _section("sh_rest", "raw_length", 2**40), "limit_exceeded"),
    ("wrong raw length", _section("sh_rest", "raw_length", 4), "bad_header"),
    ("mask raw length beyond any stream", _section("bits", "raw_length", 10**6), "bad_header"),
    ("last section past the end", _section("classes", "length", 10**6), "truncated"),
    ("unknown codec", _section("means", "codec", "lz-magic"), "unsupported_codec"),
    ("mask codec for an attribute", _section("means", "codec", "mask-zstd"), "bad_header"),
    ("float codec for the masks", _section("bits", "codec", "f32-zstd"), "bad_header"),
    ("unknown layout", _section("means", "params", {"layout": "diagonal"}), "bad_header"),
    ("missing layout", _section("means", "params", {}), "bad_header"),
    ("extra param", _section("bits", "params", {"x": 1}), "bad_header"),
    ("params not an object", _section("bits", "params", []), "bad_header"),
    ("crc out of range", _section("means", "crc32", 2**40), "bad_header"),
    ("negative crc", _section("means", "crc32", -1), "bad_header"),
    ("wrong crc", _section("means", "crc32", 12345), "bad_checksum"),
    ("section extra key", _section("means", "note", "x"), "bad_header"),
    ("missing section", lambda h: h["sections"].pop(2), "bad_header"),
    ("duplicated section", lambda h: h["sections"].insert(0, dict(h["sections"][0])), "bad_header"),
    ("reordered sections", lambda h: h["sections"].reverse(), "bad_header"),
    ("sections not a list", _set(("sections",), {"means": 0}), "bad_header"),
    ("section not an object", lambda h: h["sections"].__setitem__(0, "means"), "bad_header"),
    ("meta not an object", _set(("meta",), [1, 2]), "bad_header"),
    ("empty codec name", _set(("codec",), ""), "bad_header"),
    ("other coordinate convention", _set(("coordinate_convention",), "opengl"), "bad_header"),
    ("extra top-level key", _set(("extra",), 1), "bad_header"),
    ("missing top-level key", lambda h: h.pop("planes"), "bad_header"),
]


@pytest.mark.parametrize("mutate,expected", [c[1:] for c in HOSTILE_HEADERS], ids=[c[0] for c in HOSTILE_HEADERS])
def test_hostile_header_fields(mutate: Callable[[dict], None], expected: str) -> None:
    header, body = split(DATA)
    mutate(header)
    assert code_of(reframe(header, body)) == expected


@pytest.mark.parametrize(
    "text",
    [
        b"not json",
        b"[1, 2, 3]",
        b"[" * 200_000 + b"]" * 200_000,
        b'{"count": 1, "count": 2}',
        b"\xff\xfe{}",
        b'{"count": NaN}',
        b'{"count": ' + b"9" * 5000 + b"}",
        b"",
    ],
    ids=["not json", "array", "deep nesting", "duplicate key", "not utf-8", "NaN", "huge integer", "empty"],
)
def test_header_that_is_not_a_strict_json_object(text: bytes) -> None:
    _, body = split(DATA)
    assert code_of(frame(text, body)) == "bad_header"


def test_unsupported_version_and_header_size_limit() -> None:
    header, body = split(DATA)
    assert code_of(frame(json.dumps(header).encode(), body, version=FORMAT_VERSION + 1)) == "unsupported_version"
    assert code_of(DATA, DecodeLimits(max_header_bytes=100)) == "limit_exceeded"
    assert code_of(DATA, DecodeLimits(max_gaussians=4)) == "limit_exceeded"
    assert code_of(DATA, DecodeLimits(max_levels=1)) == "limit_exceeded"
    assert code_of(DATA, DecodeLimits(max_section_bytes=50)) == "limit_exceeded"
    decode_archive(DATA, limits=DecodeLimits(max_gaussians=5, max_levels=2, max_expanded_gaussians=20))


def test_expansion_beyond_the_limit_is_refused_before_expanding() -> None:
    contents = random_contents(3, 0, 30, seed=2)
    contents.bits[:] = True  # 3 x 2^30 Gaussians from a file of a few hundred bytes
    data = encode_archive(contents)
    assert len(data) < 8192
    assert code_of(data) == "limit_exceeded"


def _params(name: str, **changes: Any) -> bytes:
    header, body = split(QUANTIZED)
    next(s for s in header["sections"] if s["name"] == name)["params"].update(changes)
    return reframe(header, body)


@pytest.mark.parametrize(
    "archive",
    [
        _params("means", step=1e300), _params("means", step=-1.0), _params("means", origin=[0.0, 1e35, 0.0]),
        _params("scales", step=1e25), _params("scales", origin=-1e31), _params("sh_dc", step=float("inf")),
        _params("sh_rest", steps=[1e-3, 1e26]), _params("quats", step=0.0),
    ],
    ids=["huge position step", "negative step", "origin beyond 1e30", "scale grid beyond 1e30", "scale origin",
         "infinite DC step", "huge SH band step", "zero rotation step"],
)  # fmt: skip
def test_quantiser_parameters_that_would_decode_beyond_range_are_refused(archive: bytes) -> None:
    assert code_of(archive) == "bad_header"


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf"), 1e35, -3e38])
def test_float_sections_that_decode_to_non_finite_or_absurd_values_are_refused(value: float) -> None:
    contents = random_contents(5, 1, 2, seed=11, special=False)
    means = contents.stored.means.numpy().copy()
    means[3, 1] = value
    coded = FLOAT32.encode(means)
    header, body = split(with_payload(DATA, "means", coded.payload, coded.raw_length))
    header["sections"][0]["params"] = coded.params
    assert code_of(reframe(header, body)) == "corrupt_section"
    stored = contents.stored.with_(means=torch.from_numpy(means))
    with pytest.raises(ValueError, match="finite and within"):
        encode_archive(ArchiveContents(stored, contents.planes, contents.bits))


def test_plane_offsets_beyond_range_are_refused() -> None:
    header, body = split(DATA)
    header["planes"][0]["offset"] = 2e30
    assert code_of(reframe(header, body)) == "bad_header"
    contents = random_contents(5, 1, 2, seed=11, special=False)
    far = [contents.planes[0], Plane(contents.planes[1].normal, -2e30)]
    with pytest.raises(ValueError, match="plane offsets"):
        encode_archive(ArchiveContents(contents.stored, far, contents.bits))


def _zstd(raw: bytes, **kwargs: Any) -> bytes:
    return zstandard.ZstdCompressor(level=3, **kwargs).compress(raw)


@pytest.mark.parametrize(
    "name,payload,raw_length",
    [
        ("means", b"\x00" * 40, None),  # not zstd
        ("means", _zstd(b"\0" * (1 << 24)), None),  # a bomb that declares 16 MiB where the header says 60 bytes
        ("means", _zstd(b"\0" * 60, write_content_size=False), None),  # no declared size
        ("means", _zstd(b"\0" * 60) + _zstd(b"\0" * 4), None),  # a second frame
        ("means", _zstd(b"\0" * 60)[:-3] + b"\0\0\0", None),  # damaged block, right declared size
        ("bits", _zstd(bytes([0, 0xFF])), 2),  # packed level with padding bits set, one level missing
        ("bits", _zstd(bytes([2, 0, 0, 0])), 4),  # unknown block mode
        ("bits", _zstd(bytes([1]) + write_varints([2, 2, 2]) + bytes([0, 0])), 6),  # runs sum to 4, not 5
        ("bits", _zstd(bytes([1]) + write_varints([3, 1, 0, 4]) + bytes([0, 0])), 7),  # an empty inner run
        ("bits", _zstd(bytes([1, 9]) + bytes([0, 0])), 4),  # more runs than rows allow
        ("bits", _zstd(bytes([1, 1, 0x85, 0x80, 0x80, 0x80, 0x80, 0x00]) + bytes([0, 0])), 10),  # cut-short varint
        ("bits", _zstd(bytes([1, 2, 0x81, 0x80, 0x80, 0x80, 0x80, 0x01, 0x05, 0, 0])), 11),  # 6-byte varint
        ("bits", _zstd(bytes([1, 1, 0x85, 0x00, 0, 0])), 6),  # varint with a redundant zero byte
        ("bits", _zstd(bytes([0, 0, 0, 0, 7])), 5),  # a byte after the last level
    ],
)
def test_hostile_payloads_with_valid_checksums(name: str, payload: bytes, raw_length: int | None) -> None:
    assert code_of(with_payload(DATA, name, payload, raw_length)) == "corrupt_section"


def without_classes(data: bytes) -> tuple[dict[str, Any], bytes]:
    """The header and body of ``data`` as versions 1 and 2 wrote them: no step classes, the last section."""
    header, body = split(data)
    classes = header["sections"].pop()
    assert classes["name"] == "classes"
    return header, body[: classes["offset"]]


def test_headers_are_compressed_and_plain_version_1_headers_still_read() -> None:
    header, body = without_classes(DATA)
    text = json.dumps(header, separators=(",", ":")).encode()
    assert int.from_bytes(DATA[12:16], "little") < len(text)  # the writer's header is the compressed one
    plain = decode_archive(frame(text, body, version=1))
    assert plain.stored.means.shape == decode_archive(DATA).stored.means.shape and plain.classes is None
    assert code_of(frame(text, body)) == "bad_header"  # a version 3 archive must hold the classes


def test_archives_of_version_2_hold_no_classes_and_decode_as_class_0() -> None:
    header, body = without_classes(DATA)
    old = decode_archive(frame(json.dumps(header, separators=(",", ":")).encode(), body, version=2))
    assert old.classes is None and torch.equal(old.stored.means, decode_archive(DATA).stored.means)
    assert code_of(frame(json.dumps(split(DATA)[0]).encode(), split(DATA)[1], version=2)) == "bad_header"


@pytest.mark.parametrize("classes", [[0, 1, 2, 3, 8], [0, 0, 0, 0, -1], [0, 1], [0, 0, 0, 0, 0, 1]])
def test_classes_out_of_range_or_count_are_corrupt(classes: list[int]) -> None:
    payload = encode_table(np.array(classes, dtype=np.int64)[:, None])
    assert code_of(with_payload(DATA, "classes", payload)) == "corrupt_section"


def test_version_2_headers_that_do_not_inflate_are_refused() -> None:
    header, body = split(DATA)
    text = json.dumps(header, separators=(",", ":")).encode()
    not_zstd = MAGIC + struct.pack("<III", 2, len(text), zlib.crc32(text)) + text + body
    assert code_of(not_zstd) == "bad_header"
    big = zstandard.ZstdCompressor().compress(b" " * 5000 + text)
    framed = MAGIC + struct.pack("<III", 2, len(big), zlib.crc32(big)) + big + body
    assert code_of(framed, DecodeLimits(max_header_bytes=4096)) == "limit_exceeded"
    unsized = zstandard.ZstdCompressor(write_content_size=False).compress(text)
    framed = MAGIC + struct.pack("<III", 2, len(unsized), zlib.crc32(unsized)) + unsized + body
    assert code_of(framed) == "bad_header"


TWO_PLANES = [{"normal": [1.0, 0.0, 0.0], "offset": 0.0}, {"normal": [0.0, 1.0, 0.0], "offset": 0.0}]


def _refused_at_once(data: bytes, limits: DecodeLimits | None = None) -> str:
    """The code ``data`` is refused with, asserting that it took milliseconds and allocated next to nothing."""
    tracemalloc.start()
    start = time.perf_counter()
    try:
        code = code_of(data, limits)
        seconds = time.perf_counter() - start
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert seconds < 0.25 and peak < 8 << 20, (seconds, peak)
    return code


def test_a_tiny_archive_claiming_a_million_gaussians_is_refused_at_once() -> None:
    """7.8 kB of zeros claiming 1M stored Gaussians of SH degree 3, both level bits set: it decoded to 4M Gaussians
    at 3.3 GiB; within the old fixed limits an 80 kB file could ask for 30 GiB."""
    data = claiming(1_000_000, 3, TWO_PLANES)
    assert len(data) < 10_000
    assert _refused_at_once(data) == "disproportionate"


def test_level_bits_that_expand_a_small_archive_far_beyond_its_size_are_refused_before_any_attribute() -> None:
    planes = [{"normal": [0.0, 0.0, 1.0], "offset": 0.1 * i} for i in range(8)]
    data = claiming(50_000, 2, planes)  # as many stored as its size allows, each expanding 256 times
    assert len(data) < 2_000
    assert _refused_at_once(data) == "disproportionate"
    assert _refused_at_once(data, DecodeLimits(floor=1 << 25, max_memory_bytes=1 << 30)) == "limit_exceeded"


def test_archives_in_proportion_decode_within_their_memory_budget() -> None:
    data = claiming(5_000, 1, TWO_PLANES)  # 20,000 Gaussians once expanded: within any file's floor
    contents = decode_archive(data)
    assert len(expand_archive(contents)) == 20_000
    need = decode_memory(5_000, 20_000, 1, 2)
    assert code_of(data, DecodeLimits(max_memory_bytes=need - 1)) == "limit_exceeded"
    decode_archive(data, limits=DecodeLimits(max_memory_bytes=need))
