"""The server on the fixed-shape step: a real uvicorn server around GraphStreamingDetector answers KITTI
sectors of concurrent streams as the eager detector does directly; a sector too big for its state slot fails
alone; stream-state slots come back when streams end or are evicted; the scheduler prefers full buckets."""

from __future__ import annotations

import re
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import numpy as np
import pytest
import torch
from prometheus_client.parser import text_string_to_metric_families
from pydantic import ValidationError
from server_helpers import (
    LATE_S,
    START_TIMEOUT_S,
    StepGate,
    assert_same_boxes,
    comparable_detector,
    kitti_sectors,
    run_direct,
    sector_msg,
    serve,
)

from contract import (
    HTTP_STATUS,
    MSGPACK,
    DetectionsReply,
    ErrorCode,
    ErrorReply,
    decode_response,
    encode_sector,
)
from lidar.synthetic import synthetic_turn
from model.graph.engine import GraphStreamingDetector
from model.sectors import split_turn
from server.settings import Settings
from server.worker import Worker, WorkerConfig


def post(url: str, stream: str, seq: int, points) -> DetectionsReply:
    body = encode_sector(sector_msg(stream, seq, points))
    r = httpx.post(
        f"{url}/v1/streams/{stream}/sectors", content=body, headers={"Content-Type": MSGPACK}, timeout=120
    )
    assert r.status_code == 200, r.content[:300]
    out = decode_response(r.content)
    assert isinstance(out, DetectionsReply)
    return out


@pytest.mark.samples
def test_concurrent_streams_on_the_fixed_step_equal_the_eager_model():
    eager = comparable_detector()
    scans = {"car-a": kitti_sectors(0, every=2), "car-b": kitti_sectors(1, every=2)}
    refs = {k: run_direct(eager, v) for k, v in scans.items()}
    det = GraphStreamingDetector(eager.model, slots=4)
    with serve(det, max_batch=4, max_wait_ms=20.0, max_streams=4) as s, ThreadPoolExecutor(2) as pool:
        info = httpx.get(f"{s.url}/v1/model", timeout=10).json()
        assert (info["engine"], info["sector_voxels"]) == ("graph", det.sector_voxels)
        for seq in range(4):
            futures = {k: pool.submit(post, s.url, k, seq, v[seq]) for k, v in scans.items()}
            for k, f in futures.items():
                r = f.result()
                assert_same_boxes(r.boxes, r.scores, r.labels, refs[k][seq])
                assert r.context_sectors == seq + 1


@pytest.mark.samples
def test_a_compiled_server_warms_up_sealed_and_equals_the_eager_model():
    """Engine graph end to end: the warm-up compiles its bucket and seals the detector; real KITTI sectors and
    thinned ones (half the points) alike are padded to sector_points and run compiled, a sector above it
    (doubled points) op by op, all equal to the eager model; nothing compiles after ready."""
    eager = comparable_detector()
    full, thin = kitti_sectors(0), kitti_sectors(1, every=2)
    doubled = [np.concatenate([p, p]) for p in kitti_sectors(2)[:1]]  # same voxels, twice the points
    sequences = {"full": full, "thin": thin, "doubled": doubled}
    refs = {name: run_direct(eager, sectors) for name, sectors in sequences.items()}
    det = GraphStreamingDetector(eager.model, compile=True, slots=3, sector_points=40_000)
    with serve(det, wait_ready=False, max_batch=1, max_streams=3, warmup_sectors=2) as s:
        deadline = time.monotonic() + 2 * START_TIMEOUT_S  # a cold compile: minutes on a busy 2-core machine
        while httpx.get(f"{s.url}/health/ready", timeout=LATE_S).status_code != 200:
            assert httpx.get(f"{s.url}/health/live", timeout=LATE_S).status_code == 200, "the warm-up failed"
            assert time.monotonic() < deadline, "the compiled warm-up did not finish"
            time.sleep(0.5)
        warmed = det.compiled_buckets
        assert {cap.bev_crop for _, cap in warmed} == {False, True} and len(warmed) == 2 and det.sealed
        info = httpx.get(f"{s.url}/v1/model", timeout=10).json()
        assert (info["sector_points"], info["bev_crop"]) == (40_000, True)
        for name, sectors in sequences.items():
            for seq, points in enumerate(sectors):
                assert (len(points) > 40_000) == (name == "doubled")
                r = post(s.url, name, seq, points)
                assert_same_boxes(r.boxes, r.scores, r.labels, refs[name][seq])
            ran_op_by_op = {batch for batch, _ in det.uncompiled_buckets}
            assert ran_op_by_op == ({1} if name == "doubled" else set()), name
        assert det.compiled_buckets == warmed


def test_a_graph_engine_batches_at_most_the_largest_bucket():
    with pytest.raises(ValidationError, match="max_batch 64: the graph engine runs 32 at most"):
        Settings(engine="graph", max_batch=64)
    with pytest.raises(ValidationError, match="max_batch 33: the graph engine runs 32 at most"):
        Settings(engine="graph", max_batch=33)
    assert Settings(engine="graph", max_batch=32).max_batch == 32
    with pytest.raises(ValidationError, match="engine"):  # the uncompiled step is no engine of its own
        Settings(engine="fixed")
    assert Settings(engine="eager", max_batch=64).max_batch == 64


def post_raw(url: str, stream: str, seq: int, points, **kw) -> DetectionsReply | ErrorReply:
    body = encode_sector(sector_msg(stream, seq, points, **kw))
    r = httpx.post(
        f"{url}/v1/streams/{stream}/sectors", content=body, headers={"Content-Type": MSGPACK}, timeout=120
    )
    out = decode_response(r.content)
    assert r.status_code == (200 if isinstance(out, DetectionsReply) else HTTP_STATUS[out.code])
    return out


def light_sectors(seed: int) -> list[np.ndarray]:
    """A synthetic turn's 4 sectors, 120 points each: at most 120 voxels."""
    return [s[:120].contiguous().numpy() for s in split_turn(torch.from_numpy(synthetic_turn(seed=seed)), 4)]


def batches(url: str) -> tuple[float, float]:
    """(forwards, sectors) so far, from phim_batch_sectors."""
    text = httpx.get(f"{url}/metrics", timeout=10).text
    families = {f.name: f for f in text_string_to_metric_families(text)}
    got = {s.name: s.value for s in families["phim_batch_sectors"].samples}
    return got["phim_batch_sectors_count"], got["phim_batch_sectors_sum"]


def test_a_sector_too_big_for_its_slot_fails_alone_and_its_stream_goes_on():
    eager = comparable_detector()
    light = {"car-a": light_sectors(1), "car-b": light_sectors(2)}
    big = split_turn(torch.from_numpy(synthetic_turn(seed=1)), 4)[1].numpy()  # thousands of voxels
    ref_a = run_direct(eager, [light["car-a"][0], light["car-a"][2]])
    ref_b = run_direct(eager, light["car-b"][:2])
    det = GraphStreamingDetector(eager.model, sector_voxels=256, slots=2)
    with serve(det, max_batch=2, max_wait_ms=1000.0, max_streams=2) as s, ThreadPoolExecutor(2) as pool:
        for stream in ("car-a", "car-b"):
            assert isinstance(post_raw(s.url, stream, 0, light[stream][0]), DetectionsReply)
        before = batches(s.url)
        too_big = pool.submit(post_raw, s.url, "car-a", 1, big)
        fine = pool.submit(post_raw, s.url, "car-b", 1, light["car-b"][1])
        err, ok = too_big.result(), fine.result()
        assert batches(s.url) == (before[0] + 1, before[1] + 2)  # the two ran in one batch
        assert isinstance(err, ErrorReply) and (err.code, err.field) == (ErrorCode.INVALID_FIELD, "points")
        assert re.fullmatch(
            r"points: a sector of \d+ voxels; the graph engine buffers at most 256 voxels per sector "
            r"\(sector_voxels\): raise it \(phim serve --sector-voxels, PHIM_SECTOR_VOXELS\) or send fewer "
            r"points \(seq 1 not run\)",
            err.message,
        ), err.message
        assert isinstance(ok, DetectionsReply) and ok.context_sectors == 2
        assert_same_boxes(ok.boxes, ok.scores, ok.labels, ref_b[1])
        after = post_raw(s.url, "car-a", 2, light["car-a"][2])
        assert isinstance(after, DetectionsReply) and after.context_sectors == 2  # sector 1 never entered
        assert_same_boxes(after.boxes, after.scores, after.labels, ref_a[1])


def live_streams(url: str) -> int:
    return httpx.get(f"{url}/v1/streams", timeout=10).json()["live"]


def test_slots_come_back_when_streams_end_are_evicted_or_reset(monkeypatch: pytest.MonkeyPatch):
    det = GraphStreamingDetector(comparable_detector().model, sector_voxels=512, slots=3)
    light = light_sectors(3)
    with serve(det, max_streams=3, idle_timeout_s=START_TIMEOUT_S) as s:
        table = (
            s.server.config.app.state.services.worker.table
        )  # idle timeout: long while filling, then short
        info = httpx.get(f"{s.url}/v1/model", timeout=10).json()
        assert (info["state_slots"], info["slot_bytes"]) == (3, det.slots.slot_bytes)
        assert info["slot_memory_mb"] == round(4 * det.slots.slot_bytes / 2**20, 1)
        for rnd in range(2):
            table.idle_timeout_s = START_TIMEOUT_S  # no stream idles out while the round runs, however slow
            for i in range(3):
                assert isinstance(post_raw(s.url, f"r{rnd}-{i}", 0, light[i]), DetectionsReply)
            assert det.slots.free == 0
            full = post_raw(s.url, "one-too-many", 0, light[3])
            assert isinstance(full, ErrorReply) and full.code is ErrorCode.OVERLOADED
            assert "3 live streams, the limit (max_streams=3)" in full.message
            reset = post_raw(s.url, f"r{rnd}-0", 0, light[1], reset=True)
            assert isinstance(reset, DetectionsReply) and reset.context_sectors == 1 and det.slots.free == 0
            assert httpx.delete(f"{s.url}/v1/streams/r{rnd}-1", timeout=10).status_code == 200
            assert det.slots.free == 1
            table.idle_timeout_s = 0.5  # the other two are evicted once idle
            deadline = time.monotonic() + START_TIMEOUT_S
            while live_streams(s.url) != 0:
                assert time.monotonic() < deadline, "the idle streams were not evicted"
                time.sleep(0.05)
            assert live_streams(s.url) == 0 and det.slots.free == 3
        gate = StepGate.install(det, monkeypatch)  # a stream ended while its sector runs
        with ThreadPoolExecutor(1) as pool:
            running = pool.submit(post_raw, s.url, "ends-mid-step", 0, light[0])
            assert gate.entered.wait(START_TIMEOUT_S)
            assert httpx.delete(f"{s.url}/v1/streams/ends-mid-step", timeout=10).status_code == 200
            assert det.slots.free == 2  # not yet: the step in progress still writes its slot
            gate.release()
            assert isinstance(running.result(), DetectionsReply)
        assert det.slots.free == 3


def queued(worker: Worker) -> int:
    """Sectors waiting in the worker's queue (read without its lock: for polling)."""
    return sum(len(e.pending) for e in list(worker.table.entries.values()))


def test_the_scheduler_runs_a_full_bucket_at_once_and_waits_when_one_just_misses(
    monkeypatch: pytest.MonkeyPatch,
):
    det = GraphStreamingDetector(comparable_detector().model, sector_voxels=512, slots=5)
    turns = [light_sectors(seed) for seed in range(5)]
    cars = [f"car-{i}" for i in range(5)]
    max_wait_ms = 10_000.0  # far above the spread of 4 concurrent posts, even on a busy machine
    settings = dict(
        max_batch=8,
        max_wait_ms=max_wait_ms,
        max_streams=5,
        deadline_ms=START_TIMEOUT_S * 1e3,
        idle_timeout_s=START_TIMEOUT_S,  # no stream idles out, however slow the machine
    )
    with serve(det, **settings) as s, ThreadPoolExecutor(5) as pool:
        worker = s.server.config.app.state.services.worker
        first = [pool.submit(post_raw, s.url, c, 0, t[0]) for c, t in zip(cars, turns, strict=True)]
        assert all(isinstance(f.result(), DetectionsReply) for f in first)
        before = batches(s.url)
        gate = StepGate.install(det, monkeypatch)  # the fifth car's sector holds the loop while 4 queue
        fifth = pool.submit(post_raw, s.url, cars[4], 1, turns[4][1])
        assert gate.entered.wait(START_TIMEOUT_S)
        four = [pool.submit(post_raw, s.url, c, 1, t[1]) for c, t in zip(cars[:4], turns[:4], strict=True)]
        deadline = time.monotonic() + START_TIMEOUT_S
        while queued(worker) < 4:
            assert time.monotonic() < deadline, "the four sectors were never queued"
            time.sleep(0.01)
        gate.release()
        replies = [f.result() for f in four]  # 4 of 5 live streams: a full bucket, the fifth can't fill 8
        assert isinstance(fifth.result(), DetectionsReply)
        assert gate.batches == [1, 4] and batches(s.url) == (before[0] + 2, before[1] + 5)
        assert all(isinstance(r, DetectionsReply) and r.timings.queue_ms < max_wait_ms for r in replies)
        three = [pool.submit(post_raw, s.url, c, 2, t[2]) for c, t in zip(cars[:3], turns[:3], strict=True)]
        replies = [f.result() for f in three]  # 3 would pad to 4: they wait max_wait for the others
        assert max(r.timings.queue_ms for r in replies if isinstance(r, DetectionsReply)) >= max_wait_ms - 100
        fill = httpx.get(f"{s.url}/metrics", timeout=10).text
        assert 'phim_batch_fill_ratio_bucket{le="0.8"}' in fill


def test_phim_serve_sizes_the_slots_by_max_streams():
    # no warm-up: it would compile the graph (the test is about building it from the settings)
    with serve(None, engine="graph", max_streams=3, sector_voxels=512, warmup_sectors=0) as s:
        info = httpx.get(f"{s.url}/v1/model", timeout=10).json()
        assert (info["engine"], info["state_slots"], info["sector_voxels"]) == ("graph", 3, 512)
        assert info["slot_bytes"] > 0


def test_a_detector_with_fewer_slots_than_max_streams_fails_the_start_up():
    det = GraphStreamingDetector(comparable_detector().model, sector_voxels=512, slots=2)
    worker = Worker(lambda: (det, "test detector"), WorkerConfig(max_streams=3, warmup_sectors=0))
    worker.start()
    try:
        assert not worker.wait_ready(START_TIMEOUT_S)
        assert worker.status == (
            "start-up failed: ValueError: max_streams: 3, but the detector has 2 stream-state slots; "
            "expected at least max_streams (build it with slots=max_streams)"
        )
    finally:
        worker.close(1)
