"""``CompressConfig`` refuses, when it is built, every setting that would otherwise fail or mislead later: each
ValueError names the setting."""

from __future__ import annotations

import math

import pytest

from symgs_core.config import CompressConfig


@pytest.mark.parametrize("nominal", [math.nan, math.inf, -math.inf, -1000.0, 0.0, 61.0, "30"])
def test_a_nominal_psnr_that_is_no_psnr_is_refused(nominal: object) -> None:
    with pytest.raises(ValueError, match="nominal_psnr must be a number of dB in"):
        CompressConfig.for_preset("balanced", nominal_psnr=nominal)
    assert math.isfinite(CompressConfig.for_preset("balanced", nominal_psnr=27.5).self_supervised_floor())


@pytest.mark.parametrize(("name", "value"), [("seed", -1), ("seed", 2**31), ("iterations", 1.5), ("eval_views", "8")])
def test_integer_settings_are_integers_in_range(name: str, value: object) -> None:
    with pytest.raises(ValueError, match=f"{name} must be in "):
        CompressConfig.for_preset("fast", **{name: value})


def test_detect_overrides_are_checked_when_the_settings_are_built() -> None:
    with pytest.raises(ValueError, match="unknown detect settings junk; known: colour_bins, .*min_coverage"):
        CompressConfig.for_preset("fast", detect={"junk": 1})
    with pytest.raises(ValueError, match="detect setting min_coverage must be a number, got 'x'"):
        CompressConfig.for_preset("fast", detect={"min_coverage": "x"})
    with pytest.raises(ValueError, match="detect setting candidates must be an integer, got 2.5"):
        CompressConfig.for_preset("fast", detect={"candidates": 2.5})
    with pytest.raises(ValueError, match="min_coverage must be in"):  # DetectConfig's own ranges
        CompressConfig.for_preset("fast", detect={"min_coverage": 2.0})
    with pytest.raises(ValueError, match="detect must be a dict"):
        CompressConfig.for_preset("fast", detect=[("min_coverage", 0.2)])
    given = {"min_coverage": 0.2, "max_pair_distance": None, "candidates": 2}
    assert CompressConfig.for_preset("fast", detect=given).detect == given
