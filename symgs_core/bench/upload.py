"""The peers on a job's upload, scored as the job scored its own archive: the points its charts show beside ours.

Bounded by ``seconds``: each peer is converted and decoded within the time left, then scored on the job's
evaluation cameras (a few renders); once the time is spent no other peer starts, so a large upload gets fewer
peers rather than a much slower job. SOG, whose k-means takes minutes on a CPU, goes last.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import torch

from ..pictures.charts import PeerPoint
from ..ply import load_scene
from ..report import Report
from ..views import dataset_eval_views, evaluate, self_supervised_views
from .peers import PEERS, run_peers


def peer_points(
    ply: Path, report: Report, *, exe: str, seconds: float, work: Path, images: Path | None = None
) -> list[PeerPoint]:
    """Each peer that finished within ``seconds`` on ``ply``, on the job's evaluation cameras (rebuilt from the
    report's settings: the dataset's test split with ``images``, else the self-supervised rig of the job's seed).
    Files are written under ``work``."""
    deadline = time.monotonic() + seconds
    config = report.config
    source = load_scene(ply)
    device = torch.device(report.device)
    background = torch.zeros(3, device=device)
    scene = source.to(device)
    if images is not None:
        views = dataset_eval_views(images, scene, eval=config.eval_views, resolution=config.eval_resolution,
                                   background=background)  # fmt: skip
    else:
        views = list(self_supervised_views(
            scene, train=1, fit=1, eval=config.eval_views, resolution=16, eval_resolution=config.eval_resolution,
            background=background, seed=config.seed,
        ).eval)  # fmt: skip
    points = []
    for peer in sorted(PEERS, key=lambda p: p.slow):  # the slow ones last
        (output,) = run_peers(ply, source, work, exe=exe, timeout=seconds, deadline=deadline, peers=(peer,))
        if output.status != "ok" or output.decoded is None:
            continue
        psnr = evaluate(output.decoded.to(device), views, background).worst
        points.append(PeerPoint(peer.method, output.bytes or 0, psnr if math.isfinite(psnr) else None,
                                output.encode_s or 0.0))  # fmt: skip
    return points
