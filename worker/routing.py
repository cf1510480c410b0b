"""Which queue a job goes to: the client's device preference, and which workers are alive."""

from __future__ import annotations

from api_schemas import DevicePreference, Queue

from .store import JobStore


def choose_queue(store: JobStore, device: DevicePreference, *, alive_within_s: float) -> Queue:
    """``cuda`` -> gpu (waits for a GPU worker); ``cpu`` -> cpu; ``auto`` -> gpu when a GPU worker has sent a
    heartbeat within ``alive_within_s``, cpu otherwise."""
    if device == "cuda":
        return "gpu"
    if device == "cpu":
        return "cpu"
    return "gpu" if store.heartbeats.live("gpu", alive_within_s) > 0 else "cpu"
