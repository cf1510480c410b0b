"""The PSNR axis of every chart: finite, lossless points apart; the job's charts with the peers beside its points."""

from __future__ import annotations

import math

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from symgs_core.pictures import rate_distortion_png, speed_accuracy_png
from symgs_core.pictures.axes import LOSSLESS_DB, LOSSLESS_LABEL, psnr_axis
from symgs_core.pictures.charts import PeerPoint
from tests.unit.test_pictures import plain_report, png


def axes():  # noqa: ANN201 - matplotlib Axes
    fig = Figure()
    FigureCanvasAgg(fig)
    return fig.add_subplot()


def test_the_axis_covers_the_finite_figures_and_draws_lossless_apart() -> None:
    ax = axes()
    y = psnr_axis(ax, [38.0, 52.0, math.inf, None, LOSSLESS_DB + 40.0])
    lo, hi = ax.get_ylim()
    assert math.isfinite(hi) and lo < 38.0 and 52.0 < hi < 60.0  # not stretched to the near-lossless 140 dB
    assert y(math.inf) == y(None) == y(LOSSLESS_DB + 40.0) and 52.0 < y(math.inf) < hi
    assert y(45.0) == 45.0
    labels = [t.get_text() for t in ax.get_yticklabels()]
    assert labels[-1] == LOSSLESS_LABEL and all(t.replace(".", "").isdigit() for t in labels[:-1])


def test_the_axis_without_lossless_points_is_the_finite_range_alone() -> None:
    ax = axes()
    y = psnr_axis(ax, [40.0, 41.0], floor=39.5)
    lo, hi = ax.get_ylim()
    assert lo < 39.5 and 41.0 < hi < 43.0 and y(40.5) == 40.5
    assert LOSSLESS_LABEL not in [t.get_text() for t in ax.get_yticklabels()]


def test_job_charts_draw_the_peers() -> None:
    peers = [PeerPoint("splat-transform spz v3", 5000, 45.0, 0.7), PeerPoint("float16 ply + zstd", 9000, None, 0.01)]
    for draw in (rate_distortion_png, speed_accuracy_png):
        plain, compared = draw(plain_report()), draw(plain_report(), peers=peers)
        assert png(compared).size == png(plain).size == (820, 420) and compared != plain
