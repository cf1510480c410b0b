"""Quantising section codecs and their entropy coder: exact symbol round trips, error within half a step, per-Gaussian
SH degrees, hostile payloads, and a pinned encoding of a small quantised archive."""

from __future__ import annotations

import hashlib
import math
import multiprocessing
import os
import tracemalloc

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from symgs_core.codec import ArchiveContents, ArchiveError, decode_archive, encode_archive
from symgs_core.codec.entropy import MAX_ALPHABET, decode_table, encode_table
from symgs_core.codec.quantize import (
    OpacityCodec,
    PositionCodec,
    RotationCodec,
    ScalarGridCodec,
    ShDcCodec,
    ShRestCodec,
)
from symgs_core.codec.steps import QuantSteps
from symgs_core.scene import GaussianScene


def _roundtrip(codec, values: np.ndarray) -> tuple[np.ndarray, int]:  # noqa: ANN001
    coded = codec.encode(values)
    codec.check(values.shape, coded.params, coded.raw_length)
    return codec.decode(coded.payload, values.shape, coded.params, coded.raw_length), len(coded.payload)


def _random_scene(n: int, degree: int, seed: int) -> GaussianScene:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2 - 1
    return GaussianScene(
        means=torch.randn(n, 3, generator=g) * 2.0,
        quats=torch.randn(n, 4, generator=g),
        scales=torch.randn(n, 3, generator=g) - 4.0,
        opacities=torch.randn(n, generator=g) * 3.0,
        sh_dc=torch.randn(n, 3, generator=g),
        sh_rest=torch.randn(n, k, 3, generator=g) * 0.2,
    )


@settings(max_examples=15, deadline=None)
@given(
    arrays(np.int64, st.tuples(st.integers(0, 120), st.integers(1, 3)), elements=st.integers(-(2**29), 2**29 - 1))
)
def test_entropy_tables_round_trip_exactly(table: np.ndarray) -> None:
    assert np.array_equal(decode_table(encode_table(table), *table.shape, "t"), table)


def test_a_large_table_codes_its_columns_in_parallel_to_the_same_bytes(monkeypatch: pytest.MonkeyPatch) -> None:
    from symgs_core.codec import entropy

    rng = np.random.default_rng(4)
    n = entropy.PARALLEL_SYMBOLS
    table = np.stack([np.cumsum(rng.integers(-3, 4, n)), rng.geometric(0.3, n), rng.integers(0, 9, n) * 1000,
                      np.repeat(rng.integers(-50, 50, n // 64), 64)], axis=1)  # fmt: skip
    parallel = encode_table(table)
    monkeypatch.setattr(entropy, "PARALLEL_SYMBOLS", table.size + 1)
    assert encode_table(table) == parallel
    assert np.array_equal(decode_table(parallel, *table.shape, "t"), table)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork is POSIX")
def test_a_process_forked_after_coding_in_parallel_codes_in_parallel_too() -> None:
    from symgs_core.codec import entropy

    table = np.random.default_rng(5).integers(0, 100, size=(entropy.PARALLEL_SYMBOLS, 3))
    coded = encode_table(table)  # the parent's pool now has its threads
    child = multiprocessing.get_context("fork").Process(target=lambda: os._exit(int(encode_table(table) != coded)))
    child.start()
    child.join(60)
    if child.is_alive():
        child.kill()
    assert child.exitcode == 0  # None: it hung on the threads it did not inherit


def test_entropy_coder_picks_ans_for_skewed_symbols_and_zstd_for_huge_alphabets() -> None:
    rng = np.random.default_rng(0)
    skewed = rng.geometric(0.6, size=(20000, 1)).astype(np.int64)
    entropy = -(np.bincount(skewed[:, 0]) / len(skewed) * np.log2(np.bincount(skewed[:, 0]) / len(skewed) + 1e-300))
    bound = float(np.nansum(entropy)) * len(skewed) / 8
    assert len(encode_table(skewed)) < 1.03 * bound + 64  # within 3% of the order-0 entropy
    wide = rng.integers(0, 4 * MAX_ALPHABET, size=(500, 1))
    assert np.array_equal(decode_table(encode_table(wide), 500, 1, "t"), wide)


def test_a_table_whose_columns_share_their_statistics_codes_as_one_column_and_others_column_by_column() -> None:
    from symgs_core.codec import entropy

    rng = np.random.default_rng(8)
    shared = rng.geometric(0.2, size=(300, 9)) * rng.choice([-1, 1], size=(300, 9))  # one histogram pays for nine
    spread = rng.normal(size=(20000, 3)) * np.array([1.0, 30.0, 900.0])  # each column its own width
    for table, kind in ((shared, entropy.FLAT), (spread.astype(np.int64), entropy.COLUMNS)):
        coded = encode_table(table)
        assert coded[0] == kind
        assert np.array_equal(decode_table(coded, *table.shape, "t"), table)
        flat = encode_table(table.reshape(-1, 1))  # what the table's symbols cost as one column of their own
        assert len(coded) <= len(flat) + 2
        assert entropy.table_bits(table, entropy.CODING_LEVEL) <= 8 * (len(coded) + 8)  # priced with the same ways
    coded = encode_table(shared)
    for cut in (1, 5, len(coded) // 2):
        with pytest.raises(ArchiveError) as err:
            decode_table(coded[:-cut], *shared.shape, "t")
        assert err.value.code == "corrupt_section"


def test_a_columns_transforms_hold_their_symbols_at_their_streams_width() -> None:
    """A column's transforms keep their symbols as narrow as the stream that codes them, and difference it in one
    array of its size: a flat SH table of a million Gaussians is 21M symbols, 168 MB each int64 copy."""
    from symgs_core.codec import entropy

    column = np.round(np.random.default_rng(0).normal(0, 6, 1 << 20)).astype(np.int64)
    tracemalloc.start()
    try:
        kept = entropy._transforms(column)
        held, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert held <= 0.3 * column.nbytes and peak <= 1.5 * column.nbytes  # as int64: 1.0 and 3.0
    for t in kept:
        assert t.symbols.dtype == np.uint8
        expected = column if t.transform == entropy.RAW else np.diff(column, prepend=np.int64(0))
        assert np.array_equal(t.symbols.astype(np.int64) + t.offset, expected)


def test_positions_land_within_half_a_step_of_the_grid() -> None:
    values = np.random.default_rng(1).normal(size=(2000, 3)).astype(np.float32) * 5
    out, _ = _roundtrip(PositionCodec(1e-3), values)
    assert np.abs(out - values).max() <= 0.5e-3 + 1e-5


def test_morton_ordered_positions_code_smaller_than_shuffled_ones() -> None:
    from symgs_core.codec import morton_codes

    values = np.random.default_rng(2).random((20000, 3)).astype(np.float32)
    ordered = values[torch.argsort(morton_codes(torch.from_numpy(values))).numpy()]
    _, sorted_bytes = _roundtrip(PositionCodec(2.0**-16), ordered)
    _, random_bytes = _roundtrip(PositionCodec(2.0**-16), values)
    assert sorted_bytes < 0.92 * random_bytes


def test_rotations_decode_to_unit_quaternions_of_the_same_rotation() -> None:
    quats = np.random.default_rng(3).normal(size=(5000, 4)).astype(np.float32)
    step = 1.0 / 256
    out, _ = _roundtrip(RotationCodec(step), quats)
    assert np.allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-6)
    unit = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    dots = np.abs((out * unit).sum(axis=1))  # q and -q are one rotation
    # Three components off by at most step/2 each, the fourth recomputed: the angle between them stays tiny.
    assert dots.min() > math.cos(2.0 * step)


def test_scales_dc_and_opacity_within_half_a_step() -> None:
    rng = np.random.default_rng(4)
    scales = (rng.normal(size=(3000, 3)) - 4).astype(np.float32)
    out, _ = _roundtrip(ScalarGridCodec(1 / 16), scales)
    assert np.abs(out - scales).max() <= 1 / 32 + 1e-5
    dc = rng.normal(size=(3000, 3)).astype(np.float32)
    out, _ = _roundtrip(ShDcCodec(0.01), dc)
    assert np.abs(out - dc).max() <= 0.005 + 1e-6
    logits = rng.normal(size=3000).astype(np.float32) * 3
    out, _ = _roundtrip(OpacityCodec(1 / 255), logits)
    alpha, decoded = 1 / (1 + np.exp(-logits)), 1 / (1 + np.exp(-out.astype(np.float64)))
    visible = alpha > 2 / 255
    assert np.abs(decoded - alpha)[visible].max() <= 0.5 / 255 + 1e-6
    assert (decoded[~visible] < 2.5 / 255).all()  # the invisible stay (almost) invisible


def test_sh_rest_keeps_a_degree_per_gaussian_and_dropped_bands_cost_nothing() -> None:
    rng = np.random.default_rng(5)
    rest = (rng.normal(size=(4000, 15, 3)) * 0.3).astype(np.float32)
    truncated = rest.copy()
    truncated[:2000, 3:] = 0.0  # degree 1 for the first half
    truncated[2000:3000, :] = 0.0  # degree 0
    codec = ShRestCodec((0.02, 0.02, 0.02))
    out, small = _roundtrip(codec, truncated)
    _, full = _roundtrip(codec, rest)
    assert np.abs(out - truncated).max() <= 0.01 + 1e-6
    assert (out[:2000, 3:] == 0).all() and (out[2000:3000] == 0).all()
    assert small < 0.6 * full


def test_sh_bands_give_each_coefficient_its_own_histogram_and_read_archives_that_did_not() -> None:
    from symgs_core.codec.classes import encode_groups
    from symgs_core.codec.section import join_parts

    rng = np.random.default_rng(9)
    # Band 2's five coefficients with very different spreads, as trained scenes' coefficients have.
    rest = (rng.laplace(size=(6000, 8, 3)) * np.geomspace(0.02, 0.6, 8)[None, :, None]).astype(np.float32)
    codec = ShRestCodec((0.04, 0.04))
    coded = codec.encode(rest)
    assert coded.params["layout"] == "rows"
    out = codec.decode(coded.payload, rest.shape, coded.params, coded.raw_length)
    assert np.abs(out - rest).max() <= 0.02 + 1e-6
    # The layout written before format version 4: each band's symbols in one column.
    bands, per = codec._quantise(rest, None)
    one_column = join_parts([encode_table(per[:, None])]
                            + [encode_groups(b, None, lambda r: encode_table(r.reshape(-1, 1))) for b in bands])
    params = {"steps": [0.04, 0.04], "decorrelate": [False, False]}
    codec.check(rest.shape, params, coded.raw_length)
    assert np.array_equal(codec.decode(one_column, rest.shape, params, coded.raw_length), out)
    assert len(coded.payload) < 0.98 * len(one_column)
    with pytest.raises(ArchiveError) as err:
        codec.check(rest.shape, {**coded.params, "layout": "columns"}, coded.raw_length)
    assert err.value.code == "bad_header"


@pytest.mark.parametrize("degree", [0, 2])
def test_quantized_archive_decodes_to_what_the_codecs_promise(degree: int) -> None:
    from ._samples import decoded_by_sections

    scene = _random_scene(700, degree, seed=degree)
    steps = QuantSteps().scaled(3.0)
    extent = float((scene.means.max(0).values - scene.means.min(0).values).max())
    name = steps.archive_codec(extent, "test-quantized")
    contents = ArchiveContents(scene, [], torch.zeros(len(scene), 0, dtype=torch.bool), {"x": 1})
    data = encode_archive(contents, codec=name)
    decoded = decode_archive(data).stored
    expected = decoded_by_sections(scene, steps, extent)
    for key, value in decoded.tensors().items():
        assert torch.equal(value, expected.tensors()[key]), key
    assert len(data) < 0.35 * len(encode_archive(contents))


def test_quantized_archive_encoding_is_pinned() -> None:
    """A format change must be deliberate: re-pin with the new digest only when the stream layout changes."""
    scene = _random_scene(300, 1, seed=11)
    name = QuantSteps().archive_codec(8.0, "test-pinned")
    classes = torch.arange(300) * 4 // 300  # classes 0..3, in runs as the coding order leaves them
    data = encode_archive(ArchiveContents(scene, [], torch.zeros(300, 0, dtype=torch.bool), {}, classes), codec=name)
    assert hashlib.sha256(data).hexdigest() == PINNED


PINNED = "ccac7cda2a3bd22fe0e0c81258145f0e83772b748fb265358fc740d631771563"


@pytest.mark.parametrize(
    ("codec", "shape", "params"),
    [
        (PositionCodec(1.0), (4, 3), {"origin": [0, 0, 0], "step": -1.0}),
        (PositionCodec(1.0), (4, 3), {"origin": [0, 0], "step": 1.0}),
        (RotationCodec(1.0), (4, 4), {"step": float("nan")}),
        (OpacityCodec(0.1), (4,), {"step": 2.0}),
        (ShRestCodec((0.1,)), (4, 3, 3), {"steps": [0.1, 0.1], "decorrelate": [False, False]}),
        (ShRestCodec((0.1,)), (4, 3, 3), {"steps": [0.1], "decorrelate": [1]}),
        (ShDcCodec(0.1), (4, 3), {"origin": 0.0, "step": 0.1, "decorrelate": False, "extra": 1}),
        (ShDcCodec(0.1), (4, 3), {"origin": 0.0, "step": 0.1, "decorrelate": 0}),
    ],
)
def test_impossible_parameters_are_refused_before_decoding(codec, shape, params) -> None:  # noqa: ANN001
    with pytest.raises(ArchiveError) as err:
        codec.check(shape, params, int(np.prod(shape)) * 4)
    assert err.value.code == "bad_header"


@pytest.mark.parametrize("cut", [1, 7, 30])
def test_cut_or_corrupt_payloads_are_corrupt_sections(cut: int) -> None:
    values = np.random.default_rng(6).normal(size=(200, 3)).astype(np.float32)
    codec = ShDcCodec(0.05)
    coded = codec.encode(values)
    with pytest.raises(ArchiveError) as err:
        codec.decode(coded.payload[:-cut], values.shape, coded.params, coded.raw_length)
    assert err.value.code == "corrupt_section"
    rest = (np.random.default_rng(7).normal(size=(50, 8, 3)) * 0.3).astype(np.float32)
    sh = ShRestCodec((0.05, 0.05))
    coded = sh.encode(rest)
    with pytest.raises(ArchiveError):
        sh.decode(coded.payload[: len(coded.payload) // 2], rest.shape, coded.params, coded.raw_length)


def test_attributes_that_cannot_be_quantised_are_refused() -> None:
    with pytest.raises(ValueError, match="finite"):
        PositionCodec(0.1).encode(np.array([[0, np.inf, 0]], dtype=np.float32))
    with pytest.raises(ValueError, match="cells"):
        PositionCodec(1e-9).encode(np.array([[0, 0, 0], [100, 0, 0]], dtype=np.float32))


def test_attributes_on_a_grid_of_their_own_are_kept_on_it() -> None:
    """8-bit colours and alphas (scenes decoded from .splat or .spz) survive exactly; coarser asks use multiples."""
    rng = np.random.default_rng(8)
    c0 = 0.28209479177387814
    dc = ((rng.integers(0, 256, size=(3000, 3)) / 255.0 - 0.5) / c0).astype(np.float32)
    out, _ = _roundtrip(ShDcCodec(0.001), dc)  # finer than the grid: the grid itself
    assert np.abs(out - dc).max() < 1e-5
    out, _ = _roundtrip(ShDcCodec(0.06), dc)  # coarser: every 4th grid value (step 4/(255 C0) = 0.0556)
    cells = (out.astype(np.float64) - dc.min()) * 255 * c0
    assert np.abs(cells - 4 * np.round(cells / 4)).max() < 1e-3
    logits = np.log((a := rng.integers(1, 255, size=3000) / 255.0) / (1 - a)).astype(np.float32)
    out, _ = _roundtrip(OpacityCodec(1 / 1000), logits)
    assert np.abs(1 / (1 + np.exp(-out.astype(np.float64))) - a).max() < 1e-6
    scales = (rng.integers(0, 160, size=(3000, 3)) / 16.0 - 10.0).astype(np.float32)
    out, _ = _roundtrip(ScalarGridCodec(0.01), scales)
    assert np.array_equal(out, scales)
    trained = rng.normal(size=(3000, 3)).astype(np.float32)  # no grid: the step asked for
    out, _ = _roundtrip(ShDcCodec(0.02), trained)
    assert 0.009 < np.abs(out - trained).max() <= 0.01 + 1e-6


def test_colour_channels_that_move_together_are_stored_decorrelated() -> None:
    rng = np.random.default_rng(9)
    grey = rng.normal(size=(4000, 1))
    dc = (grey + 0.02 * rng.normal(size=(4000, 3))).astype(np.float32)
    coded = ShDcCodec(0.01).encode(dc)
    assert coded.params["decorrelate"] is True
    out, _ = _roundtrip(ShDcCodec(0.01), dc)
    assert np.abs(out - dc).max() <= 0.005 + 1e-6
    independent = rng.normal(size=(4000, 3)).astype(np.float32)
    assert ShDcCodec(0.01).encode(independent).params["decorrelate"] is False
    rest = (np.repeat(rng.normal(size=(2000, 8, 1)), 3, axis=2) * 0.3).astype(np.float32)
    coded = ShRestCodec((0.01, 0.01)).encode(rest)
    assert coded.params["decorrelate"] == [True, True]
    out, _ = _roundtrip(ShRestCodec((0.01, 0.01)), rest)
    assert np.abs(out - rest).max() <= 0.005 + 1e-6


@pytest.mark.parametrize("palette", [0, 64])
def test_an_archive_tells_where_its_bytes_are_each_sh_band_apart(palette: int) -> None:
    from dataclasses import replace

    from symgs_core.codec import section_bytes

    scene = _random_scene(400, 2, seed=3)
    bits = torch.zeros(400, 0, dtype=torch.bool)
    writer = replace(QuantSteps(), sh_palette=palette).archive_codec(8.0, "test-parts")
    data = encode_archive(ArchiveContents(scene, [], bits, {}), codec=writer)
    parts = section_bytes(data)
    index = "sh_index" if palette else "sh_degrees"
    names = ["header", "means", "quats", "scales", "opacities", "sh_dc", index, "sh_band_1", "sh_band_2", "bits",
             "classes"]
    assert [name for name, _ in parts] == names
    assert sum(size for _, size in parts) == len(data) and all(size > 0 for _, size in parts)
    lossless = section_bytes(encode_archive(ArchiveContents(scene, [], bits, {})))
    assert [name for name, _ in lossless][-3:] == ["sh_rest", "bits", "classes"]
