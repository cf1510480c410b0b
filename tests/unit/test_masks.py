"""The level bit matrix codec: exact round trips, near-free runs, no blow-up on noise, strict parsing."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from symgs_core.codec import ArchiveError
from symgs_core.codec.masks import (
    MASKS,
    PACKED,
    RUNS,
    column_runs,
    decode_masks,
    encode_masks,
    max_raw_length,
    read_varints,
    varint,
    write_varints,
)


def round_trip(bits: np.ndarray) -> tuple[np.ndarray, int]:
    """Decoded matrix and stored bytes through the section codec, with the checks a reader runs first."""
    coded = MASKS.encode(bits)
    MASKS.check(bits.shape, coded.params, coded.raw_length)
    return MASKS.decode(coded.payload, bits.shape, coded.params, coded.raw_length), len(coded.payload)


def run_structured(n: int, levels: int, mean_run: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    columns = []
    for _ in range(levels):
        lengths = rng.geometric(1 / mean_run, size=n)
        columns.append(np.repeat(np.arange(len(lengths)) % 2 == 1, lengths)[:n])
    return np.stack(columns, axis=1) if levels else np.zeros((n, 0), dtype=bool)


@settings(max_examples=150, deadline=None)
@given(arrays(np.bool_, st.tuples(st.integers(0, 300), st.integers(0, 5))))
def test_random_matrices_round_trip(bits: np.ndarray) -> None:
    back, _ = round_trip(bits)
    assert back.dtype == np.bool_ and np.array_equal(back, bits)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2000), st.integers(1, 4), st.floats(1.0, 400.0), st.integers(0, 2**31))
def test_run_structured_matrices_round_trip(n: int, levels: int, mean_run: float, seed: int) -> None:
    bits = run_structured(n, levels, mean_run, seed)
    back, _ = round_trip(bits)
    assert np.array_equal(back, bits)


def test_runs_cost_far_less_than_a_bit_per_row() -> None:
    n, levels = 100_000, 3
    bits = run_structured(n, levels, 1000.0, seed=1)  # about 100 runs per level
    _, size = round_trip(bits)
    assert size < 0.05 * levels * n / 8, size
    grouped = np.sort(np.random.default_rng(2).random((n, levels)) < 0.3, axis=0)[::-1]  # one run of each value
    _, size = round_trip(np.ascontiguousarray(grouped))
    assert size < 64, size


def test_random_columns_stay_near_one_bit_per_row() -> None:
    n, levels = 50_000, 2
    bits = np.random.default_rng(3).random((n, levels)) < 0.5
    _, size = round_trip(bits)
    assert size <= 1.01 * levels * n / 8 + 64, size
    raw = encode_masks(bits)
    assert raw[0] == PACKED and len(raw) == levels * (1 + n // 8)


def test_encoder_picks_runs_for_runs_and_packed_bits_for_noise() -> None:
    noise = np.random.default_rng(4).random(4000) < 0.5
    runs = np.arange(4000) >= 1234
    raw = encode_masks(np.stack([noise, runs], axis=1))
    assert raw[0] == PACKED
    assert raw[1 + 500 :] == bytes([RUNS]) + write_varints([2]) + write_varints([1234, 2766])


@pytest.mark.parametrize(
    "column,runs",
    [
        ([], []),
        ([0], [1]),
        ([1], [0, 1]),
        ([1, 1, 0, 0, 0, 1], [0, 2, 3, 1]),
        ([0, 0, 1, 0], [2, 1, 1]),
    ],
)
def test_column_runs(column: list[int], runs: list[int]) -> None:
    assert column_runs(np.array(column, dtype=bool)).tolist() == runs


def test_varints_match_leb128() -> None:
    values = [0, 1, 127, 128, 300, 2**14 - 1, 2**14, 2**35 - 1]
    data = write_varints(np.array(values))
    assert write_varints(np.array([300])) == b"\xac\x02" and write_varints(np.array([127])) == b"\x7f"
    assert write_varints(np.array([2**35 - 1])) == b"\xff\xff\xff\xff\x7f"
    back, end = read_varints(np.frombuffer(data, np.uint8), 0, len(values))
    assert back.tolist() == values and end == len(data)
    for bad in ([-1], [2**35]):
        with pytest.raises(ValueError, match="varints hold"):
            write_varints(np.array(bad))
        with pytest.raises(ValueError, match="varints hold"):
            varint(bad[0])
    assert b"".join(varint(v) for v in values) == data


@pytest.mark.parametrize(
    "raw,n,levels,message",
    [
        (b"", 4, 1, "ends before level 0"),
        (bytes([3]), 4, 1, "unknown block mode 3"),
        (bytes([PACKED]), 4, 1, "0 packed bytes of 1"),
        (bytes([PACKED, 0x0F]), 4, 1, "padding bits set"),
        (bytes([RUNS, 2, 2, 1]), 4, 1, "runs sum to 3"),
        (bytes([RUNS, 3, 1, 0, 3]), 4, 1, "empty run"),
        (bytes([RUNS, 1, 0]), 0, 1, "empty run"),
        (bytes([RUNS, 0]), 4, 1, "runs sum to 0"),
        (bytes([RUNS, 6]), 4, 1, "6 runs for 4 rows"),
        (bytes([RUNS, 2, 0x80]), 4, 1, "varints end within"),
        (bytes([RUNS, 1, 0x84, 0x00]), 4, 1, "redundant zero byte"),
        (bytes([RUNS, 1, 0xFF, 0xFF, 0xFF, 0xFF, 0x7F]), 4, 1, r"runs sum to 34359738367"),
        (bytes([PACKED, 0xF0, 0]), 4, 1, "1 bytes after the last level"),
    ],
)
def test_malformed_streams_are_corrupt_sections(raw: bytes, n: int, levels: int, message: str) -> None:
    with pytest.raises(ArchiveError, match=message) as info:
        decode_masks(raw, n, levels)
    assert info.value.code == "corrupt_section"


def test_reader_bounds_the_stream_before_decoding() -> None:
    assert max_raw_length(10, 2) == 2 * (1 + 5 * 12)
    MASKS.check((10, 2), {}, max_raw_length(10, 2))
    for raw_length in (1, max_raw_length(10, 2) + 1):
        with pytest.raises(ArchiveError, match="impossible") as info:
            MASKS.check((10, 2), {}, raw_length)
        assert info.value.code == "bad_header"
    with pytest.raises(ValueError, match="bool matrix"):
        encode_masks(np.zeros((3, 2), dtype=np.uint8))
