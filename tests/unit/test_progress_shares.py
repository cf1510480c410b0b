"""The job's progress bar: each stage's share follows the time it takes, so the time left estimated from the bar's
pace holds from stage to stage, and the mirror levels fill their share without knowing how many will run."""

from __future__ import annotations

import pytest

from symgs_core.config import CompressConfig
from symgs_core.pipeline.job import STAGES, Reporter, level_share, stage_shares


def width(shares: dict[str, tuple[float, float]], stage: str) -> float:
    lo, hi = shares[stage]
    return hi - lo


@pytest.mark.parametrize("preset", ["fast", "small", "balanced", "high", "lossless"])
@pytest.mark.parametrize("photographs", [False, True])
def test_the_shares_tile_the_bar_in_stage_order(preset: str, photographs: bool) -> None:
    shares = stage_shares(CompressConfig.for_preset(preset), photographs)
    assert list(shares) == list(STAGES)
    ends = [0.0] + [shares[stage][1] for stage in STAGES]
    assert [shares[stage][0] for stage in STAGES] == ends[:-1]
    assert ends == sorted(ends) and ends[-1] == pytest.approx(1.0)


def test_stages_a_job_skips_take_none_of_the_bar() -> None:
    fast = stage_shares(CompressConfig.for_preset("fast"), photographs=True)
    assert width(fast, "refine") == 0.0 and width(fast, "levels") == 0.0
    plain = stage_shares(CompressConfig.for_preset(), photographs=False)
    assert width(plain, "refine") == 0.0
    no_mirrors = stage_shares(CompressConfig.for_preset(use_mirrors=False), photographs=False)
    assert width(no_mirrors, "levels") == 0.0
    untuned = CompressConfig.for_preset(iterations=0)
    assert stage_shares(untuned, photographs=True) == stage_shares(untuned, photographs=False)


def test_fine_tunes_on_photographs_take_the_bar_that_their_steps_take_of_the_time() -> None:
    # Without photographs the codec's fit is most of a job; with them, the fine-tunes (the upload's, then each
    # level's), and the more steps they may run, the more of the bar.
    plain = stage_shares(CompressConfig.for_preset(), photographs=False)
    assert max(STAGES, key=lambda s: width(plain, s)) == "codec"
    photos = stage_shares(CompressConfig.for_preset(), photographs=True)
    assert width(photos, "refine") + width(photos, "levels") > 0.9
    assert width(photos, "codec") < width(plain, "codec") / 10
    shorter = stage_shares(CompressConfig.for_preset(iterations=400), photographs=True)
    assert width(shorter, "refine") < width(photos, "refine")


def test_each_level_fills_half_of_what_the_levels_before_it_left() -> None:
    assert level_share(0, 0.0) == 0.0 and level_share(0, 1.0) == 0.5
    assert level_share(1, 0.0) == 0.5 and level_share(1, 0.5) == 0.625 and level_share(1, 1.0) == 0.75
    points = [level_share(level, within / 10) for level in range(16) for within in range(11)]
    assert points == sorted(points) and points[-1] < 1.0
    assert level_share(3, -1.0) == level_share(3, 0.0) and level_share(3, 2.0) == level_share(4, 0.0)


def test_a_stage_reports_within_its_own_share() -> None:
    config = CompressConfig.for_preset()
    shares = stage_shares(config, photographs=True)
    events: list[float] = []
    reporter = Reporter(lambda e: events.append(e.fraction), None, shares)
    reporter("refine", 0.5, "half the fine-tune")
    lo, hi = shares["refine"]
    assert events == [pytest.approx((lo + hi) / 2)]
    reporter("codec", 1.0, "a stage run again after the bar passed it")  # the bar never moves back
    reporter("levels", level_share(1, 0.0), "level 1")
    lo, hi = shares["levels"]
    assert events[1] == events[0] and events[2] == pytest.approx((lo + hi) / 2)
    assert Reporter(None, None).shares == stage_shares(config, photographs=False)
