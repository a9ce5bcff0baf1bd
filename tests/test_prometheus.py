"""GET /metrics of a real server, read with prometheus_client's own text parser: names by the Prometheus
conventions, the served model's build info, process metrics, latency buckets dense around the 25 ms sensor
period, each sector counted once under its transport and outcome, GPU gauges only on CUDA."""

from __future__ import annotations

import importlib.util
import math
import re
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
import torch
from conftest import REPO
from prometheus_client import Metric
from prometheus_client.parser import text_string_to_metric_families
from server_helpers import default_detector, sector_msg, serve

from contract import encode_sector
from model.checkpoint import load_default_model
from model.stream import StreamingDetector
from server.metrics import Metrics

Families = dict[str, Metric]
DOCS = REPO / "docs" / "deployment.md"
PHIM_FAMILIES = {  # name (as the parser gives it: a counter's without `_total`) -> type, on the CPU
    "phim_build_info": "gauge",
    "phim_sectors": "counter",
    "phim_queued_sectors": "gauge",
    "phim_max_queued_sectors": "gauge",
    "phim_live_streams": "gauge",
    "phim_max_streams": "gauge",
    "phim_stream_evictions": "counter",
    "phim_batch_sectors": "histogram",
    "phim_batch_fill_ratio": "histogram",
    "phim_batch_failures": "counter",
    "phim_queue_latency_seconds": "histogram",
    "phim_model_latency_seconds": "histogram",
    "phim_sector_latency_seconds": "histogram",
    "phim_ready": "gauge",
    "phim_live_view_dropped": "counter",
    "phim_heap_in_use_bytes": "gauge",  # glibc
    "phim_heap_free_bytes": "gauge",
}
GPU_FAMILIES = ("memory_allocated_bytes", "memory_reserved_bytes", "memory_total_bytes", "utilization_ratio")
LATENCIES = ("phim_queue_latency_seconds", "phim_model_latency_seconds", "phim_sector_latency_seconds")
MSGPACK = {"Content-Type": "application/msgpack"}


def scrape(url: str) -> Families:
    r = httpx.get(f"{url}/metrics", timeout=10)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain; version=")
    return {f.name: f for f in text_string_to_metric_families(r.text)}


def samples(families: Families, name: str, sample: str | None = None) -> list[Any]:
    return [s for s in families[name].samples if s.name == (sample or name)]


def value(families: Families, name: str, sample: str | None = None) -> float:
    (s,) = samples(families, name, sample)
    return s.value


@pytest.fixture(scope="module")
def det() -> StreamingDetector:
    return default_detector()


@pytest.fixture(scope="module")
def scraped(det: StreamingDetector, scan_a: list) -> Iterator[tuple[Families, dict[str, Any]]]:
    """A fresh server that answered one good and one undecodable sector over HTTP, then was scraped."""
    with serve(det) as s:
        good = encode_sector(sector_msg("car-1", 0, scan_a[0]))
        url = f"{s.url}/v1/streams/car-1/sectors"
        assert httpx.post(url, content=good, headers=MSGPACK, timeout=60).status_code == 200
        assert httpx.post(url, content=b"\xc1junk", headers=MSGPACK, timeout=60).status_code == 400
        model = httpx.get(f"{s.url}/v1/model", timeout=10).json()
        yield scrape(s.url), model


def test_names_follow_the_conventions(scraped):
    families, _ = scraped
    assert {n: f.type for n, f in families.items() if n.startswith("phim_")} == PHIM_FAMILIES
    for name, family in families.items():
        names = {s.name for s in family.samples}
        if family.type == "counter":  # the parser drops a counter's _total from the family name
            assert names == {f"{name}_total"}, name
        else:
            assert not any(n.endswith("_total") for n in names) and not name.endswith("_total"), name
        assert not name.endswith("_created"), name  # no created-timestamp gauges beside the counters
        if family.type == "histogram" and name.startswith("phim_"):
            assert name.endswith(("_seconds", "_sectors", "_ratio")), name  # the unit is in the name


def test_every_metric_is_documented(scraped):
    families, _ = scraped
    documented = set(re.findall(r"`(phim_\w+)", DOCS.read_text()))
    exported = {f"{n}_total" if f.type == "counter" else n for n, f in families.items() if n[:5] == "phim_"}
    assert exported | {f"phim_gpu_{g}" for g in GPU_FAMILIES} == documented


def test_build_info_names_the_served_model(scraped):
    families, model = scraped
    (info,) = samples(families, "phim_build_info")
    assert info.value == 1
    assert info.labels == {k: model[k] for k in ("version", "config", "device", "scan_impl", "weights")}
    assert info.labels["config"] == "tiny" and info.labels["scan_impl"] in ("numba", "triton")


def test_process_and_python_metrics(scraped):
    families, _ = scraped
    assert value(families, "process_cpu_seconds", "process_cpu_seconds_total") > 0
    assert value(families, "process_resident_memory_bytes") > 50e6  # torch and a model are in there
    assert value(families, "process_open_fds") > 0
    (py,) = samples(families, "python_info")
    assert py.labels["implementation"] == "CPython"
    assert len(samples(families, "python_gc_collections", "python_gc_collections_total")) == 3
    used, free = value(families, "phim_heap_in_use_bytes"), value(families, "phim_heap_free_bytes")
    assert 10e6 < used < value(families, "process_resident_memory_bytes") and free >= 0  # glibc here


def test_latency_buckets_are_dense_around_the_sensor_period(scraped):
    families, _ = scraped
    dense = [2.5e-3 * i for i in range(2, 17)]  # 5, 7.5, ..., 40 ms
    for name in LATENCIES:
        buckets = samples(families, name, f"{name}_bucket")
        bounds = [float(s.labels["le"]) for s in buckets]
        assert bounds == sorted(bounds) and bounds[-1] == math.inf and 10 <= bounds[-2] <= 30, name
        assert all(any(math.isclose(b, d) for b in bounds) for d in dense), (name, bounds)
        assert sum(0.005 <= b <= 0.04 for b in bounds) == len(dense), bounds  # none between the steps
        assert sum(0.04 < b < math.inf for b in bounds) <= 15, bounds  # sparser beyond
        assert buckets[-1].value == value(families, name, f"{name}_count") == 1, name  # one answered sector
    assert value(families, "phim_model_latency_seconds", "phim_model_latency_seconds_sum") > 0


def test_a_sector_is_counted_once_under_its_transport_and_outcome(scraped):
    families, _ = scraped
    counted = {
        (s.labels["transport"], s.labels["outcome"]): s.value for s in families["phim_sectors"].samples
    }
    assert counted == {("http", "ok"): 1, ("http", "bad_request"): 1}
    assert value(families, "phim_batch_sectors", "phim_batch_sectors_count") == 1  # one forward ...
    assert value(families, "phim_batch_sectors", "phim_batch_sectors_sum") == 1  # ... of one sector
    assert value(families, "phim_batch_fill_ratio", "phim_batch_fill_ratio_sum") == 1  # eager: unpadded
    gauges = ("phim_ready", "phim_live_streams", "phim_queued_sectors", "phim_max_queued_sectors")
    assert [value(families, g) for g in gauges] == [1, 1, 0, 64]
    assert value(families, "phim_stream_evictions", "phim_stream_evictions_total") == 0


def test_gpu_metrics_only_on_cuda(scraped):
    families, model = scraped
    assert model["device"] == "cpu"
    assert not [n for n in families if n.startswith("phim_gpu_")]  # docs/deployment.md says so


def test_each_server_has_its_own_registry():
    a, b = Metrics(), Metrics()
    a.count("http", "ok")
    a.count("http", "ok")
    b.count("zenoh", "ok")
    assert b'phim_sectors_total{outcome="ok",transport="http"} 2.0' in a.exposition()
    assert b"http" not in b.exposition() and b'transport="zenoh"} 1.0' in b.exposition()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_gpu_memory_and_utilization_on_cuda(scan_a):
    cuda_det = StreamingDetector(load_default_model("cuda")[0])
    with serve(cuda_det) as s:
        body = encode_sector(sector_msg("car-1", 0, scan_a[0]))
        r = httpx.post(f"{s.url}/v1/streams/car-1/sectors", content=body, headers=MSGPACK, timeout=60)
        assert r.status_code == 200
        families = scrape(s.url)
    gpu = {n.removeprefix("phim_gpu_"): f.samples for n, f in families.items() if n.startswith("phim_gpu_")}
    nvml = importlib.util.find_spec("pynvml") is not None
    assert set(gpu) == set(GPU_FAMILIES if nvml else GPU_FAMILIES[:3])
    allocated, reserved, total = (gpu[name][0] for name in GPU_FAMILIES[:3])
    assert 0 < allocated.value <= reserved.value < total.value
    assert allocated.labels == {"device": f"cuda:{torch.cuda.current_device()}"}
    if nvml:
        assert 0 <= gpu["utilization_ratio"][0].value <= 1
    assert samples(families, "phim_build_info")[0].labels["device"].startswith("cuda")
