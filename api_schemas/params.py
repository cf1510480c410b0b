"""What a client may ask of a compression job (the ``params`` part of ``POST /v1/jobs``)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

Preset = Literal["small", "balanced", "high", "lossless"]
DevicePreference = Literal["auto", "cpu", "cuda"]


class JobParams(BaseModel):
    """Compression parameters; every field is optional. Bounds keep one job within a worker's means.

    ``device``: ``cuda`` waits for a GPU worker, ``cpu`` runs on a CPU worker, ``auto`` takes a GPU worker when one
    is alive and a CPU worker otherwise.
    """

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {"preset": "balanced", "psnr_budget": 0.5, "max_levels": 4, "device": "auto"},
                {"preset": "small", "iterations": 20, "train_views": 4, "eval_views": 2, "resolution": 64},
            ]
        },
    )

    preset: Preset = "balanced"
    psnr_budget: float = Field(0.5, ge=0, le=20, description="dB of held-out PSNR the mirrors may cost in total")
    max_levels: int = Field(4, ge=0, le=16, description="cap on mirror levels")
    iterations: int = Field(200, ge=0, le=20_000, description="optimisation steps per level")
    train_views: int = Field(24, ge=1, le=512)
    eval_views: int = Field(8, ge=1, le=256)
    resolution: int = Field(192, ge=16, le=2048, description="longest side of rendered views, pixels")
    use_mirrors: bool = Field(True, description="false: the plain codec only (the baseline)")
    seed: int = Field(0, ge=0, le=2**31 - 1)
    device: DevicePreference = "auto"
