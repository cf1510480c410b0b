"""The metrics report of a finished job, as the pipeline writes it (``GET /v1/jobs/{id}/report``)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class LevelReport(BaseModel):
    """One mirror level, accepted or rolled back."""

    model_config = ConfigDict(extra="allow")

    level: int
    normal: list[float] = Field(min_length=3, max_length=3, description="unit normal n of the plane n.x = offset")
    offset: float
    votes: float
    left: int = Field(description="Gaussians kept and reflected")
    right: int = Field(description="Gaussians dropped because the reflection covers them")
    coverage: float
    psnr_before: float | None = Field(description="dB; null when infinite")
    psnr_after: float | None
    ssim: float | None
    seconds: float
    accepted: bool


class GaussianCounts(BaseModel):
    input: int
    stored: int
    decoded: int


class Report(BaseModel):
    """Sizes in bytes, PSNR in dB, times in seconds."""

    model_config = ConfigDict(
        extra="allow",
        json_schema_extra={
            "examples": [
                {
                    "input_bytes": 1_240_000,
                    "output_bytes": 81_000,
                    "baseline_bytes": 122_000,
                    "ratio_to_ply": 15.3,
                    "ratio_to_baseline": 1.51,
                    "gaussians": {"input": 5000, "stored": 2600, "decoded": 5000},
                    "levels": [
                        {
                            "level": 0, "normal": [1.0, 0.0, 0.0], "offset": 0.0, "votes": 812.0, "left": 2400,
                            "right": 2400, "coverage": 0.96, "psnr_before": 38.2, "psnr_after": 41.0, "ssim": 0.991,
                            "seconds": 3.1, "accepted": True,
                        }  # fmt: skip
                    ],
                    "psnr": 41.0,
                    "ssim": 0.991,
                    "psnr_reference": "renders of the input",
                    "seconds": {"load": 0.1, "detect": 0.4, "optimize": 3.1, "encode": 0.2},
                    "device": "cpu",
                    "config": {"preset": "balanced", "psnr_budget": 0.5},
                }
            ]
        },
    )

    input_bytes: int
    output_bytes: int
    baseline_bytes: int
    ratio_to_ply: float
    ratio_to_baseline: float
    gaussians: GaussianCounts
    levels: list[LevelReport]
    psnr: float | None = Field(description="dB of the decoded scene; null when infinite")
    ssim: float | None
    psnr_reference: Literal["renders of the input", "test images"] | str
    seconds: dict[str, float]
    device: str
    config: dict
