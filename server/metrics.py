"""Prometheus metrics of one server: its own registry (several servers can live in one process) with the
process and Python collectors, the worker's sector counts and latencies, the served model's build info and,
on CUDA, the GPU's memory (and utilisation where NVML answers). docs/deployment.md lists them.

Names follow the Prometheus conventions: counters end in `_total` (prometheus_client appends it) and nothing
else does; units are in the names (`_seconds`, `_bytes`, `_sectors`, `_ratio`); sectors count as sectors.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from typing import Any

import torch
from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    GCCollector,
    Histogram,
    Info,
    PlatformCollector,
    ProcessCollector,
    disable_created_metrics,
    generate_latest,
)
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.registry import Collector

from phim.process import heap_bytes

log = logging.getLogger(__name__)

# A sensor sends a sector every 25 ms: every 2.5 ms from 5 to 40 ms, sparser below and beyond, up to 10 s
LATENCY_BUCKETS_S = (
    0.001,
    0.0025,
    *(round(0.005 + 0.0025 * i, 4) for i in range(15)),
    *(0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.5, 0.75, 1.0, 2.5, 5.0, 10.0),
)
BATCH_BUCKETS = (1, 2, 3, 4, 6, 8, 12, 16, 32, 64, 128)  # sectors per forward
FILL_BUCKETS = (0.5, 0.6, 0.7, 0.8, 0.9, 1.0)  # sectors / batch bucket (always > 0.5: buckets double)
BUILD_LABELS = ("version", "config", "device", "scan_impl", "weights")  # keys of the worker's model info
OK = "ok"  # the outcome label of an answered sector; errors use their ErrorCode value


class Metrics:
    content_type = CONTENT_TYPE_LATEST

    def __init__(self) -> None:
        # no `<name>_created` gauge beside every counter and histogram (prometheus_client's switch is global)
        disable_created_metrics()
        self.registry = r = CollectorRegistry(auto_describe=True)
        ProcessCollector(registry=r)  # process_cpu_seconds_total, process_resident_memory_bytes, ...
        PlatformCollector(registry=r)  # python_info
        GCCollector(registry=r)  # python_gc_*
        if heap_bytes() is not None:
            r.register(HeapCollector())  # phim_heap_*: what of the RSS the allocator holds, used or free
        self.build_info = Info("phim_build", "The served model: " + ", ".join(BUILD_LABELS), registry=r)
        self.sectors = Counter(
            "phim_sectors",
            "Sectors answered, by transport and outcome (ok or an error code)",
            ["transport", "outcome"],
            registry=r,
        )
        self.queued = Gauge("phim_queued_sectors", "Sectors waiting for the device loop", registry=r)
        self.max_queued = Gauge("phim_max_queued_sectors", "Limit on queued sectors (queue_size)", registry=r)
        self.live_streams = Gauge("phim_live_streams", "Streams in the stream table", registry=r)
        self.max_streams = Gauge("phim_max_streams", "Limit on live streams", registry=r)
        self.evictions = Counter(
            "phim_stream_evictions", "Streams evicted after the idle timeout", registry=r
        )
        self.batch_sectors = Histogram(
            "phim_batch_sectors", "Sectors per model forward", buckets=BATCH_BUCKETS, registry=r
        )
        self.batch_fill = Histogram(
            "phim_batch_fill_ratio",
            "Sectors per forward / the batch size it runs at (fixed-shape engines pad to a bucket; eager: 1)",
            buckets=FILL_BUCKETS,
            registry=r,
        )
        self.batch_failures = Counter("phim_batch_failures", "Model forwards that raised", registry=r)
        self.queue_latency = self._latency(
            "phim_queue_latency_seconds", "Time a sector waited before its forward"
        )
        self.model_latency = self._latency(
            "phim_model_latency_seconds", "Model time of the forward a sector ran in"
        )
        self.sector_latency = self._latency(
            "phim_sector_latency_seconds", "Time from submit to reply inside the worker"
        )
        self.ready = Gauge("phim_ready", "1 when warmed up and taking sectors", registry=r)
        self.live_view_dropped = Counter(
            "phim_live_view_dropped",
            "Answered sectors the live view (--foxglove-port) skipped: its queue was full",
            registry=r,
        )

    def _latency(self, name: str, doc: str) -> Histogram:
        return Histogram(name, doc, buckets=LATENCY_BUCKETS_S, registry=self.registry)

    def bind(self, queued: Callable[[], float], live_streams: Callable[[], float]) -> None:
        """Gauges read from the worker at scrape time."""
        self.queued.set_function(queued)
        self.live_streams.set_function(live_streams)

    def model_loaded(self, info: dict[str, Any]) -> None:
        """The worker's model info (server.warmup.model_info) -> build info; GPU gauges when on CUDA."""
        self.build_info.info({key: str(info[key]) for key in BUILD_LABELS})
        if info["device"].startswith("cuda"):
            self.registry.register(GpuCollector(info["device"]))

    def count(self, transport: str, outcome: str) -> None:
        self.sectors.labels(transport=transport, outcome=outcome).inc()

    def exposition(self) -> bytes:
        return generate_latest(self.registry)


class HeapCollector(Collector):
    """glibc malloc's heap at scrape time (phim.process.heap_bytes): in use, and free but kept."""

    def collect(self) -> Iterator[GaugeMetricFamily]:
        heap = heap_bytes()
        if heap is None:
            return
        used, free = heap
        yield GaugeMetricFamily("phim_heap_in_use_bytes", "malloc'd and not yet freed (glibc)", value=used)
        yield GaugeMetricFamily("phim_heap_free_bytes", "freed, kept by malloc for reuse (glibc)", value=free)


class GpuCollector(Collector):
    """The worker's CUDA device, read at scrape time: torch's memory counters, the device's memory, and its
    utilisation through NVML (torch.cuda.utilization) when nvidia-ml-py is installed and NVML answers."""

    def __init__(self, device: str) -> None:
        dev = torch.device(device)
        self.index = torch.cuda.current_device() if dev.index is None else dev.index
        self.label = f"cuda:{self.index}"
        self.total_bytes = torch.cuda.get_device_properties(self.index).total_memory
        self.nvml = self._utilization() is not None
        if not self.nvml:
            log.info("GPU utilisation not exported: no NVML (nvidia-ml-py and the driver's libnvidia-ml)")

    def _utilization(self) -> float | None:
        """0..1, or None without NVML (nvidia-ml-py missing, no NVML library or driver)."""
        try:
            return torch.cuda.utilization(self.index) / 100
        except Exception as e:  # ModuleNotFoundError, RuntimeError or pynvml's NVMLError
            log.debug("NVML: %s: %s", type(e).__name__, e)
            return None

    def collect(self) -> Iterator[GaugeMetricFamily]:
        yield self._gauge(
            "phim_gpu_memory_allocated_bytes",
            "GPU memory in live tensors (torch.cuda.memory_allocated)",
            torch.cuda.memory_allocated(self.index),
        )
        yield self._gauge(
            "phim_gpu_memory_reserved_bytes",
            "GPU memory held by torch's caching allocator (memory_reserved)",
            torch.cuda.memory_reserved(self.index),
        )
        yield self._gauge("phim_gpu_memory_total_bytes", "The GPU's memory", self.total_bytes)
        utilization = self._utilization() if self.nvml else None
        if utilization is not None:
            yield self._gauge(
                "phim_gpu_utilization_ratio",
                "Time a kernel was running in NVML's last sample period",
                utilization,
            )

    def _gauge(self, name: str, doc: str, value: float) -> GaugeMetricFamily:
        gauge = GaugeMetricFamily(name, doc, labels=["device"])
        gauge.add_metric([self.label], value)
        return gauge
