"""Prometheus metrics: the registry, the HTTP latency histogram and the store collector."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily, HistogramMetricFamily

from ..storage.store import STATUSES
from .deps import ServiceContext

DURATION_BUCKETS = (1, 2, 5, 10, 20, 30, 60, 120, 300, 600, 1800, 3600)
LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60)


class StoreCollector:
    """Job gauges and the job-duration histogram, read from the store at scrape time
    (the store is shared by API and workers, so every process sees the same numbers)."""

    def __init__(self, ctx_getter: Callable[[], ServiceContext | None]):
        self.ctx_getter = ctx_getter

    def collect(self):
        ctx = self.ctx_getter()
        if ctx is None:
            return
        counts = ctx.store.count_by_status()
        jobs = GaugeMetricFamily("dsareg_jobs", "Jobs in the store by state.", labels=["state"])
        for state in STATUSES:
            jobs.add_metric([state], counts.get(state, 0))
        yield jobs
        yield GaugeMetricFamily("dsareg_queue_depth", "Jobs waiting for a worker.", value=counts.get("queued", 0))
        yield GaugeMetricFamily("dsareg_workers_alive", "Worker processes alive.", value=ctx.executor.alive_workers())
        yield GaugeMetricFamily("dsareg_event_streams_open", "Event streams (GET …/events) open in this API process.",
                                value=ctx.extra.get("event_streams_open", 0))
        hist = HistogramMetricFamily("dsareg_job_duration_seconds", "Run time of finished jobs (started → finished).",
                                     labels=["state"])
        durations = ctx.store.finished_durations()
        for state in ("succeeded", "failed", "canceled"):
            values = [d for s, d in durations if s == state]
            buckets = [(str(b), sum(1 for v in values if v <= b)) for b in DURATION_BUCKETS]
            buckets.append(("+Inf", len(values)))
            hist.add_metric([state], buckets, sum_value=float(sum(values)))
        yield hist


@dataclass
class ServiceMetrics:
    registry: CollectorRegistry
    http_latency: Histogram
    uploads: Counter


def make_metrics(ctx_getter: Callable[[], ServiceContext | None]) -> ServiceMetrics:
    registry = CollectorRegistry(auto_describe=True)
    http_latency = Histogram("dsareg_http_request_duration_seconds", "HTTP request latency by route template.",
                             ["method", "route", "status"], registry=registry, buckets=LATENCY_BUCKETS)
    uploads = Counter("dsareg_upload_bytes", "Bytes of accepted input files.", registry=registry)
    registry.register(StoreCollector(ctx_getter))
    return ServiceMetrics(registry=registry, http_latency=http_latency, uploads=uploads)
