"""Native grids: positions that already lie on one grid (scenes decoded from .spz) are coded on it, bit for bit, and
cost less than the step asked for; positions that do not keep that step. The grid's step is refined on growing spans
before every value is tested against it, so float32 values on 8000+ cells near magnitude 1 are found."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from symgs_core.codec import morton_codes
from symgs_core.codec.entropy import encode_table
from symgs_core.codec.quantize import GRID_TOLERANCE, PositionCodec, native_grid
from tests.conftest import shared_file

GRID = 1 / 4096


def _roundtrip(codec: PositionCodec, values: np.ndarray) -> tuple[np.ndarray, dict, int]:
    coded = codec.encode(values)
    codec.check(values.shape, coded.params, coded.raw_length)
    return codec.decode(coded.payload, values.shape, coded.params, coded.raw_length), coded.params, len(coded.payload)


def _assert_the_step_asked_for(values: np.ndarray, step: float, tolerance: float) -> None:
    """``values`` coded on ``step`` from their minimum, as without a native grid: error within half a step."""
    out, params, _ = _roundtrip(PositionCodec(step), values)
    assert params["step"] == step
    assert params["origin"] == values.min(axis=0).astype(np.float64).tolist()
    assert np.abs(out - values).max() <= step / 2 + tolerance


def _forced(values: np.ndarray, step: float) -> int:
    """Payload bytes of ``values`` [N, 3] on a ``step`` grid from their minimum: the coding without grid detection."""
    x = values.astype(np.float64)
    return len(encode_table(np.round((x - x.min(axis=0)) / step).astype(np.int64)))


def _on_grid(origin: float, gap: float, n: int = 40000, seed: int = 0) -> np.ndarray:
    """Positions [n, 3] float32 at origin + k * gap for about 10k distinct k per axis, in Morton order."""
    k = np.random.default_rng(seed).integers(-6000, 6000, size=(n, 3))
    values = torch.from_numpy((origin + k * gap).astype(np.float32))
    return values[torch.argsort(morton_codes(values), stable=True)].numpy()


@pytest.mark.parametrize(
    ("origin", "gap"),
    [(0.0, GRID), (0.4 * GRID, GRID), (0.1234, 0.003)],
    ids=["through-zero", "shifted-0.4-cells", "offset-0.003"],
)
def test_positions_on_a_grid_decode_bit_for_bit_and_code_smaller(origin: float, gap: float) -> None:
    values = _on_grid(origin, gap)
    assert min(len(np.unique(values[:, a])) for a in range(3)) > 10000
    step = gap / 4.85  # finer than the grid, as a fitted step on the fox scene is
    out, params, size = _roundtrip(PositionCodec(step), values)
    assert np.array_equal(out, values)
    assert abs(params["step"] / gap - 1) < 1e-7  # the grid, up to float32 precision
    low = values.min(axis=0).astype(np.float64)
    assert np.abs(np.array(params["origin"]) - low).max() <= GRID_TOLERANCE * gap  # the grid point at the minimum
    assert size < 0.95 * _forced(values, step)
    if origin == 0.0:  # float32 holds k / 4096 exactly: the minimum itself is the origin
        assert params["origin"] == low.tolist()


def test_positions_off_the_grid_by_float_noise_keep_the_step_asked_for() -> None:
    values = _on_grid(0.4 * GRID, GRID)
    noisy = (values + np.random.default_rng(1).uniform(-0.01, 0.01, size=values.shape) * GRID).astype(np.float32)
    _assert_the_step_asked_for(noisy, GRID / 4.85, 1e-6)


def test_a_step_three_grid_cells_wide_keeps_whole_multiples_of_the_grid() -> None:
    values = _on_grid(0.4 * GRID, GRID)
    out, params, _ = _roundtrip(PositionCodec(3.2 * GRID), values)  # less than 4x: every 3rd grid value
    assert abs(params["step"] / (3 * GRID) - 1) < 1e-7
    cells = (out.astype(np.float64) - values.min(axis=0)) / GRID
    assert np.abs(cells - 3 * np.round(cells / 3)).max() < 1e-3
    assert np.abs(out.astype(np.float64) - values).max() <= 1.5 * GRID * (1 + 1e-6)


def test_continuous_positions_keep_the_step_asked_for() -> None:
    values = (np.random.default_rng(2).normal(size=(20000, 3)) * 5).astype(np.float32)
    step = 1e-3
    _assert_the_step_asked_for(values, step, 1e-5)
    empty, params, _ = _roundtrip(PositionCodec(step), np.zeros((0, 3), dtype=np.float32))
    assert empty.shape == (0, 3) and (params["origin"], params["step"]) == ([0.0, 0.0, 0.0], step)


def test_axes_on_grids_of_different_steps_keep_the_step_asked_for() -> None:
    k = np.random.default_rng(3).integers(-3000, 3000, size=(20000, 3))
    values = (k * np.array([GRID, 1 / 1000, GRID])).astype(np.float32)
    assert all(native_grid(values[:2000, a].astype(np.float64), 0.0) for a in range(3))  # each axis alone: a grid
    _assert_the_step_asked_for(values, GRID / 3, 1e-6)


def test_the_grid_step_is_refined_before_the_values_are_tested() -> None:
    """4000 float32 values on 8200 cells of a grid shifted off zero near magnitude 1 (the fox's x axis)."""
    rng = np.random.default_rng(4)
    k = np.concatenate([[0, 1, 8199], rng.choice(np.arange(2, 8199), size=3997, replace=False)])
    values = ((k + 0.4) / 4096 - 0.9945).astype(np.float32).astype(np.float64)
    unique = np.unique(values)
    rough = (unique - unique[0]) / np.diff(unique).min()
    assert np.abs(rough - np.round(rough)).max() > 0.1  # the smallest difference alone misses the far cells
    step, origin = native_grid(values, 0.0)
    assert abs(step / GRID - 1) < 1e-7
    assert origin == unique[0]
    step, _ = native_grid(values, 2.5 * GRID)
    assert abs(step / (2 * GRID) - 1) < 1e-7


def test_the_fox_scene_positions_decode_bit_for_bit_below_the_fitted_step_cost() -> None:
    from symgs_core.ply import load_scene

    means = load_scene(shared_file("fox_cc0_mujoco_warp/fox_graphdeco_sanitized.ply")).means
    values = means[torch.argsort(morton_codes(means), stable=True)].numpy()
    step = 5.03e-5  # the step fitted for this scene
    out, params, size = _roundtrip(PositionCodec(step), values)
    assert np.array_equal(out, values)
    assert params["step"] == GRID
    assert size < 0.92 * _forced(values, step)
