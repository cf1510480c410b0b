"""The rows of ``bench.json`` and the file itself: what every figure means, in one place.

PSNR and SSIM are measured against renders of the uncompressed scene, on cameras that fitted nothing: the
evaluation rig (``psnr_db``; the pipeline's own evaluation cameras, never its fitting ones) and a second,
independent rig (``psnr_other_db``; other directions, the same range of distances). In the JSON an infinite PSNR
(identical renders) is null with ``status`` "ok"; a peer that did not finish has ``status`` "timed_out",
"failed" or "unavailable" and null figures.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Literal

SCHEMA = "symgs-bench/1"
Role = Literal["preset", "sweep", "peer"]
TOLERANCE_DB = 0.2  # a claim holds on the other rig if ours reaches the peer's PSNR there within this


@dataclass
class BenchRow:
    scene: str
    method: str  # ours: "symgs" (mirrors on) or "symgs no mirrors"; peers: "splat-transform spz v3", ...
    role: Role  # preset: one of our presets; sweep: our run at a budget chosen to meet a peer; peer
    status: str  # ok | timed_out | failed | unavailable
    file: str | None  # the output, relative to the bench's folder
    preset: str | None = None
    mirrors: bool | None = None
    budget_db: float | None = None  # psnr_budget of our run
    floor_db: float | None = None  # the PSNR floor our run held on its fitting cameras
    bytes: int | None = None
    ratio: float | None = None  # input PLY bytes / bytes
    gaussians: int | None = None  # decoded
    psnr_db: float | None = None
    psnr_object_db: float | None = None  # the object's own pixels
    ssim: float | None = None
    psnr_other_db: float | None = None
    psnr_object_other_db: float | None = None
    ssim_other: float | None = None
    encode_s: float | None = None  # ours: the whole pipeline; peers: the tool's run, process start included
    decode_s: float | None = None  # to PLY bytes (peers: the tool's run writing a PLY)
    reason: str = ""
    trained: bool | None = None  # the scene as a trainer wrote it (float32), or decoded from a quantised container
    sections: dict[str, int] | None = None  # ours: the archive's bytes by part (``Report.sections``)
    # Peers only: our curve ("symgs", or "symgs no mirrors" when mirrors did not run) at this row's PSNR.
    equal_psnr_bytes: float | None = None  # our bytes at this peer's psnr_db, interpolated (never extrapolated)
    equal_psnr_ratio: float | None = None  # bytes / equal_psnr_bytes: > 1 means ours is smaller at equal PSNR
    equal_psnr_other_ratio: float | None = None  # the same on the other rig, at psnr_other_db
    equal_psnr_object_ratio: float | None = None  # the same on the object's pixels, at psnr_object_db
    claim_holds_other: bool | None = None  # equal_psnr_ratio > 1: does ours stay smaller on the other rig
    # (reaching psnr_other_db - TOLERANCE_DB there in fewer bytes)? None: no claim made

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def ours(self) -> bool:
        return self.role != "peer"

    def as_json(self) -> dict[str, Any]:
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> BenchRow:
        """The row of ``as_json`` output; a null PSNR of an ok row is +inf again."""
        row = cls(**data)
        if row.ok:
            for name in ("psnr_db", "psnr_object_db", "psnr_other_db", "psnr_object_other_db"):
                if getattr(row, name) is None:
                    setattr(row, name, math.inf)
        return row


REQUIRED = ("scene", "method", "preset", "bytes", "ratio", "psnr_db", "ssim", "encode_s", "decode_s", "file")


def claims(rows: list[BenchRow]) -> list[dict[str, Any]]:
    """Every claim the rows make that ours is smaller than a peer at no lower PSNR, with its check on the other rig."""
    out = []
    for r in rows:
        if r.role == "peer" and r.equal_psnr_ratio is not None and r.equal_psnr_ratio > 1:
            out.append({
                "scene": r.scene, "peer": r.method, "peer_bytes": r.bytes, "peer_psnr_db": r.psnr_db,
                "our_bytes": r.equal_psnr_bytes, "equal_psnr_ratio": r.equal_psnr_ratio,
                "peer_psnr_other_db": r.psnr_other_db, "equal_psnr_other_ratio": r.equal_psnr_other_ratio,
                "equal_psnr_object_ratio": r.equal_psnr_object_ratio,
                "holds_on_other_cameras": r.claim_holds_other,
            })  # fmt: skip
    return out
