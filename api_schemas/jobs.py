"""A compression job as clients see it (``GET /v1/jobs/{id}``) and pages of jobs (``GET /v1/jobs``)."""

from __future__ import annotations

from typing import Literal, get_args

from pydantic import BaseModel, ConfigDict, Field

from .params import JobParams

JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
JOB_STATES: tuple[JobState, ...] = get_args(JobState)
TERMINAL_STATES: frozenset[str] = frozenset({"succeeded", "failed", "cancelled"})
Queue = Literal["gpu", "cpu"]
QUEUES: tuple[Queue, ...] = get_args(Queue)  # the workers' queues: a GPU worker's and a CPU worker's


class JobError(BaseModel):
    code: str = Field(
        description="machine-readable: bad_sh_count, bad_dataset, time_limit, worker_lost, storage_unavailable, ..."
    )
    message: str


class MirrorSummary(BaseModel):
    """An accepted mirror level: the plane n.x = offset and what it saved."""

    level: int
    normal: list[float] = Field(min_length=3, max_length=3)
    offset: float
    left: int
    right: int
    psnr_after: float | None


class JobMetrics(BaseModel):
    """Headline figures of a finished job; the full report is at ``/v1/jobs/{id}/report``."""

    input_bytes: int
    output_bytes: int
    ratio_to_ply: float
    ratio_to_baseline: float
    psnr: float | None = Field(description="dB on the evaluation cameras, full frame; null when infinite")
    psnr_object: float | None = Field(None, description="dB on the evaluation cameras, the object's own pixels")
    ssim: float | None
    seconds: float = Field(description="pipeline time, all stages")
    notes: list[str] = Field(default_factory=list,
                             description="what the user could do for a better result (the report's notes)")


class JobLinks(BaseModel):
    self: str
    events: str
    result: str = Field(description="the .symgs archive")
    report: str
    scene: str = Field(description="the scene as uploaded (.ply)")
    exports: dict[str, str] = Field(description="the decoded scene in each export format, by format name")


class SceneInfo(BaseModel):
    filename: str
    bytes: int
    gaussians: int
    sh_degree: int


class ImagesInfo(BaseModel):
    layout: Literal["nerf_synthetic", "colmap"]
    images: int
    bytes: int = Field(description="extracted size")


class Job(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "id": "3f2c9a1e0b7d4c55a8e6f1d2c3b4a596",
                    "state": "running",
                    "stage": "optimize",
                    "level": 0,
                    "progress": 0.42,
                    "message": "level 0: step 80/200",
                    "eta_s": 57.0,
                    "params": {"preset": "balanced", "psnr_budget": 0.3, "max_levels": 4, "device": "auto"},
                    "queue": "cpu",
                    "scene": {"filename": "chair.ply", "bytes": 1240000, "gaussians": 5000, "sh_degree": 3},
                    "images": None,
                    "mirrors": [],
                    "metrics": None,
                    "artifacts": [],
                    "error": None,
                    "attempts": 1,
                    "cancel_requested": False,
                    "created_at": 1767225600.0,
                    "started_at": 1767225601.2,
                    "finished_at": None,
                    "updated_at": 1767225620.9,
                    "links": {
                        "self": "/v1/jobs/3f2c9a1e0b7d4c55a8e6f1d2c3b4a596",
                        "events": "/v1/jobs/3f2c9a1e0b7d4c55a8e6f1d2c3b4a596/events",
                        "result": "/v1/jobs/3f2c9a1e0b7d4c55a8e6f1d2c3b4a596/result",
                        "report": "/v1/jobs/3f2c9a1e0b7d4c55a8e6f1d2c3b4a596/report",
                        "scene": "/v1/jobs/3f2c9a1e0b7d4c55a8e6f1d2c3b4a596/scene",
                        "exports": {
                            "ply": "/v1/jobs/3f2c9a1e0b7d4c55a8e6f1d2c3b4a596/result.ply",
                            "spz": "/v1/jobs/3f2c9a1e0b7d4c55a8e6f1d2c3b4a596/result.spz",
                        },
                    },
                }
            ]
        }
    )

    id: str
    state: JobState
    stage: str | None = Field(None, description="pipeline stage: load, views, detect, optimize, evaluate, encode, ...")
    level: int | None = Field(None, description="mirror level being worked on")
    progress: float = Field(ge=0, le=1)
    message: str = Field("", description="what the job is doing; once it has succeeded, the export formats its scene "
                         "could not be written in and why (empty when every one was)")
    eta_s: float | None = Field(
        None, ge=0, description="estimated seconds until a running job ends, from its progress so far; null when "
        "unknown or not running",
    )
    params: JobParams
    queue: Queue
    scene: SceneInfo
    images: ImagesInfo | None = None
    mirrors: list[MirrorSummary] = Field(default_factory=list, description="accepted mirror levels")
    metrics: JobMetrics | None = None
    artifacts: list[str] = Field(
        default_factory=list,
        description="result files of a succeeded job: result.symgs, report.json, charts/<name>.png and "
        "result<extension> for each export format",
    )
    error: JobError | None = None
    attempts: int = Field(0, description="runs started; above 1 when a worker was lost and the job resumed")
    cancel_requested: bool = False
    created_at: float = Field(description="Unix time, seconds")
    started_at: float | None = None
    finished_at: float | None = None
    updated_at: float
    links: JobLinks


class JobPage(BaseModel):
    """Jobs newest first. Ask for the next page with ``offset=next_offset`` until it is null."""

    model_config = ConfigDict(
        json_schema_extra={"examples": [{"items": [], "total": 0, "offset": 0, "limit": 20, "next_offset": None}]}
    )

    items: list[Job]
    total: int
    offset: int
    limit: int
    next_offset: int | None

