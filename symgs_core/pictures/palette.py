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
