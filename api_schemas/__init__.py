"""Pydantic models: the contract between client, API and worker."""

from __future__ import annotations

from .errors import ErrorDetail, ErrorResponse
from .events import JobEvent
from .jobs import (
    TERMINAL_STATES,
    ImagesInfo,
    Job,
    JobError,
    JobLinks,
    JobMetrics,
    JobPage,
    JobState,
    MirrorSummary,
    Queue,
    SceneInfo,
)
from .params import DevicePreference, JobParams, Preset
from .report import GaussianCounts, LevelReport, Report

__all__ = [
    "TERMINAL_STATES",
    "DevicePreference",
    "ErrorDetail",
    "ErrorResponse",
    "GaussianCounts",
    "ImagesInfo",
    "Job",
    "JobError",
    "JobEvent",
    "JobLinks",
    "JobMetrics",
    "JobPage",
    "JobParams",
    "JobState",
    "LevelReport",
    "MirrorSummary",
    "Preset",
    "Queue",
    "Report",
    "SceneInfo",
]
