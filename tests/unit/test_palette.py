"""The palette codec of the higher SH bands: exact palettes of distinct rows, k-means palettes, zero rows, archives
written with it, hostile payloads and deterministic output."""

from __future__ import annotations

import gc
import weakref

import numpy as np
import pytest
import torch

from symgs_core.codec import ArchiveContents, ArchiveError, decode_archive, encode_archive, palette
from symgs_core.codec.entropy import encode_table
from symgs_core.codec.palette import RowWeights, ShPaletteCodec, _nearest, _reassign, fit_palette
from symgs_core.codec.quantize import ShRestCodec
from symgs_core.codec.steps import QuantSteps
from symgs_core.scene import GaussianScene

STEPS = (0.01, 0.01, 0.01)


def _roundtrip(codec: ShPaletteCodec, values: np.ndarray) -> tuple[np.ndarray, dict]:
    coded = codec.encode(values)
    codec.check(values.shape, coded.params, coded.raw_length)
    return codec.decode(coded.payload, values.shape, coded.params, coded.raw_length), coded.params


def _clustered(n: int, k: int, centres: int, noise: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    means = rng.normal(size=(centres, k, 3)) * 0.3
    return (means[rng.integers(0, centres, n)] + rng.normal(size=(n, k, 3)) * noise).astype(np.float32)


def test_distinct_rows_that_fit_decode_within_half_a_step_and_zero_rows_exactly() -> None:
    rng = np.random.default_rng(0)
    rows = (rng.normal(size=(40, 8, 3)) * 0.3).astype(np.float32)
    values = rows[rng.integers(0, 40, 600)]
    values[::7] = 0.0  # Gaussians whose bands were all dropped
    out, params = _roundtrip(ShPaletteCodec(64, STEPS), values)
    assert np.abs(out - values).max() <= 0.005 + 1e-6
    assert (out[::7] == 0).all()
    assert params["size"] == 1 + len(np.unique(values[values.any(axis=(1, 2))], axis=0))


def test_a_kmeans_palette_stays_well_below_the_spread_of_the_data() -> None:
    values = _clustered(4000, 3, centres=50, noise=0.02, seed=1)
    out, params = _roundtrip(ShPaletteCodec(256, STEPS), values)
    assert params["size"] <= 256
    assert len(np.unique(out.reshape(len(out), -1), axis=0)) <= params["size"]  # every row is a palette entry
    rms, spread = float(np.sqrt(((out - values) ** 2).mean())), float(values.std())
    assert rms < 0.1 * spread and rms < 0.03


def test_a_palette_codes_clustered_sh_smaller_than_the_scalar_codec() -> None:
    values = _clustered(4000, 8, centres=100, noise=0.0, seed=2)
    palette = ShPaletteCodec(128, STEPS).encode(values)
    scalar = ShRestCodec(STEPS).encode(values)
    assert len(palette.payload) < 0.5 * len(scalar.payload)


def test_incremental_reassignment_finds_the_nearest_entries() -> None:
    g = torch.Generator().manual_seed(3)
    rows, entries = torch.randn(3000, 9, generator=g), torch.randn(200, 9, generator=g)
    labels = _nearest(rows, entries)[0]
    moved = np.zeros(200, dtype=bool)
    moved[::9] = True
    entries[torch.from_numpy(moved)] += 0.5 * torch.randn(int(moved.sum()), 9, generator=g)
    exact = torch.cdist(rows.double(), entries.double()).argmin(dim=1).numpy()
    assert np.array_equal(_reassign(rows, entries, labels, moved), exact)


def test_fits_and_encodings_are_deterministic() -> None:
    values = _clustered(3000, 3, centres=400, noise=0.02, seed=4)
    flat = values.reshape(len(values), -1)
    first, second = fit_palette(flat, 100), fit_palette(flat, 100)
    assert np.array_equal(first[0], second[0]) and np.array_equal(first[1], second[1])
    codec = ShPaletteCodec(101, STEPS)
    assert codec.encode(values).payload == codec.encode(values.copy()).payload


def test_a_palette_of_one_entry_and_a_scene_without_higher_bands() -> None:
    values = _clustered(50, 3, centres=5, noise=0.0, seed=5)
    out, params = _roundtrip(ShPaletteCodec(1, STEPS), values)
    assert params["size"] == 1 and (out == 0).all()
    empty = np.zeros((50, 0, 3), dtype=np.float32)
    out, params = _roundtrip(ShPaletteCodec(256, ()), empty)
    assert out.shape == (50, 0, 3)
    assert params == {"size": 1, "steps": [], "decorrelate": [], "order": "use", "classes": False}


@pytest.mark.parametrize("degree", [0, 2])
def test_palette_archive_decodes_to_what_the_codecs_promise(degree: int) -> None:
    from symgs_core.pipeline.budget import extent_of

    from ._samples import decoded_by_sections

    g = torch.Generator().manual_seed(degree)
    n, k = 600, (degree + 1) ** 2 - 1
    scene = GaussianScene(
        means=torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        scales=torch.randn(n, 3, generator=g) - 4.0,
        opacities=torch.randn(n, generator=g),
        sh_dc=torch.randn(n, 3, generator=g),
        sh_rest=torch.from_numpy(_clustered(n, k, centres=50, noise=0.01, seed=6)),
    )
    steps = QuantSteps(sh_palette=32).scaled(3.0)
    assert steps.sh_palette == 32 and steps.report().sh_palette == 32
    name = steps.archive_codec(extent_of(scene), "test-palette")
    contents = ArchiveContents(scene, [], torch.zeros(n, 0, dtype=torch.bool), {})
    data = encode_archive(contents, codec=name)
    decoded = decode_archive(data).stored
    expected = decoded_by_sections(scene, steps, extent_of(scene))
    assert steps.codecs(1.0)["sh_rest"].name == "vq-sh"
    for key, value in decoded.tensors().items():
        assert torch.equal(value, expected.tensors()[key]), key


def test_hostile_palette_sections_are_archive_errors() -> None:
    values = _clustered(300, 8, centres=20, noise=0.0, seed=7)
    codec = ShPaletteCodec(64, STEPS)
    coded = codec.encode(values)
    shape, params, raw = values.shape, coded.params, coded.raw_length

    def code(payload: bytes, params: dict = params) -> str:
        with pytest.raises(ArchiveError) as err:
            codec.check(shape, params, raw)
            codec.decode(payload, shape, params, raw)
        return err.value.code

    assert code(coded.payload[:-3]) == "corrupt_section"
    assert code(coded.payload + b"\0") == "corrupt_section"
    indices = encode_table(np.full((300, 1), params["size"], dtype=np.int64))
    bands = coded.payload[4 + int.from_bytes(coded.payload[:4], "little") :]
    assert code(len(indices).to_bytes(4, "little") + indices + bands) == "corrupt_section"
    for bad in (
        params | {"size": 0},
        params | {"size": 302},
        params | {"size": True},
        params | {"steps": params["steps"][:1]},
        params | {"steps": [0.01, -0.01]},
        params | {"decorrelate": [1, 0]},
        {"size": params["size"], "steps": params["steps"]},
    ):
        assert code(coded.payload, bad) == "bad_header", bad
    with pytest.raises(ArchiveError, match="raw length"):
        codec.check(shape, params, raw + 4)


def _sog_like(n: int, entries: int, seed: int) -> np.ndarray:
    """Rows drawn from a palette where most entries serve one or two rows, as in scenes decoded from SOG."""
    rng = np.random.default_rng(seed)
    palette = np.round(rng.normal(size=(entries, 3, 3)) * 10.0) / 40.0  # on the 0.025 grid: exact at STEPS x 2.5
    values = palette[rng.integers(0, entries, n)].astype(np.float32)
    values[::11] = 0.0
    return values


def test_palettes_of_rarely_shared_entries_are_numbered_by_first_use() -> None:
    values = _sog_like(6000, 4000, seed=21)
    codec = ShPaletteCodec(1 << 14, (0.025,))
    coded = codec.encode(values)
    assert coded.params["order"] == "first"
    out = codec.decode(coded.payload, values.shape, coded.params, coded.raw_length)
    assert np.abs(out - values).max() <= 1e-6 and (out[::11] == 0).all()
    # Against the same entries ordered by use, with an entropy-coded index: the index part alone shrinks by a third.
    index = np.unique(values.reshape(len(values), -1), axis=0, return_inverse=True)[1].reshape(-1)
    by_use_index = len(encode_table(index[:, None]))
    first_use_index = int.from_bytes(coded.payload[:4], "little")  # the first part: the index stream
    assert first_use_index < 0.67 * by_use_index


def test_palettes_of_widely_shared_entries_keep_the_order_by_use() -> None:
    values = _clustered(6000, 3, centres=50, noise=0.0, seed=22)
    coded = ShPaletteCodec(64, STEPS).encode(values)
    assert coded.params["order"] == "use"


def test_archives_without_an_entry_order_still_decode() -> None:
    values = _clustered(6000, 3, centres=30, noise=0.0, seed=23)
    codec = ShPaletteCodec(64, STEPS)
    coded = codec.encode(values)
    assert coded.params["order"] == "use"
    legacy = {key: value for key, value in coded.params.items() if key != "order"}
    codec.check(values.shape, legacy, coded.raw_length)
    assert np.array_equal(codec.decode(coded.payload, values.shape, legacy, coded.raw_length),
                          codec.decode(coded.payload, values.shape, coded.params, coded.raw_length))  # fmt: skip
    with pytest.raises(ArchiveError, match="order"):
        codec.check(values.shape, {**coded.params, "order": "random"}, coded.raw_length)


def test_hostile_first_use_streams_are_refused() -> None:
    values = _sog_like(800, 600, seed=24)
    codec = ShPaletteCodec(1 << 12, (0.025,))
    coded = codec.encode(values)
    assert coded.params["order"] == "first"
    payload = coded.payload
    index_length = 4 + int.from_bytes(payload[:4], "little")
    for bad in (payload[: index_length - 1], payload[:index_length] + b"\xff" + payload[index_length:]):
        with pytest.raises(ArchiveError):
            codec.decode(bad, values.shape, coded.params, coded.raw_length)
    for size in (coded.params["size"] - 1, coded.params["size"] + 1):
        with pytest.raises(ArchiveError):
            codec.decode(payload, values.shape, {**coded.params, "size": size}, coded.raw_length)
    rng = np.random.default_rng(25)
    for _ in range(200):  # flipped bytes: refused, or a palette index within range
        flipped = bytearray(payload)
        flipped[rng.integers(0, len(flipped))] ^= 1 << int(rng.integers(0, 8))
        try:
            out = codec.decode(bytes(flipped), values.shape, coded.params, coded.raw_length)
        except ArchiveError:
            continue
        assert out.shape == values.shape


def test_entry_classes_follow_the_inverse_square_root_of_the_weight() -> None:
    from symgs_core.codec.palette import MAX_CLASS, entry_classes

    mean = 1.0
    weights = np.array([4.0, 1.0, 0.25, 1.0 / 16, 1.0 / 64, 1e-9, 0.0]) * mean
    weights = weights * (weights.size / weights.sum())  # rescaled so their mean is 1
    classes = entry_classes(weights)
    assert classes.tolist() == sorted(classes.tolist())  # lighter entries never get finer steps
    assert classes[0] == 0 and classes[-1] == MAX_CLASS and classes[-2] == MAX_CLASS
    ratio = 1.0 / weights[2:5]  # mean / weight
    assert np.array_equal(classes[2:5], np.clip(np.round(0.5 * np.log2(ratio)), 0, MAX_CLASS))
    assert not entry_classes(np.zeros(5)).any() and len(entry_classes(np.zeros(0))) == 0


def test_row_weights_are_found_in_any_order_and_shared_among_repeats() -> None:
    rows = _sog_like(400, 100, seed=31)
    weights = np.random.default_rng(32).random(400)
    table = RowWeights.of(rows, weights)
    flat = rows.reshape(400, -1)
    perm = np.random.default_rng(33).permutation(400)
    looked = table.lookup(flat[perm].astype(np.float64))
    keys = [r.tobytes() for r in (flat + np.float32(0.0))]
    expected = np.array([sum(w for k2, w in zip(keys, weights) if k2 == keys[i]) for i in perm])
    assert np.allclose(looked, expected)
    assert np.allclose(table.per_row(flat).sum(), weights.sum())
    # Shares are remembered for the rows last asked about, and follow the rows when they change.
    assert np.array_equal(table.per_row(flat[perm]), table.per_row(flat)[perm])
    assert np.array_equal(table.per_row(flat[:3]), table.lookup(flat[:3]) / [keys[:3].count(k) for k in keys[:3]])
    assert table.lookup(np.full((2, flat.shape[1]), 9.0)).tolist() == [0.0, 0.0]


def test_weighted_palettes_give_light_entries_coarser_steps() -> None:
    from symgs_core.codec.palette import RowWeights

    rng = np.random.default_rng(34)
    values = (rng.normal(size=(3000, 3, 3)) * 0.3).astype(np.float32)  # every row its own entry
    weights = np.where(np.arange(3000) < 1500, 1.0, 1e-3)  # the second half barely seen
    step = 0.01
    plain = ShPaletteCodec(4096, (step,)).encode(values)
    weighted_codec = ShPaletteCodec(4096, (step,), RowWeights.of(values, weights))
    coded = weighted_codec.encode(values)
    assert coded.params["classes"] is True and len(coded.payload) < 0.85 * len(plain.payload)  # measured 0.80
    out = weighted_codec.decode(coded.payload, values.shape, coded.params, coded.raw_length)
    error = np.abs(out - values).reshape(3000, -1).max(axis=1)
    assert error[:1500].max() <= step / 2 + 1e-6  # heavy entries: class 0
    assert error[1500:].max() <= step * 8 / 2 + 1e-6 and error[1500:].max() > step  # light ones: up to class 3
    legacy = {key: value for key, value in plain.params.items() if key != "classes"}
    assert np.array_equal(ShPaletteCodec(4096, (step,)).decode(plain.payload, values.shape, legacy, plain.raw_length),
                          ShPaletteCodec(4096, (step,)).decode(plain.payload, values.shape, plain.params,
                                                               plain.raw_length))  # fmt: skip


def test_hostile_entry_classes_are_refused() -> None:
    from symgs_core.codec.palette import RowWeights
    from symgs_core.codec.section import join_parts, split_all

    values = _sog_like(600, 500, seed=35)
    weights = np.random.default_rng(36).random(600) ** 4
    codec = ShPaletteCodec(1 << 12, (0.025,), RowWeights.of(values, weights))
    coded = codec.encode(values)
    assert coded.params["classes"] is True
    parts = split_all(coded.payload, "t")
    bad_classes = encode_table(np.full((coded.params["size"] - 1, 1), 9))
    for payload in (join_parts(parts[:1] + [bad_classes] + parts[2:]), join_parts(parts[:-1])):
        with pytest.raises(ArchiveError):
            codec.decode(payload, values.shape, coded.params, coded.raw_length)
    with pytest.raises(ArchiveError):
        codec.check(values.shape, {**coded.params, "classes": "yes"}, coded.raw_length)


def test_a_ladder_of_steps_fits_its_palette_once_and_prices_each_rung_as_a_fresh_codec(monkeypatch) -> None:  # noqa: ANN001
    values = _clustered(3000, 8, centres=400, noise=0.02, seed=5)
    rng = np.random.default_rng(1)
    weights = [RowWeights.of(values, 10.0 ** rng.uniform(-4, 0, len(values))) for _ in range(2)]
    fit, fits = palette.fit_palette, []
    monkeypatch.setattr(palette, "fit_palette", lambda rows, size: fits.append(size) or fit(rows, size))
    rungs = [(w, step) for w in weights for step in (0.004, 0.01, 0.04)]
    estimates = [ShPaletteCodec(301, (step,) * 3, w).estimate(values) for w, step in rungs]
    assert fits == [300]  # one k-means for every rung, whichever weights price the entries' classes
    for (w, step), estimate in zip(rungs, estimates):
        palette._fits.clear()
        palette._row_fits.clear()
        codec = ShPaletteCodec(301, (step,) * 3, w)
        fresh = codec.estimate(values.copy())
        assert estimate.bits == fresh.bits and np.array_equal(estimate.decoded, fresh.decoded)
        assert estimate.index is not None and len(estimate.rows) <= 301  # priced per entry
        assert np.array_equal(estimate.decoded, _roundtrip(codec, values)[0])
    assert not np.array_equal(estimates[0].decoded, estimates[3].decoded)  # the weights' classes differ


def test_a_kept_fit_does_not_keep_a_finished_job_s_weights_alive() -> None:
    # A worker's fit cache outlives its jobs; a job's row weights (a million rows' keys) must not.
    values = _clustered(500, 3, centres=100, noise=0.02, seed=6)
    weights = RowWeights.of(values, np.ones(len(values)))
    first = ShPaletteCodec(51, STEPS, weights).estimate(values)
    assert ShPaletteCodec(51, STEPS, weights).estimate(values).bits == first.bits  # from the kept fit
    gone = weakref.ref(weights)
    del weights
    gc.collect()
    assert gone() is None
