"""The peers on a job's upload, drawn into its charts when PlayCanvas splat-transform is installed on the worker.

Optional and bounded: ``SYMGS_PEER_SECONDS`` caps the time (0 turns it off), and a job never fails because of it;
without the tool, or when nothing finishes in time, the job keeps its own charts.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from symgs_core.report import Report

log = logging.getLogger(__name__)


def peer_charts(scene: Path, images: Path | None, report: Report, *, seconds: float, work: Path) -> dict[str, bytes]:
    """The job's rate-distortion and speed-accuracy charts redrawn with the peers beside its own points; empty when
    there are none to draw."""
    from symgs_core.bench import splat_transform

    exe = splat_transform.find()
    if seconds <= 0 or exe is None:
        return {}
    from symgs_core.bench.upload import peer_points
    from symgs_core.pictures import rate_distortion_png, speed_accuracy_png

    try:
        points = peer_points(scene, report, exe=exe, seconds=seconds, work=work, images=images)
    except Exception:  # noqa: BLE001 - the comparison decorates the charts; it must never fail the job
        log.warning("peers on the upload failed; the job keeps its own charts", exc_info=True)
        return {}
    if not points:
        return {}
    return {"rate_distortion": rate_distortion_png(report, peers=points),
            "speed_accuracy": speed_accuracy_png(report, peers=points)}  # fmt: skip
