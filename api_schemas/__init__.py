"""Pydantic models: the contract between client, API and worker."""

from __future__ import annotations

from .errors import ErrorDetail, ErrorResponse
from .events import JobEvent
from .jobs import (
    JOB_STATES,
    QUEUES,
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
from .params import DevicePreference, JobParams, Preset, PresetInfo
from .report import (
    Cameras,
    CameraSet,
    CodecReport,
    Fidelity,
    GaussianCounts,
    LevelReport,
    PhotoScale,
    Report,
    ReportConfig,
    StageReport,
    Steps,
)

__all__ = [
    "TERMINAL_STATES",
    "CameraSet",
    "Cameras",
    "CodecReport",
    "DevicePreference",
    "ErrorDetail",
    "ErrorResponse",
    "Fidelity",
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
    "PhotoScale",
    "Preset",
    "PresetInfo",
    "Queue",
    "QUEUES",
    "JOB_STATES",
    "Report",
    "ReportConfig",
    "SceneInfo",
    "StageReport",
    "Steps",
]
