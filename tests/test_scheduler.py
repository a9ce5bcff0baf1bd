"""The scheduler's decision (server/scheduler.py) as a pure function of the queue: at most max_batch, every
live stream queued -> now, and for a fixed-shape engine a full bucket now when waiting could only pad; a
batch's streams taken round-robin by tenant."""

from __future__ import annotations

import pytest

from model.graph.buckets import BATCH_BUCKETS
from server.scheduler import Dispatch, Wait, batch_fill, bucket_of, decide, fair_order

WAIT = 0.05  # max_wait_s


def fixed(heads: int, live: int, waited: float = 0.0, max_batch: int = 32) -> Dispatch | Wait:
    return decide(heads, live, waited, WAIT, max_batch, BATCH_BUCKETS)


def eager(heads: int, live: int, waited: float = 0.0, max_batch: int = 32) -> Dispatch | Wait:
    return decide(heads, live, waited, WAIT, max_batch, None)


@pytest.mark.parametrize("decide_", [fixed, eager])
def test_every_live_stream_queued_runs_now_and_max_batch_caps_it(decide_):
    assert decide_(5, 5) == Dispatch(5)  # nothing more is expected: no bucket to fill
    assert decide_(1, 1) == Dispatch(1)
    assert decide_(12, 40, max_batch=8) == Dispatch(8)  # the oldest 8; the rest next
    assert decide_(8, 40, max_batch=8) == Dispatch(8)


@pytest.mark.parametrize("decide_", [fixed, eager])
def test_after_max_wait_or_when_closing_whatever_is_queued_runs(decide_):
    assert decide_(3, 5, waited=WAIT) == Dispatch(3)
    assert decide(3, 5, 0.0, WAIT, 32, BATCH_BUCKETS, closing=True) == Dispatch(3)
    assert decide(3, 5, 0.0, 0.0, 32, None) == Dispatch(3)  # max_wait 0: never waits


def test_a_full_bucket_runs_now_when_waiting_could_only_pad_the_next():
    assert fixed(4, 5) == Dispatch(4)  # 5 would run padded to 8: 4 now, the fifth later
    assert fixed(8, 9) == Dispatch(8)
    assert fixed(8, 15) == Dispatch(8)
    assert fixed(4, 7, max_batch=6) == Dispatch(4)  # 6 at most: a batch of 6 pads to 8


def test_a_batch_that_just_misses_a_bucket_waits():
    assert fixed(3, 5, waited=0.01) == Wait(pytest.approx(0.04))  # 3 pads to 4: wait for the others
    assert fixed(7, 9) == Wait(WAIT)
    assert fixed(4, 8) == Wait(WAIT)  # the live streams can fill 8 exactly
    assert fixed(8, 16) == Wait(WAIT)
    assert fixed(1, 2) == Wait(WAIT)


def test_the_eager_engine_waits_for_every_live_stream():
    assert eager(4, 5) == Wait(WAIT)  # no padding: a fuller batch costs little more
    assert eager(8, 9) == Wait(WAIT)


def test_batch_fill():
    assert [bucket_of(n, BATCH_BUCKETS) for n in (1, 2, 3, 5, 9, 32)] == [1, 2, 4, 8, 16, 32]
    assert batch_fill(3, BATCH_BUCKETS) == 0.75
    assert batch_fill(8, BATCH_BUCKETS) == 1.0
    assert batch_fill(3, None) == 1.0
    with pytest.raises(ValueError, match="sectors: 33 in one batch; the largest bucket is 32"):
        bucket_of(33, BATCH_BUCKETS)
    with pytest.raises(ValueError, match="heads: 0"):
        decide(0, 3, 0.0, WAIT, 8, None)


def test_fair_order_takes_the_tenants_in_turn():
    # heads oldest first: a flooding tenant's 5 streams, then 2 of another, then a third's
    tenants = ["a.", "a.", "a.", "b.", "a.", "b.", "c.", "a."]
    order = fair_order(tenants)
    assert sorted(order) == list(range(8))  # every queued stream, once
    assert order == [0, 3, 6, 1, 5, 2, 4, 7]  # a, b, c, a, b, a, a, a: each tenant's oldest first
    assert [tenants[i] for i in order[:4]] == ["a.", "b.", "c.", "a."]  # a batch of 4: no tenant twice ahead
    assert fair_order(["x", "y", "z"]) == [0, 1, 2]  # one stream each: oldest first, as without tenants
    assert fair_order([]) == []
