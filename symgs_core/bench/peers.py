"""The peers' formats, run on one input PLY: each written, timed, and decoded back by its own tool.

splat-transform's formats are written from the input file and decoded back to a PLY by splat-transform itself (so
its reader, not ours, says what the file holds); the float16 PLY is ours (``half_ply``). A peer that fails or runs
past its time limit is reported as such, never dropped silently. ``deadline`` (a ``time.monotonic()`` instant)
bounds all of them together: a job's charts must not make the job much slower.
"""

from __future__ import annotations

import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from ..ply import load_scene, ply_bytes
from ..scene import GaussianScene
from . import splat_transform
from .half_ply import EXTENSION as HALF_EXTENSION
from .half_ply import read_half_ply, write_half_ply

PeerStatus = Literal["ok", "timed_out", "failed", "unavailable"]


@dataclass(frozen=True)
class Peer:
    method: str  # as the bench's rows name it
    file: str  # output file name
    options: tuple[str, ...] = ()  # splat-transform options
    tool: Literal["splat-transform", "symgs"] = "splat-transform"
    slow: bool = False  # minutes on a CPU for large scenes (SOG's k-means)


PEERS: tuple[Peer, ...] = (
    Peer("splat-transform spz v3", "spz-v3.spz", ("--spz-version", "3")),
    Peer("splat-transform spz v4", "spz-v4.spz", ("--spz-version", "4")),
    Peer("splat-transform compressed ply", "playcanvas.compressed.ply"),
    Peer("splat-transform sog", "playcanvas.sog", ("-g", "cpu"), slow=True),
    Peer("float16 ply + zstd", f"float16{HALF_EXTENSION}", tool="symgs"),
)


@dataclass
class PeerOutput:
    peer: Peer
    status: PeerStatus
    reason: str = ""
    path: Path | None = None  # the file written
    bytes: int | None = None
    encode_s: float | None = None
    decode_s: float | None = None  # decoding back to a PLY, as the tool does it
    decoded: GaussianScene | None = None


def _half(peer: Peer, source: GaussianScene, target: Path) -> PeerOutput:
    t0 = time.perf_counter()
    target.write_bytes(write_half_ply(source))
    encode = time.perf_counter() - t0
    t0 = time.perf_counter()
    decoded = read_half_ply(target.read_bytes())
    ply_bytes(decoded)  # the same work as the other tools' decoding: down to PLY bytes
    return PeerOutput(peer, "ok", "", target, target.stat().st_size, encode, time.perf_counter() - t0, decoded)


def _splat_transform(peer: Peer, exe: str, ply: Path, target: Path, timeout: float) -> PeerOutput:
    """Write ``target`` from ``ply`` and decode it back, both within ``timeout`` seconds together."""
    with tempfile.TemporaryDirectory(prefix="symgs-peer-") as tmp:
        back = Path(tmp) / "decoded.ply"
        try:
            encode = splat_transform.convert(exe, ply, target, peer.options, timeout)
            if encode >= timeout:
                raise subprocess.TimeoutExpired("splat-transform", timeout)
            decode = splat_transform.convert(exe, target, back, (), timeout - encode)
        except subprocess.TimeoutExpired:
            target.unlink(missing_ok=True)
            return PeerOutput(peer, "timed_out", f"ran past its time limit of {timeout:.0f} s")
        except splat_transform.ToolError as exc:
            target.unlink(missing_ok=True)
            return PeerOutput(peer, "failed", str(exc))
        decoded = load_scene(back)
    return PeerOutput(peer, "ok", "", target, target.stat().st_size, encode, decode, decoded)


def run_peers(
    ply: Path,
    source: GaussianScene,
    out: Path,
    *,
    exe: str | None,
    timeout: float,
    slow_timeout: float | None = None,
    deadline: float | None = None,
    peers: tuple[Peer, ...] = PEERS,
    unavailable: str = "splat-transform is not installed",
) -> list[PeerOutput]:
    """Every peer of ``peers`` on ``ply`` (whose scene is ``source``), files written into ``out``.

    ``timeout`` seconds per peer (writing and decoding back), ``slow_timeout`` for the slow ones (default
    ``timeout``); with
    ``deadline``, no conversion is given more than the time left, and none starts once it has passed. ``exe`` None:
    splat-transform's peers are reported unavailable with the reason ``unavailable``."""
    out.mkdir(parents=True, exist_ok=True)
    results = []
    for peer in peers:
        limit = slow_timeout if peer.slow and slow_timeout is not None else timeout
        if deadline is not None:
            limit = min(limit, deadline - time.monotonic())
            if limit <= 0:
                results.append(PeerOutput(peer, "timed_out", "the time for the peers was spent before it started"))
                continue
        if peer.tool == "symgs":
            results.append(_half(peer, source, out / peer.file))
        elif exe is None:
            results.append(PeerOutput(peer, "unavailable", unavailable))
        else:
            results.append(_splat_transform(peer, exe, ply, out / peer.file, limit))
    return results
