"""The worker (stream table + scheduler + device loop) with the real default model, no transport."""

from __future__ import annotations

import contextlib
import gc
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import Future
from typing import Any

import numpy as np
import pytest
from server_helpers import (
    START_TIMEOUT_S,
    StepGate,
    assert_same_boxes,
    comparable_detector,
    sector_msg,
)

from contract import DetectionsReply, ErrorCode, ServiceError
from model.stream import StreamingDetector
from server.worker import Worker, WorkerConfig


@pytest.fixture(scope="module")
def det() -> StreamingDetector:
    return comparable_detector()


@contextlib.contextmanager
def running(det: StreamingDetector, **kw: Any) -> Iterator[Worker]:
    w = Worker(lambda: (det, "test detector"), WorkerConfig(warmup_sectors=1, **kw))
    w.start()
    assert w.wait_ready(START_TIMEOUT_S), w.status
    try:
        yield w
    finally:
        w.close(10)


def ok(fut: Future) -> DetectionsReply:
    return fut.result(60)


def err(fut: Future) -> ServiceError:
    e = fut.exception(60)
    assert isinstance(e, ServiceError), e
    return e


def answered(w: Worker) -> dict[str, float]:
    return {
        s.labels["outcome"]: s.value
        for m in w.metrics.sectors.collect()
        for s in m.samples
        if s.name.endswith("_total")
    }


def check(reply: DetectionsReply, ref: Any) -> None:
    assert_same_boxes(reply.boxes, reply.scores, reply.labels, ref)


def test_stream_equals_direct_model(det, scan_a, ref_a):
    with running(det) as w:
        replies = [ok(w.submit(sector_msg("car", i, s))) for i, s in enumerate(scan_a)]
    assert len(ref_a[-1]) > 0  # the reference has boxes, so the comparison means something
    for i, (r, ref) in enumerate(zip(replies, ref_a, strict=True)):
        check(r, ref)
        assert (r.stream_id, r.seq, r.context_sectors, r.gap) == ("car", i, i + 1, 0)
        assert r.class_names == tuple(det.cfg.head.class_names[k] for k in r.labels)
        assert r.timings.total_ms >= r.timings.model_ms > 0


def test_two_streams_batch_together_and_never_mix(det, monkeypatch, scan_a, scan_b, ref_a, ref_b):
    with running(det) as w:
        gate = StepGate.install(det, monkeypatch)
        blocker = w.submit(sector_msg("z", 0, scan_a[0]))
        assert gate.entered.wait(START_TIMEOUT_S)
        futs = [
            (w.submit(sector_msg("a", i, scan_a[i])), w.submit(sector_msg("b", i, scan_b[i])))
            for i in range(4)
        ]
        gate.release()
        ok(blocker)
        for i, (fa, fb) in enumerate(futs):
            check(ok(fa), ref_a[i])
            check(ok(fb), ref_b[i])
    assert gate.batches == [1, 2, 2, 2, 2]  # one sector per stream per forward, streams in order


def test_stale_and_duplicate_seq_leave_the_stream_unharmed(det, scan_a, ref_a):
    with running(det) as w:
        check(ok(w.submit(sector_msg("car", 10, scan_a[0], index=0))), ref_a[0])
        check(ok(w.submit(sector_msg("car", 11, scan_a[1], index=1))), ref_a[1])
        for seq in (11, 5):
            e = err(w.submit(sector_msg("car", seq, scan_a[3], index=3)))
            assert e.code == ErrorCode.STALE_SEQUENCE and e.field == "seq" and "greater than 11" in e.message
        r2 = ok(w.submit(sector_msg("car", 12, scan_a[2], index=2)))
        check(r2, ref_a[2])
        assert r2.gap == 0 and r2.context_sectors == 3
        assert w.stream("car")["sectors"] == 3


def test_gap_is_reported_and_reset_starts_fresh(det, scan_a, ref_a):
    with running(det) as w:
        ok(w.submit(sector_msg("car", 0, scan_a[0])))
        r = ok(w.submit(sector_msg("car", 3, scan_a[1], index=1)))
        assert r.gap == 2 and w.stream("car")["gaps"] == 2
        fresh = ok(w.submit(sector_msg("car", 0, scan_a[0], reset=True)))  # seq may restart with reset
        assert fresh.gap == 0 and fresh.context_sectors == 1 and fresh.cold_start
        check(fresh, ref_a[0])


def test_a_reply_says_when_its_stream_started_cold(det, scan_a):
    """cold_start: the sector ran on a fresh state. A stream's first sector, and the next one after the
    stream was ended (or evicted, or lost in a restart) even with a later seq; not the sectors between."""
    with running(det) as w:
        first, second = (ok(w.submit(sector_msg("car", i, scan_a[i]))) for i in range(2))
        assert (first.cold_start, second.cold_start) == (True, False)
        w.end_stream("car")
        again = ok(w.submit(sector_msg("car", 2, scan_a[2])))
        assert again.cold_start and again.context_sectors == 1 and again.gap == 0
        assert not ok(w.submit(sector_msg("car", 3, scan_a[3]))).cold_start


def test_overload_rejects_at_once_and_every_request_is_answered_once(det, monkeypatch, scan_a, ref_a):
    with running(det, queue_size=3) as w:
        gate = StepGate.install(det, monkeypatch)
        futs = [w.submit(sector_msg("s0", 0, scan_a[0]))]
        assert gate.entered.wait(START_TIMEOUT_S)  # s0 is in the forward, the queue is empty
        futs += [w.submit(sector_msg(f"s{i}", 0, scan_a[0])) for i in range(1, 9)]
        rejected = [f for f in futs if f.done()]
        assert len(rejected) == 5 and w.queue_depth == 3
        for f in rejected:
            e = err(f)
            assert e.code == ErrorCode.OVERLOADED and e.retry_after_s is not None and e.retry_after_s > 0
            assert "queue_size=3" in e.message
        gate.release()
        for f in futs:
            if f not in rejected:
                check(ok(f), ref_a[0])
        check(ok(w.submit(sector_msg("s1", 1, scan_a[1]))), ref_a[1])  # recovered; s1's state intact
        counts = answered(w)
    assert counts == {"ok": 5.0, "overloaded": 5.0}


def test_deadline_and_retry_of_the_same_seq(det, monkeypatch, scan_a, ref_a):
    with running(det, deadline_ms=100) as w:
        gate = StepGate.install(det, monkeypatch)
        blocker = w.submit(sector_msg("z", 0, scan_a[0]))
        assert gate.entered.wait(START_TIMEOUT_S)
        late = w.submit(sector_msg("car", 0, scan_a[0]))
        time.sleep(0.3)
        gate.release()
        ok(blocker)
        e = err(late)
        assert e.code == ErrorCode.DEADLINE_EXCEEDED and "deadline is 100 ms" in e.message
        check(ok(w.submit(sector_msg("car", 0, scan_a[0]))), ref_a[0])  # a failed seq may be sent again


def test_failed_batch_answers_errors_and_states_stay(det, monkeypatch, scan_a, scan_b, ref_a, ref_b):
    with running(det) as w:
        ok(w.submit(sector_msg("a", 0, scan_a[0])))
        gate = StepGate.install(det, monkeypatch)
        gate.fail_at = {1}
        blocker = w.submit(sector_msg("z", 0, scan_a[0]))
        assert gate.entered.wait(START_TIMEOUT_S)
        fa, fb = w.submit(sector_msg("a", 1, scan_a[1])), w.submit(sector_msg("b", 0, scan_b[0]))
        gate.release()
        ok(blocker)
        for f in (fa, fb):
            e = err(f)
            assert e.code == ErrorCode.INTERNAL and "injected fault" in e.message
        check(ok(w.submit(sector_msg("a", 1, scan_a[1]))), ref_a[1])  # state as before the failed batch
        check(ok(w.submit(sector_msg("b", 0, scan_b[0]))), ref_b[0])
        assert gate.batches == [1, 2, 1, 1]


def test_bad_points_never_enter_a_batch(det, monkeypatch, scan_a):
    with running(det) as w:
        gate = StepGate.install(det, monkeypatch, closed=False)
        nan = scan_a[0].copy()
        nan[5, 2] = np.nan
        e = err(w.submit(sector_msg("car", 0, nan)))
        assert e.code == ErrorCode.INVALID_FIELD and e.field == "points" and "NaN" in e.message
        e = err(w.submit(sector_msg("car", 0, scan_a[0], index=4)))
        assert e.code == ErrorCode.INVALID_FIELD and e.field == "sector_index" and "0..3" in e.message
        e = err(w.submit(sector_msg("car", 0, np.zeros(8, np.float32))))
        assert e.code == ErrorCode.INVALID_FIELD and e.field == "points" and "2-D" in e.message
        assert gate.batches == [] and w.streams() == []
        ok(w.submit(sector_msg("car", 0, scan_a[0])))  # the stream starts cleanly afterwards


def test_stream_limit(det, scan_a):
    with running(det, max_streams=2) as w:
        ok(w.submit(sector_msg("a", 0, scan_a[0])))
        ok(w.submit(sector_msg("b", 0, scan_a[0])))
        e = err(w.submit(sector_msg("c", 0, scan_a[0])))
        assert e.code == ErrorCode.OVERLOADED and e.field == "stream_id" and "max_streams=2" in e.message
        assert e.retry_after_s == 10.0
        w.end_stream("a")
        ok(w.submit(sector_msg("c", 0, scan_a[0])))


def test_idle_eviction(det, scan_a):
    with running(det, idle_timeout_s=0.2) as w:
        ok(w.submit(sector_msg("a", 0, scan_a[0])))
        ok(w.submit(sector_msg("b", 0, scan_a[0])))
        deadline = time.monotonic() + 10
        while w.streams() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert w.streams() == []
        assert w.metrics.evictions._value.get() == 2
        r = ok(w.submit(sector_msg("a", 1, scan_a[1])))
        assert r.context_sectors == 1 and r.cold_start  # evicted: the stream starts cold, and says so


def test_end_stream(det, monkeypatch, scan_a):
    with running(det) as w:
        with pytest.raises(ServiceError) as info:
            w.end_stream("nope")
        e = info.value
        assert e.code == ErrorCode.UNKNOWN_STREAM and "'nope'" in e.message
        gate = StepGate.install(det, monkeypatch)
        running_one = w.submit(sector_msg("car", 0, scan_a[0]))
        assert gate.entered.wait(START_TIMEOUT_S)
        queued = w.submit(sector_msg("car", 1, scan_a[1]))
        w.end_stream("car")
        assert err(queued).code == ErrorCode.UNKNOWN_STREAM
        gate.release()
        assert ok(running_one).context_sectors == 1  # the sector in the forward still gets its answer
        assert w.streams() == []


def test_not_ready_during_warm_up(det, monkeypatch, scan_a):
    gate = StepGate.install(det, monkeypatch)
    w = Worker(lambda: (det, "test detector"), WorkerConfig(warmup_sectors=1))
    w.start()
    try:
        assert gate.entered.wait(START_TIMEOUT_S) and not w.ready
        e = err(w.submit(sector_msg("car", 0, scan_a[0])))
        assert e.code == ErrorCode.NOT_READY and "warming up" in e.message
        gate.release()
        assert w.wait_ready(START_TIMEOUT_S)
    finally:
        w.close(10)


def test_close_drains_everything_in_flight(det, monkeypatch, scan_a):
    w = Worker(lambda: (det, "test detector"), WorkerConfig(warmup_sectors=1))
    w.start()
    assert w.wait_ready(START_TIMEOUT_S)
    gate = StepGate.install(det, monkeypatch)
    futs = [w.submit(sector_msg(f"s{i}", 0, scan_a[0])) for i in range(3)]
    futs.append(w.submit(sector_msg("s0", 1, scan_a[1])))
    assert gate.entered.wait(START_TIMEOUT_S)
    closer = threading.Thread(target=w.close, args=(30,))
    closer.start()
    time.sleep(0.1)
    late = w.submit(sector_msg("s9", 0, scan_a[0]))
    assert err(late).code == ErrorCode.NOT_READY
    gate.release()
    closer.join(60)
    assert [ok(f).seq for f in futs] == [0, 0, 0, 1]
    assert answered(w) == {"ok": 4.0, "not_ready": 1.0}


def test_close_answers_what_the_drain_timeout_leaves(det, monkeypatch, scan_a):
    w = Worker(lambda: (det, "test detector"), WorkerConfig(warmup_sectors=1))
    w.start()
    assert w.wait_ready(START_TIMEOUT_S)
    gate = StepGate.install(det, monkeypatch)
    in_forward = w.submit(sector_msg("s0", 0, scan_a[0]))
    assert gate.entered.wait(START_TIMEOUT_S)
    queued = [w.submit(sector_msg(f"s{i}", 0, scan_a[0])) for i in (1, 2)]
    closer = threading.Thread(target=w.close, args=(0.2,))
    closer.start()
    for f in queued:  # answered at the drain timeout although the forward is still stuck
        e = err(f)
        assert e.code == ErrorCode.NOT_READY and "shut down before this sector ran" in e.message
    assert not in_forward.done()
    gate.release()
    closer.join(60)
    assert ok(in_forward).seq == 0
    assert answered(w) == {"ok": 1.0, "not_ready": 2.0}


def test_queued_points_are_bounded_and_an_empty_queue_takes_any_sector(det, monkeypatch, scan_a):
    """max_queued_points bounds the memory the queue holds: a sector that would pass it gets OVERLOADED at
    once (nothing queued, its stream unharmed); one that fits, or any sector when the queue is empty, is
    queued and answered."""
    big, small = scan_a[0][:3000], scan_a[1][:1000]
    with running(det, max_queued_points=5000) as w:
        gate = StepGate.install(det, monkeypatch)
        running_one = w.submit(sector_msg("r", 0, scan_a[2]))
        assert gate.entered.wait(START_TIMEOUT_S)  # in the forward: the queue is empty
        alone = w.submit(sector_msg("a", 0, np.concatenate([scan_a[0]] * 2)[:6000]))  # > 5000, queue empty
        refused = w.submit(sector_msg("b", 0, big))  # 6000 + 3000 > 5000
        e = err(refused)
        assert e.code == ErrorCode.OVERLOADED and "max_queued_points=5000" in e.message and e.retry_after_s
        assert w.queue_depth == 1
        gate.release()
        assert ok(running_one).context_sectors == ok(alone).context_sectors == 1
        later = [w.submit(sector_msg("c", 0, small)), w.submit(sector_msg("b", 0, big))]  # 4000: both fit
        assert [ok(f).context_sectors for f in later] == [1, 1]  # b was never started: seq 0 again


def test_the_heap_alive_after_the_warm_up_is_frozen(det):
    """Once ready, the worker has moved what is alive (model, modules, caches) out of the collector's reach,
    so a full collection while serving walks only what serving allocates."""
    gc.unfreeze()  # the heap this module's fixture froze (conftest): the worker's own freeze shows from 0
    assert gc.get_freeze_count() == 0
    with running(det):
        assert gc.get_freeze_count() > 10_000


WARM_NMS = """
from model.checkpoint import resolve_checkpoint
from model.ops.nms_numba import _class_nms_batch, _greedy
from model.stream import StreamingDetector
from server.warmup import warm_up

before = len(_greedy.signatures), len(_class_nms_batch.signatures)
warm_up(StreamingDetector(resolve_checkpoint("default")[0]), 0)
print(*before, len(_greedy.signatures), len(_class_nms_batch.signatures))
"""


def test_warm_up_compiles_the_nms_kernels_before_the_first_request() -> None:
    """In a fresh interpreter the NMS kernels (`_greedy` and the batch's `_class_nms_batch`, which compile
    the kernels they call with them) are not compiled; after a warm-up, even of no forwards, they are
    (compiled, or loaded from numba's cache). Without it, the first sector with a candidate above the score
    threshold paid the compile: over 10 s on a loaded machine's fresh install, a client's timeout."""
    out = subprocess.run([sys.executable, "-c", WARM_NMS], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["0", "0", "1", "1"], out.stdout
