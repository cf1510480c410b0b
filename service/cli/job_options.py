"""A job's settings as command-line options, made from the one table of them (``symgs_core.config.JOB_SETTINGS``),
which the API's ``JobParams`` is made from too: `symgs compress` takes every one, `symgs bench` those it does not
vary itself. Left out, each takes the preset's value."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from symgs_core.config import JOB_SETTINGS, SETTINGS_BY_NAME, Setting

from .parser import CliError


def _settings(names: Sequence[str] | None) -> tuple[Setting, ...]:
    return JOB_SETTINGS if names is None else tuple(SETTINGS_BY_NAME[name] for name in names)


def add_job_options(parser: argparse.ArgumentParser, names: Sequence[str] | None = None) -> None:
    """An option for each setting of ``names`` (None: all); a flag turns a setting that is on by default off."""
    for setting in _settings(names):
        if setting.kind is bool:
            parser.add_argument(setting.option, dest=setting.name, action="store_const", const=False,
                                help=setting.help)  # fmt: skip
        else:
            parser.add_argument(setting.option, dest=setting.name, type=setting.kind, help=setting.help)


def job_overrides(args: argparse.Namespace, names: Sequence[str] | None = None) -> dict[str, object]:
    """The settings of ``names`` (None: all) given on the command line, each within its bounds (an error names the
    option); those left out are None."""
    given = {setting.name: getattr(args, setting.name) for setting in _settings(names)}
    for setting in _settings(names):
        value = given[setting.name]
        if value is not None and setting.kind is int and not setting.holds(value):
            raise CliError(f"{setting.option} must be in {setting.bounds}, got {value}")
    return given
