"""Morton gap coding of positions: exact round trips of codes and cells, runs, the smaller of the two codings, the
coding order on the codec's own grid, old archives without the flag, and hostile streams."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from symgs_core.codec import ArchiveError
from symgs_core.codec.entropy import encode_table
from symgs_core.codec.morton import AXIS_BITS, decode_codes, deinterleave, encode_codes, interleave
from symgs_core.codec.order import coding_order, grid_cells
from symgs_core.codec.quantize import PositionCodec
from symgs_core.scene import GaussianScene


def _surface(n: int, seed: int = 0) -> np.ndarray:
    """Points on a bumpy sphere, float32: clustered as captured scenes are."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return (d * (1.0 + 0.05 * rng.normal(size=(n, 1)))).astype(np.float32)


def test_interleave_is_bitwise_exact() -> None:
    rng = np.random.default_rng(1)
    cells = rng.integers(0, 1 << AXIS_BITS, size=(5000, 3))
    codes = interleave(cells)
    assert np.array_equal(deinterleave(codes), cells)
    # Bit k of axis a lands on bit 3k + a.
    one = interleave(np.array([[1 << 20, 0, 0], [0, 1 << 20, 0], [0, 0, 1 << 20], [5, 0, 0]]))
    assert one.tolist() == [1 << 60, 1 << 61, 1 << 62, (1 << 0) | (1 << 6)]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, (1 << 63) - 1), max_size=300), st.integers(0, 5))
def test_codes_round_trip_whatever_their_runs(values: list[int], runs: int) -> None:
    codes = np.sort(np.array(values, dtype=np.int64))
    if len(codes) and runs:
        codes = np.concatenate(np.array_split(codes, runs + 1)[::-1])  # descending steps between runs
    assert np.array_equal(decode_codes(encode_codes(codes), len(codes), "t"), codes)


def test_sorted_codes_cost_less_than_per_axis_differences() -> None:
    points = _surface(40000)
    codec = PositionCodec(2e-4)
    cells = codec.cells(points)
    order = np.argsort(interleave(cells), kind="stable")
    coded = codec.encode(points[order])
    assert coded.params["morton"] is True
    table = encode_table(cells[order])
    assert len(coded.payload) < 0.9 * len(table)
    out = codec.decode(coded.payload, points.shape, coded.params, coded.raw_length)
    assert np.abs(out - points[order]).max() <= 1e-4 + 1e-6


def test_unsorted_positions_keep_the_table() -> None:
    points = _surface(5000, seed=2)
    coded = PositionCodec(2e-4).encode(points)  # random order: a run per point or so
    assert coded.params["morton"] is False
    out = PositionCodec(2e-4).decode(coded.payload, points.shape, coded.params, coded.raw_length)
    assert np.abs(out - points).max() <= 1e-4 + 1e-6


def test_archives_without_the_flag_still_decode() -> None:
    points = _surface(3000, seed=3)
    codec = PositionCodec(1e-3)
    cells = codec.cells(points)
    origin = points.astype(np.float64).min(axis=0)
    params = {"origin": origin.tolist(), "step": 1e-3}
    codec.check(points.shape, params, points.size * 4)
    out = codec.decode(encode_table(cells), points.shape, params, points.size * 4)
    assert np.array_equal(out, (origin + cells * 1e-3).astype(np.float32))


def test_coding_order_follows_the_codecs_grid() -> None:
    points = torch.from_numpy(_surface(20000, seed=4))
    n = len(points)
    scene = GaussianScene(
        means=points, quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), scales=torch.zeros(n, 3),
        opacities=torch.zeros(n), sh_dc=torch.zeros(n, 3), sh_rest=torch.zeros(n, 0, 3),
    )  # fmt: skip
    bits = torch.zeros(n, 1, dtype=torch.bool)
    bits[::3] = True  # two level groups: two runs of rising codes
    codec = PositionCodec(1e-3)
    cells = grid_cells(codec, points.numpy())
    perm = coding_order(scene, bits, cells).numpy()
    codes = interleave(cells[perm])
    assert int((np.diff(codes) < 0).sum()) == 1
    assert codec.encode(points.numpy()[perm]).params["morton"] is True
    assert grid_cells(object(), points.numpy()) is None
    with pytest.raises(ValueError, match="cells"):
        coding_order(scene, bits, cells[:-1])


@pytest.mark.parametrize("cut", [0, 3, 10, -1])
def test_cut_streams_are_refused(cut: int) -> None:
    codes = np.sort(interleave(np.random.default_rng(5).integers(0, 1 << 12, size=(500, 3))))
    payload = encode_codes(codes)
    with pytest.raises(ArchiveError):
        decode_codes(payload[:cut] if cut >= 0 else payload + b"\x00", len(codes), "t")


def test_a_stream_for_other_counts_is_refused() -> None:
    codes = np.sort(interleave(np.random.default_rng(6).integers(0, 1 << 12, size=(500, 3))))
    payload = encode_codes(codes)
    for n in (499, 501):
        with pytest.raises(ArchiveError):
            decode_codes(payload, n, "t")


@settings(max_examples=100, deadline=None)
@given(st.binary(max_size=200), st.integers(0, 50))
def test_random_streams_are_refused_or_decode_in_range(data: bytes, n: int) -> None:
    try:
        codes = decode_codes(data, n, "t")
    except ArchiveError:
        return
    assert len(codes) == n and (n == 0 or codes.min() >= 0)
