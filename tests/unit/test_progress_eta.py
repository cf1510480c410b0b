"""The estimate of the time left that the CLI, the job's events and the dashboard show, against exact oracles."""

from __future__ import annotations

import pytest

from symgs_core.progress import Eta, format_seconds


def feed(eta: Eta, samples: list[tuple[float, float]]) -> list[float | None]:
    return [eta.update(f, t) for t, f in samples]


def test_constant_rate_gives_the_exact_time_left():
    eta = Eta(window_s=30.0, min_elapsed_s=2.0)
    out = feed(eta, [(t, t / 200) for t in range(0, 201)])  # 200 s job, 0.5% per second
    assert out[:2] == [None, None]  # too early to tell
    for t in range(2, 200):
        assert out[t] == pytest.approx(200 - t, rel=1e-9)
    assert out[200] == 0.0


def test_a_rate_change_is_followed_once_the_window_has_passed_it():
    # 1% per second for 40 s, then 0.25% per second: the time left is (1 - f) / rate over the last window.
    f = lambda t: t / 100 if t <= 40 else 0.4 + (t - 40) / 400  # noqa: E731
    eta = Eta(window_s=20.0, min_elapsed_s=0.0)
    out = feed(eta, [(t, f(t)) for t in range(0, 200)])
    assert out[30] == pytest.approx((1 - 0.3) / 0.01)
    for t in (50, 55):  # the window straddles the change: its mean rate
        rate = (f(t) - f(t - 20)) / 20
        assert out[t] == pytest.approx((1 - f(t)) / rate)
    assert out[60] == pytest.approx((1 - f(60)) / 0.0025)
    assert out[150] == pytest.approx((1 - f(150)) / 0.0025) == pytest.approx(280 - 150)  # done at t = 40 + 0.6 / 0.0025


def test_uneven_sampling_uses_the_newest_report_at_the_windows_start():
    eta = Eta(window_s=10.0, min_elapsed_s=0.0)
    feed(eta, [(0.0, 0.0), (4.0, 0.1), (7.0, 0.2), (13.0, 0.3)])
    # window start is 3.0: the newest report at or before it is t=0 (f=0), so the rate is 0.3 / 13
    assert eta.update(0.3, 13.0) == pytest.approx(0.7 * 13 / 0.3)
    # at t=15 the window starts at 5.0: the newest report at or before it is t=4 (f=0.1)
    assert eta.update(0.4, 15.0) == pytest.approx(0.6 * (15 - 4) / (0.4 - 0.1))


def test_no_estimate_without_progress_and_fractions_never_move_back():
    eta = Eta(window_s=10.0, min_elapsed_s=1.0, min_progress=0.01)
    assert feed(eta, [(0, 0.2), (5, 0.2), (6, 0.205)]) == [None, None, None]  # not enough progress yet
    assert eta.update(0.3, 10) == pytest.approx(0.7 * 10 / 0.1)
    assert eta.update(0.1, 20) is None  # a stall over the whole window (0.1 counts as 0.3): unknown, not infinite
    assert eta.update(0.5, 25) == pytest.approx(0.5 * (25 - 10) / 0.2)
    assert eta.update(1.0, 26) == 0.0


def test_between_reports_the_estimate_sees_the_stage_slowing_down():
    eta = Eta(window_s=20.0, min_elapsed_s=0.0)
    feed(eta, [(t, t / 100) for t in range(0, 51)])  # 1% per second, then silence at 50%
    assert eta.estimate(50.0) == pytest.approx(50.0)
    # at 60 s the window starts at 40 s (40%): 10% in 20 s
    assert eta.estimate(60.0) == pytest.approx(0.5 / (0.1 / 20))
    assert eta.estimate(65.0) == pytest.approx(0.5 / (0.05 / 20))  # window from 45 s (45%)
    assert eta.estimate(70.5) is None  # no progress over a whole window
    assert Eta().estimate(3.0) is None  # nothing reported yet


def test_bad_settings_are_refused():
    with pytest.raises(ValueError):
        Eta(window_s=0.0)


@pytest.mark.parametrize(
    ("seconds", "text"),
    [(None, "-:--"), (0, "0:00"), (0.2, "0:01"), (59, "0:59"), (61, "1:01"), (3600, "1:00:00"), (3723.5, "1:02:04")],
)
def test_format_seconds(seconds, text):
    assert format_seconds(seconds) == text
