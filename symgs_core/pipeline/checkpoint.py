"""A job's checkpoints: the level loop's state, records and best size saved after every level, and the upload's own
fine-tune against photographs (``refine``), each read back by a rerun of the same job (the same ``scene_fingerprint``
of its inputs), so a job whose worker died resumes after its last level, its fine-tune done."""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from ..config import CompressConfig
from ..files import partial_file
from ..report import LevelReport, Refinement
from ..scene import GaussianScene
from .state import LevelState


def settings_digest(config: CompressConfig, images: str | Path | None) -> bytes:
    """What a job's checkpoints must match besides its scene: the settings and the photographs' contents (a job's
    stages take it once, ``Job.settings_digest``: a phone capture's photographs are read whole to hash them)."""
    h = hashlib.sha256(json.dumps(asdict(config), sort_keys=True, default=str).encode())
    if images is not None:  # the dataset's contents, not where it lies: a job resumed on another host matches
        root = Path(images)
        for file in sorted(p for p in (root.rglob("*") if root.is_dir() else [root]) if p.is_file()):
            h.update(str(file.relative_to(root) if root.is_dir() else file.name).encode())
            with file.open("rb") as f:
                for chunk in iter(lambda: f.read(1 << 20), b""):
                    h.update(chunk)
    return h.digest()


def scene_fingerprint(scene: GaussianScene, settings: bytes) -> str:
    """The job's inputs, which a checkpoint must match to be resumed from: ``scene`` and its job's
    ``settings_digest``."""
    h = hashlib.sha256()
    for t in scene.tensors().values():
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    h.update(settings)
    return h.hexdigest()


@dataclass(frozen=True)
class Checkpoint:
    """Where the level decisions are saved, and the job's inputs (``fingerprint``) a saved file must match."""

    path: Path
    fingerprint: str


def save_checkpoint(checkpoint: Checkpoint, state: LevelState, records: list[LevelReport], done: bool,
                     best_bytes: int) -> None:  # fmt: skip
    """The level loop's progress so far, for a rerun of the same job to resume after it."""
    path = checkpoint.path
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "fingerprint": checkpoint.fingerprint,
        "stored": {k: v.detach().cpu() for k, v in state.stored.tensors().items()},
        "normals": state.normals.detach().cpu(),
        "offsets": state.offsets.detach().cpu(),
        "bits": state.bits.cpu(),
        "records": [asdict(r) for r in records],
        "done": done,
        "best_bytes": best_bytes,
    }
    # A temporary file of its own: two runs of one job may overlap (a worker whose lease lapsed while Redis
    # restarted runs on until it notices), and a shared temporary name let one move the other's half-written file
    # into place, or find it gone. Moved into place whole: a worker killed mid-write leaves the previous one intact.
    with partial_file(path) as (out, tmp):
        torch.save(payload, out)
    os.replace(tmp, path)


def load_checkpoint(
    checkpoint: Checkpoint, device: torch.device
) -> tuple[LevelState, list[LevelReport], bool, int] | None:
    """The state, the records, whether the search was done, and the best archive's bytes saved at ``checkpoint``;
    None where there is none, it cannot be read, or it was saved for other inputs."""
    if not checkpoint.path.exists():
        return None
    try:
        payload = torch.load(checkpoint.path, map_location=device, weights_only=True)
    except Exception:  # noqa: BLE001 - an unreadable checkpoint is recomputed, never trusted
        return None
    if payload.get("fingerprint") != checkpoint.fingerprint or "best_bytes" not in payload:
        return None
    state = LevelState(GaussianScene(**payload["stored"]), payload["normals"], payload["offsets"], payload["bits"])
    records = [LevelReport(**{**r, "normal": tuple(r["normal"])}) for r in payload["records"]]
    return state, records, bool(payload["done"]), int(payload["best_bytes"])


def save_refined(path: Path, fingerprint: str, scene: GaussianScene | None, record: Refinement) -> None:
    """The upload's fine-tune: the scene kept (None: the upload) and its record, for a rerun to go on from."""
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "fingerprint": fingerprint,
        "stored": None if scene is None else {k: v.detach().cpu() for k, v in scene.tensors().items()},
        "record": asdict(record),
    }
    with partial_file(path) as (out, tmp):
        torch.save(payload, out)
    os.replace(tmp, path)


def load_refined(path: Path, fingerprint: str, device: torch.device) -> tuple[GaussianScene | None, Refinement] | None:
    """What ``save_refined`` saved for the inputs ``fingerprint``; None where there is none, it cannot be read, or it
    was saved for other inputs."""
    if not path.exists():
        return None
    try:
        payload = torch.load(path, map_location=device, weights_only=True)
        if payload.get("fingerprint") != fingerprint:
            return None
        scene = None if payload["stored"] is None else GaussianScene(**payload["stored"])
        return scene, Refinement(**payload["record"])
    except Exception:  # noqa: BLE001 - an unreadable checkpoint is recomputed, never trusted
        return None
