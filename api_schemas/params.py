"""What a client may ask of a compression job (the ``params`` part of ``POST /v1/jobs``).

Presets and their defaults are decided in one place, ``symgs_core.config``; a field left out takes the value the
preset gives it there, so a job sent here and the same settings given to ``symgs compress`` or ``symgs_core.compress``
write the same archive.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from symgs_core.config import DEFAULT_PRESET, PRESETS, SETTINGS_BY_NAME, DeviceChoice, Preset

DevicePreference = DeviceChoice
_PRESETS_TEXT = "; ".join(f"{name}: {spec.summary}" for name, spec in PRESETS.items())


def _setting(name: str, **more: Any) -> Any:
    """The field of the job setting ``name`` (``symgs_core.config.JOB_SETTINGS``): its bounds and help, None (the
    preset's value) when left out."""
    setting = SETTINGS_BY_NAME[name]
    return Field(None, ge=setting.low, le=setting.high, description=setting.help, **more)


class JobParams(BaseModel):
    """Compression parameters. Every field is optional: a field left out (or null) takes the default of the preset
    (``GET /v1/presets`` lists them). Fields, bounds and help are ``symgs_core.config.JOB_SETTINGS``, which the
    command line's options are made from too; the bounds keep one job within a worker's means.

    ``device``: ``cuda`` waits for a GPU worker, ``cpu`` runs on a CPU worker, ``auto`` takes a GPU worker when one
    is alive and a CPU worker otherwise.
    """

    model_config = ConfigDict(
        extra="forbid",
        strict=True,  # a value of another type is refused, not coerced: true is no count of steps, "7" no seed
        # (psnr_budget excepted: there a string reads as a number, and "nan" is refused as not finite)
        json_schema_extra={
            "examples": [
                {},
                {"preset": "small", "device": "auto"},
                {"preset": "balanced", "iterations": 20, "train_views": 4, "eval_views": 2, "resolution": 64},
            ]
        },
    )

    preset: Preset = Field(DEFAULT_PRESET, description=f"what the job may spend and must keep. {_PRESETS_TEXT}")
    psnr_budget: float | None = _setting("psnr_budget", allow_inf_nan=False, strict=False)
    max_levels: int | None = _setting("max_levels")
    iterations: int | None = _setting("iterations")
    train_views: int | None = _setting("train_views")
    fit_views: int | None = _setting("fit_views")
    eval_views: int | None = _setting("eval_views")
    resolution: int | None = _setting("resolution")
    eval_resolution: int | None = _setting("eval_resolution")
    use_mirrors: bool | None = _setting("use_mirrors")
    seed: int | None = _setting("seed")
    device: DevicePreference = "auto"

    @field_validator("preset", "device", mode="before")
    @classmethod
    def _null_takes_the_default(cls, value: Any, info: ValidationInfo) -> Any:
        # The docstring's promise for every field; the others have None as their default already.
        return cls.model_fields[info.field_name or ""].default if value is None else value

    @field_validator("psnr_budget", mode="before")
    @classmethod
    def _no_boolean_budget(cls, value: Any) -> Any:
        # Not strict, so that "0.5" reads as a number; Python's bools are ints, and true is no number of dB.
        if isinstance(value, bool):
            raise ValueError("a number of dB is expected, not a boolean")
        return value

    def pipeline_overrides(self) -> dict:
        """The preset and the fields the client set, as keyword arguments of ``CompressConfig.for_preset``
        (device excluded: the worker's queue decides it)."""
        return self.model_dump(exclude={"device"}, exclude_none=True)


class PresetInfo(BaseModel):
    """A preset as ``GET /v1/presets`` lists it."""

    model_config = ConfigDict(
        json_schema_extra={"examples": [{"name": "balanced", "psnr_budget": 0.3, "default": True,
                                         "summary": PRESETS["balanced"].summary}]}  # fmt: skip
    )

    name: Preset
    psnr_budget: float = Field(description="dB of PSNR a job of this preset may cost, unless it names its own")
    default: bool = Field(description="the preset of a job that names none")
    summary: str

    @classmethod
    def listing(cls) -> list[PresetInfo]:
        return [cls(name=s.name, psnr_budget=s.budget, default=s.name == DEFAULT_PRESET, summary=s.summary)
                for s in PRESETS.values()]  # fmt: skip
