"""One contract for a job: every door takes its settings from ``CompressConfig.for_preset``, and the report that the
core produces is the one the API documents, field for field."""

from __future__ import annotations

import dataclasses
import math
import typing

import pytest
from pydantic import BaseModel

import api_schemas
from api_schemas import JobParams
from service.cli.bench import BENCH_SETTINGS
from service.cli.codec import config_from_args
from service.cli.job_options import job_overrides
from service.cli.parser import CliError, build_parser
from symgs_core import report as core
from symgs_core.config import (
    DEFAULT_PRESET,
    JOB_SETTINGS,
    PRESET_NAMES,
    PRESETS,
    CompressConfig,
    Setting,
    budget_for_floor,
    floor_for_budget,
)

from ._samples import sample_report


def test_the_default_is_one_preset_whichever_door() -> None:
    python = CompressConfig.for_preset()
    assert python == CompressConfig() and python.preset == DEFAULT_PRESET == "balanced"
    assert python.budget == PRESETS["balanced"].budget == 0.3
    http = CompressConfig.for_preset(**JobParams().pipeline_overrides())
    cli = config_from_args(build_parser().parse_args(["compress", "s.ply", "-o", "s.symgs"]))
    assert http == python
    assert dataclasses.replace(cli, pictures=True) == python  # the CLI draws pictures only when asked to


def test_a_preset_named_without_a_budget_gets_the_presets_budget() -> None:
    for name in PRESET_NAMES:
        via_http = CompressConfig.for_preset(**JobParams(preset=name).pipeline_overrides())
        via_cli = config_from_args(build_parser().parse_args(["compress", "s.ply", "-o", "o", "--preset", name]))
        assert via_http.budget == via_cli.budget == CompressConfig(preset=name).budget == PRESETS[name].budget
    with pytest.raises(ValueError, match="unknown settings"):
        CompressConfig.for_preset(budget=0.3)
    with pytest.raises(ValueError, match="psnr_budget"):
        CompressConfig.for_preset(psnr_budget=math.nan)


def test_budget_and_floor_convert_both_ways() -> None:
    assert floor_for_budget(0.3, 30.0) == pytest.approx(41.46, abs=0.01)
    assert floor_for_budget(0.0, 30.0) == math.inf
    for budget in (0.05, 0.3, 1.0, 3.0):
        assert budget_for_floor(floor_for_budget(budget, 30.0), 30.0) == pytest.approx(budget)


def test_one_preset_list() -> None:
    assert typing.get_args(JobParams.model_fields["preset"].annotation) == PRESET_NAMES
    compress = next(a for a in build_parser()._subparsers._group_actions[0].choices["compress"]._actions  # noqa: SLF001
                    if a.dest == "preset")  # fmt: skip
    assert tuple(compress.choices) == PRESET_NAMES and compress.default == DEFAULT_PRESET


def _options(command: str) -> dict[str, typing.Any]:
    """The options of a ``symgs`` command by destination."""
    parser = build_parser()._subparsers._group_actions[0].choices[command]  # noqa: SLF001
    return {a.dest: a for a in parser._actions}  # noqa: SLF001


def _taken(setting: Setting, value: float) -> dict[str, bool]:
    """Whether each door takes ``value`` for ``setting``."""
    doors = {}
    for door, attempt in (
        ("python", lambda: CompressConfig.for_preset(**{setting.name: value})),
        ("http", lambda: CompressConfig.for_preset(**JobParams(**{setting.name: value}).pipeline_overrides())),
        ("compress", lambda: config_from_args(build_parser().parse_args(
            ["compress", "s.ply", "-o", "o", setting.option, str(value)]))),
        ("bench", lambda: CompressConfig.for_preset(**job_overrides(build_parser().parse_args(
            ["bench", "s.ply", "--out", "o", setting.option, str(value)]), BENCH_SETTINGS))),
    ):  # fmt: skip
        if door == "bench" and setting.name not in BENCH_SETTINGS:
            continue
        try:
            attempt()
            doors[door] = True
        except (ValueError, CliError):  # pydantic's ValidationError is a ValueError
            doors[door] = False
    return doors


def test_every_door_takes_the_one_table_of_settings() -> None:
    """``CompressConfig``, ``JobParams`` and the options of `symgs compress` and `symgs bench` are made from
    ``JOB_SETTINGS``: the same names, the preset's value where a setting is left out, the same help, and the same
    bounds (a value at a bound is taken by every door, one past it by none)."""
    names = [s.name for s in JOB_SETTINGS]
    assert set(names) <= {f.name for f in dataclasses.fields(CompressConfig)}
    assert list(JobParams.model_fields) == ["preset", *names, "device"]
    compress, bench = _options("compress"), _options("bench")
    assert set(BENCH_SETTINGS) <= set(names) and not {*names} - {*BENCH_SETTINGS} & set(bench)
    for setting in JOB_SETTINGS:
        field = JobParams.model_fields[setting.name]
        assert field.default is None and field.description == setting.help
        for command in (compress, bench) if setting.name in BENCH_SETTINGS else (compress,):
            option = command[setting.name]
            assert option.option_strings == [setting.option] and option.default is None
            assert option.help == setting.help
        if setting.kind is bool:  # a flag on the command line, which turns the setting off
            via_cli = config_from_args(build_parser().parse_args(["compress", "s.ply", "-o", "o", setting.option]))
            via_http = CompressConfig.for_preset(**JobParams(**{setting.name: False}).pipeline_overrides())
            assert getattr(via_cli, setting.name) is getattr(via_http, setting.name) is False
            continue
        assert setting.low is not None and setting.high is not None
        for value, held in ((setting.low, True), (setting.high, True), (setting.low - 1, False),
                            (setting.high + 1, False)):  # fmt: skip
            doors = _taken(setting, value)
            assert set(doors.values()) == {held}, (setting.name, value, doors)


def _fields_of(annotation: typing.Any) -> type | None:
    """The dataclass or model a field holds (directly, optionally, or as a sequence of them)."""
    if isinstance(annotation, type) and (dataclasses.is_dataclass(annotation) or issubclass(annotation, BaseModel)):
        return annotation
    for arg in typing.get_args(annotation):
        found = _fields_of(arg)
        if found is not None:
            return found
    return None


def _compare(dataclass: type, model: type[BaseModel], where: str) -> None:
    hints = typing.get_type_hints(dataclass)
    ours = [f.name for f in dataclasses.fields(dataclass)]
    assert ours == list(model.model_fields), f"{where}: {ours} against {list(model.model_fields)}"
    for name in ours:
        nested = _fields_of(hints[name])
        if nested is not None and dataclasses.is_dataclass(nested):
            mirrored = _fields_of(model.model_fields[name].annotation)
            assert mirrored is not None, f"{where}.{name} holds {nested.__name__}, the schema a plain value"
            _compare(nested, mirrored, f"{where}.{name}")


def test_the_api_report_mirrors_the_core_report_field_for_field() -> None:
    _compare(core.Report, api_schemas.Report, "Report")


def test_a_core_report_validates_against_the_api_schema() -> None:
    data = sample_report().as_json()
    parsed = api_schemas.Report.model_validate(data)
    assert parsed.model_dump(mode="json") == data
    assert parsed.fidelity.psnr is None  # an infinite PSNR travels as null
