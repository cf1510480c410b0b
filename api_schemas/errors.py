"""The error body every 4xx/5xx answer carries: ``{"error": {"code": "...", "message": "..."}}``."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class ErrorDetail(BaseModel):
    code: str = Field(description="machine-readable reason, e.g. bad_sh_count, upload_too_large, not_found")
    message: str = Field(description="what went wrong, for people")


class ErrorResponse(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {"error": {"code": "bad_sh_count", "message": "scene.ply: 10 f_rest properties match no SH degree"}}
            ]
        }
    )

    error: ErrorDetail
