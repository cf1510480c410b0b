"""Prometheus metrics, read from the job store at scrape time so every API replica reports the same figures."""

from __future__ import annotations

from prometheus_client.core import GaugeMetricFamily, HistogramMetricFamily
from prometheus_client.registry import Collector, CollectorRegistry

from api_schemas import QUEUES
from worker.gateway import JobStore, Settings


class JobCollector(Collector):
    def __init__(self, store: JobStore, settings: Settings) -> None:
        self.store, self.settings = store, settings

    def collect(self):  # noqa: ANN201 - an iterator of metric families, as prometheus_client expects
        jobs = GaugeMetricFamily("symgs_jobs", "Jobs in the store by state", labels=["state"])
        for state, count in self.store.count_by_state().items():
            jobs.add_metric([state], count)
        yield jobs

        buckets, total, count = self.store.metrics.durations()
        yield HistogramMetricFamily(
            "symgs_job_duration_seconds",
            "Time from a job's start to its success",
            buckets=[(str(bound), n) for bound, n in buckets] + [("+Inf", count)],
            sum_value=total,
        )

        depth = GaugeMetricFamily("symgs_queue_depth", "Jobs waiting in each queue", labels=["queue"])
        for queue, n in self.store.metrics.queue_depth(QUEUES).items():
            depth.add_metric([queue], n)
        yield depth

        workers = GaugeMetricFamily("symgs_workers", "Workers alive (heartbeat within one lease)", labels=["mode"])
        for mode in QUEUES:
            workers.add_metric([mode], self.store.heartbeats.live(mode, self.settings.lease_seconds))
        yield workers


def make_registry(store: JobStore, settings: Settings) -> CollectorRegistry:
    registry = CollectorRegistry(auto_describe=False)
    registry.register(JobCollector(store, settings))
    return registry
