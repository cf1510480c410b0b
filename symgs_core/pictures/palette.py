"""Colours of mirror levels, shared by every picture (and, in the same order, by the dashboard's mirror table).

Okabe-Ito hues, readable for the common colour-vision deficiencies, ordered so the first levels show well both on
a render's dark background and on a chart's white one."""

from __future__ import annotations

LEVEL_COLOURS = ["#E69F00", "#56B4E9", "#009E73", "#CC79A7", "#F0E442", "#D55E00", "#0072B2", "#FFFFFF"]
NEUTRAL = "#7F7F7F"  # rolled-back levels and stage bands


def level_colour(level: int) -> str:
    """The colour of mirror level ``level`` (they repeat after eight)."""
    if level < 0:
        raise ValueError(f"level must be non-negative, got {level}")
    return LEVEL_COLOURS[level % len(LEVEL_COLOURS)]

# Methods in the charts that compare formats: ours in the level-0 orange (the job charts' evaluated star), the
# peers in colours of their own, with a marker each (none that the job charts give their own points), so that the
# same format looks the same in every chart.
METHOD_STYLES = {
    "symgs": ("#E07A1F", "o"),
    "symgs no mirrors": ("#3D5A80", "o"),
    "splat-transform spz v3": ("#009E73", "d"),
    "splat-transform spz v4": ("#56B4E9", "8"),
    "splat-transform compressed ply": ("#CC79A7", "^"),
    "splat-transform sog": ("#6A3D9A", "<"),
    "float16 ply + zstd": ("#555555", "p"),
}


def method_style(method: str) -> tuple[str, str]:
    """(colour, marker) of a method; unknown ones are grey crosses."""
    return METHOD_STYLES.get(method, (NEUTRAL, "x"))
