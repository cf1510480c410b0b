"""What a client may ask of a compression job (the ``params`` part of ``POST /v1/jobs``)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

Preset = Literal["small", "balanced", "high", "lossless"]
DevicePreference = Literal["auto", "cpu", "cuda"]


class JobParams(BaseModel):
    """Compression parameters. Every field is optional: a field left out (or null) takes the pipeline's default,
    which may depend on the preset. Bounds keep one job within a worker's means.

    ``device``: ``cuda`` waits for a GPU worker, ``cpu`` runs on a CPU worker, ``auto`` takes a GPU worker when one
    is alive and a CPU worker otherwise.
    """

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {"preset": "balanced", "psnr_budget": 0.3, "max_levels": 4, "device": "auto"},
                {"preset": "small", "iterations": 20, "train_views": 4, "eval_views": 2, "resolution": 64},
            ]
        },
    )

    preset: Preset | None = Field(None, description="attribute codec and reductions: small, balanced, high, lossless")
    psnr_budget: float | None = Field(
        None, ge=0, le=60, allow_inf_nan=False, description="dB of held-out PSNR the job may cost in total"
    )
    max_levels: int | None = Field(None, ge=0, le=16, description="cap on mirror levels")
    iterations: int | None = Field(None, ge=0, le=20_000, description="optimisation steps per level")
    train_views: int | None = Field(None, ge=1, le=512)
    eval_views: int | None = Field(None, ge=1, le=256)
    resolution: int | None = Field(None, ge=16, le=2048, description="longest side of rendered views, pixels")
    use_mirrors: bool | None = Field(None, description="false: the plain codec only (the baseline)")
    seed: int | None = Field(None, ge=0, le=2**31 - 1)
    device: DevicePreference = "auto"

    def pipeline_overrides(self) -> dict:
        """The fields the client set, as keyword arguments of the pipeline's config (device excluded)."""
        return self.model_dump(exclude={"device"}, exclude_none=True)
