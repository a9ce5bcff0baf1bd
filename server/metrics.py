"""Prometheus metrics of one server (its own registry, so several servers can live in one process)."""

from __future__ import annotations

from collections.abc import Callable

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
)

LATENCY_BUCKETS_S = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0)
BATCH_BUCKETS = (1, 2, 4, 8, 16, 32, 64, 128)
OK = "ok"  # the outcome label of an answered sector; errors use their ErrorCode value


class Metrics:
    content_type = CONTENT_TYPE_LATEST

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        r = self.registry
        self.requests = Counter(
            "phim_requests",
            "Sectors by transport and outcome (ok or an error code)",
            ["transport", "outcome"],
            registry=r,
        )
        self.queue_depth = Gauge("phim_queue_depth", "Sectors waiting for the device loop", registry=r)
        self.live_streams = Gauge("phim_live_streams", "Streams in the stream table", registry=r)
        self.max_streams = Gauge("phim_max_streams", "Limit on live streams", registry=r)
        self.evictions = Counter(
            "phim_stream_evictions", "Streams evicted after the idle timeout", registry=r
        )
        self.batch_size = Histogram(
            "phim_batch_size", "Sectors per model forward", buckets=BATCH_BUCKETS, registry=r
        )
        self.batch_failures = Counter("phim_batch_failures", "Model forwards that raised", registry=r)
        self.queue_latency = self._latency("phim_queue_seconds", "Time a sector waited before its forward")
        self.model_latency = self._latency("phim_model_seconds", "Model time of the forward a sector ran in")
        self.total_latency = self._latency("phim_total_seconds", "Submit to reply inside the worker")
        self.ready = Gauge("phim_ready", "1 when warmed up and taking sectors", registry=r)

    def _latency(self, name: str, doc: str) -> Histogram:
        return Histogram(name, doc, buckets=LATENCY_BUCKETS_S, registry=self.registry)

    def bind(self, queue_depth: Callable[[], float], live_streams: Callable[[], float]) -> None:
        """Gauges read from the worker at scrape time."""
        self.queue_depth.set_function(queue_depth)
        self.live_streams.set_function(live_streams)

    def count(self, transport: str, outcome: str) -> None:
        self.requests.labels(transport=transport, outcome=outcome).inc()

    def exposition(self) -> bytes:
        return generate_latest(self.registry)
