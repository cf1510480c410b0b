"""The peers on a job's upload, drawn into its charts when PlayCanvas splat-transform is installed on the worker.

Optional and bounded: ``SYMGS_PEER_SECONDS`` caps the time (0 turns it off), and a job never fails because of it;
without the tool, or when nothing finishes in time, the job's charts show its own points alone.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from symgs_core.pictures.charts import PeerPoint
    from symgs_core.report import Report

log = logging.getLogger(__name__)


def upload_peers(scene: Path, images: Path | None, report: Report, *, seconds: float, work: Path) -> list[PeerPoint]:
    """Each peer that finished within ``seconds`` on the job's upload, scored as the job was: the points its charts
    show beside its own; none without the tool, with ``seconds`` 0, or when the peers fail."""
    from symgs_core.bench import splat_transform

    exe = splat_transform.find()
    if seconds <= 0 or exe is None:
        return []
    from symgs_core.bench.upload import peer_points

    try:
        return peer_points(scene, report, exe=exe, seconds=seconds, work=work, images=images)
    except Exception:  # noqa: BLE001 - the comparison decorates the charts; it must never fail the job
        log.warning("peers on the upload failed; the job's charts show its own points", exc_info=True)
        return []
