"""Progress events of a job, as relayed by ``GET /v1/jobs/{id}/events`` (Server-Sent Events)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from .jobs import JobState


class JobEvent(BaseModel):
    """The ``data`` of one SSE message. The SSE ``event`` field is ``kind``; its ``id`` is the stream position,
    to send back as ``Last-Event-ID`` to resume after it."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "kind": "progress", "state": "running", "stage": "optimize", "level": 0, "progress": 0.42,
                    "message": "level 0: step 80/200", "eta_s": 57.0, "time": 1767225600.5,
                },  # fmt: skip
                {"kind": "state", "state": "succeeded", "stage": "done", "level": None, "progress": 1.0,
                 "message": "", "time": 1767225642.0},  # fmt: skip
            ]
        }
    )

    kind: Literal["state", "progress"] = Field(description="state: the job changed state; progress: a stage report")
    state: JobState
    stage: str | None = None
    level: int | None = None
    progress: float = Field(ge=0, le=1)
    message: str = ""
    eta_s: float | None = Field(
        None, ge=0, description="estimated seconds until the job ends, from its progress so far; null when unknown"
    )
    time: float = Field(description="Unix time, seconds")
