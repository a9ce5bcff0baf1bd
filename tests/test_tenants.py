"""Tenants (server/tenants.py): a stream's tenant from its ID or its token's prefix; per-tenant stream caps;
a queue a tenant alone may fill but that makes room for a tenant within its share; batches shared
round-robin by tenant. Two tenants over a real uvicorn server, one flooding: the other gets its streams and
every one of its sectors answered. Accounting only: the forward is held shut while the queue fills."""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import torch
from server_helpers import START_TIMEOUT_S, StepGate, default_detector, sector_msg, serve

from contract import (
    MSGPACK,
    DetectionsReply,
    ErrorCode,
    ErrorReply,
    ServiceError,
    decode_response,
    encode_sector,
)
from model.stream import StreamingDetector
from server.admission import Backlog
from server.auth import TokenFile, add_token
from server.tenants import TenantQueue, plan_push_out, tenant_of_id
from server.worker import Worker, WorkerConfig

POINTS = np.random.default_rng(3).uniform(-20, 20, (300, 4)).astype(np.float32)


@pytest.fixture(scope="module")
def det() -> StreamingDetector:
    return default_detector()


def wait_for(cond: Callable[[], bool], timeout_s: float = 60) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, "condition never became true"
        time.sleep(0.02)


def test_a_streams_tenant(tmp_path: Path):
    assert tenant_of_id("fleet-a.car-7") == "fleet-a."
    assert tenant_of_id("fleet-a.depot.car") == "fleet-a."
    assert tenant_of_id("car1") == "car1"  # the ROS 2 bridge's default stream: a tenant of its own
    path = tmp_path / "tokens.jsonl"
    add_token(path, "fleet-a.")
    add_token(path, "fleet-a.depot-1.")  # the longest prefix wins
    add_token(path, "ops", admin=True)  # an admin token names no tenant
    tokens = TokenFile(path)
    assert tokens.tenant_of("fleet-a.car") == "fleet-a."
    assert tokens.tenant_of("fleet-a.depot-1.car") == "fleet-a.depot-1."
    assert tokens.tenant_of("fleet-b.car") == "fleet-b."  # no token covers it: up to the first '.'
    assert tokens.tenant_of("opsstream") == "opsstream"
    add_token(path, "fleet-b")
    assert tokens.tenant_of("fleet-b.car") == "fleet-b"  # re-read: a token's prefix now covers it


def test_the_push_out_plan():
    """Which queued sectors make room: the newest of the tenant furthest beyond its share, never below it."""
    queue, backlog = TenantQueue(share_sectors=2, share_points=500), Backlog(max_sectors=4, max_points=1000)
    queued: dict[str, list[Any]] = {"a.": [], "b.": []}
    for tenant, n in (("a.", 100), ("a.", 100), ("a.", 100), ("b.", 100)):
        sector = type("Queued", (), {"points": np.zeros((n, 4), np.float32)})()
        queued[tenant].insert(0, sector)  # newest first
        queue.add(tenant, n)
        backlog.add(n)
    plan = plan_push_out(queue, backlog, "c.", 50, lambda t: list(queued[t]))
    assert plan == [queued["a."][0]]  # a. holds 3 of its share of 2: its newest makes room
    assert plan_push_out(queue, backlog, "a.", 50, lambda t: list(queued[t])) is None  # beyond its own
    assert plan_push_out(queue, backlog, "b.", 50, lambda t: list(queued[t])) == [queued["a."][0]]
    assert plan_push_out(queue, backlog, "c.", 600, lambda t: list(queued[t])) is None  # over its points
    queue.remove("a.", 100)
    backlog.remove([100])  # now a. holds 2, b. 1: nobody beyond a share, and one free place
    backlog.max_sectors = 3
    assert plan_push_out(queue, backlog, "c.", 50, lambda t: list(queued[t])) is None


def test_default_shares_are_half_and_a_lone_tenant_may_fill_the_queue(det, monkeypatch):
    assert WorkerConfig().tenant_shares() == (128, 32, 2_000_000)
    assert WorkerConfig(max_streams=1, queue_size=1).tenant_shares()[:2] == (1, 1)
    w = Worker(lambda: (det, "test"), WorkerConfig(warmup_sectors=1, queue_size=6, deadline_ms=120_000))
    w.start()
    assert w.wait_ready(START_TIMEOUT_S), w.status
    gate = StepGate.install(det, monkeypatch)
    try:
        first = w.submit(sector_msg("solo.car", 0, POINTS))
        assert gate.entered.wait(START_TIMEOUT_S)
        futs = [w.submit(sector_msg("solo.car", s, POINTS)) for s in range(1, 8)]  # 6 queue, 1 refused
        refused = futs[-1].exception(10)
        assert isinstance(refused, ServiceError) and "queue_size=6" in refused.message
        gate.release()
        assert all(isinstance(f.result(120), DetectionsReply) for f in [first, *futs[:-1]])
    finally:
        gate.release()
        w.close(10)


def test_a_flooding_ros2_stream_leaves_the_queue_share_of_the_others(det, monkeypatch):
    """The ROS 2 bridge submits a topic's scans to one stream (`car1`: its own tenant); a flood of them fills
    the queue while it is alone, and the other tenants' sectors still get in (pushing its newest out) and
    are answered. Batches take the tenants' streams round-robin: the flood's one stream gets one place."""
    cfg = WorkerConfig(warmup_sectors=1, queue_size=8, deadline_ms=120_000, max_batch=4)
    w = Worker(lambda: (det, "test"), cfg)
    w.start()
    assert w.wait_ready(START_TIMEOUT_S), w.status
    gate = StepGate.install(det, monkeypatch)
    try:
        flood = [w.submit(sector_msg("car1", 0, POINTS), transport="ros2")]
        assert gate.entered.wait(START_TIMEOUT_S)
        flood += [w.submit(sector_msg("car1", s, POINTS), transport="ros2") for s in range(1, 20)]
        assert sum(f.done() for f in flood) == 11  # 8 queued, 11 refused at once (full), 1 running
        others = [w.submit(sector_msg(f"fleet-b.v{i}", 0, POINTS), transport="http") for i in range(4)]
        assert sum(f.done() for f in flood) == 15  # 4 of car1's newest pushed out; none of fleet-b refused
        pushed = [f.exception(0) for f in flood[5:9]]
        assert all(isinstance(e, ServiceError) and "beyond its share" in e.message for e in pushed), pushed
        assert not any(f.done() for f in others)
        gate.release()
        assert all(isinstance(f.result(120), DetectionsReply) for f in others)
        answered = [f.result(120) for f in flood if f.exception(120) is None]
        assert [r.seq for r in answered] == list(range(5))  # car1: seq 0 ran, 1-4 stayed queued, in order
        assert gate.batches[:2] == [1, 4]  # the held one; then car1's head and the 3 oldest of fleet-b
    finally:
        gate.release()
        w.close(10)


def _post(url: str, stream: str, seq: int, token: str) -> httpx.Response:
    headers = {"Content-Type": MSGPACK, "Authorization": f"Bearer {token}"}
    body = encode_sector(sector_msg(stream, seq, POINTS))
    return httpx.post(f"{url}/v1/streams/{stream}/sectors", content=body, headers=headers, timeout=120)


def _pending(url: str, token: str) -> int:
    r = httpx.get(f"{url}/v1/streams", headers={"Authorization": f"Bearer {token}"}, timeout=30)
    return sum(s["pending"] for s in r.json()["streams"])


def _reply(r: httpx.Response) -> Any:
    return decode_response(r.content)


def test_two_tenants_one_flooding_over_http(det, monkeypatch, tmp_path: Path):
    """Tenant A takes every stream it may and fills the queue; tenant B still starts its streams and gets
    every one of its sectors answered with detections. Before tenants: B got 503 "cannot start stream" and
    "queue full"."""
    path = tmp_path / "tokens.jsonl"
    a, b = add_token(path, "fleet-a."), add_token(path, "fleet-b.")
    settings = dict(auth_tokens=path, max_streams=20, tenant_max_streams=8, queue_size=16)
    settings |= dict(deadline_ms=120_000, idle_timeout_s=600)
    with serve(det, **settings) as s, ThreadPoolExecutor(48) as pool:
        gate = StepGate.install(det, monkeypatch)
        try:
            _flood_and_share(s.url, pool, gate, a, b)
        finally:
            gate.release()


def _flood_and_share(url: str, pool: ThreadPoolExecutor, gate: StepGate, a: str, b: str) -> None:
    send = lambda stream, seq, t: pool.submit(_post, url, stream, seq, t)  # noqa: E731
    held = send("fleet-a.s0", 0, a)
    assert gate.entered.wait(START_TIMEOUT_S)
    # A: 15 more streams at once; it may hold 8: 7 more start, 8 are refused at once
    starts = {f"fleet-a.s{i}": send(f"fleet-a.s{i}", 0, a) for i in range(1, 16)}
    wait_for(lambda: sum(f.done() for f in starts.values()) == 8)
    refused = [_reply(f.result()) for f in starts.values() if f.done()]
    assert all(isinstance(e, ErrorReply) and "tenant_max_streams=8" in e.message for e in refused)
    mine = [sid for sid, f in starts.items() if not f.done()]
    assert len(mine) == 7
    # A: a burst of sectors; it is alone, so it may fill the queue (16), the rest refused at once
    burst: list[Future[httpx.Response]] = []
    for seq in (1, 2):
        for sid in mine:
            burst.append(send(sid, seq, a))
            wait_for(lambda: burst[-1].done() or _pending(url, a) == 1 + 7 + len(burst))
    wait_for(lambda: _pending(url, a) + sum(f.done() for f in burst) == 1 + 7 + len(burst))
    assert _pending(url, a) == 17  # 16 queued and the one held in the forward
    # B: 8 streams (its share), each a sector: every one gets in, pushing out A's newest
    b_first = [send(f"fleet-b.v{i}", 0, b) for i in range(8)]
    wait_for(lambda: _pending(url, b) == 8)
    assert _pending(url, a) == 9
    gate.release()
    for r in [held, *starts.values(), *burst]:  # A: each sector has its one answer, 200 or 503
        assert r.result().status_code in (200, 503)
    assert sum(r.result().status_code == 200 for r in [held, *starts.values(), *burst]) == 9
    replies = [_reply(f.result()) for f in b_first]
    replies += [_reply(r) for r in pool.map(lambda i: _post(url, f"fleet-b.v{i}", 1, b), range(8))]
    assert all(isinstance(r, DetectionsReply) for r in replies), replies
    assert [r.context_sectors for r in replies] == [1] * 8 + [2] * 8
    # B's own share holds too: a ninth stream of B is refused while its 8 live
    ninth = _reply(_post(url, "fleet-b.v8", 0, b))
    assert ninth.code is ErrorCode.OVERLOADED and "tenant 'fleet-b.' holds 8" in ninth.message


def test_batches_share_the_device_between_tenants(det, monkeypatch):
    """A batch takes the tenants' queued streams in turn: 6 streams of A and 2 of B, max_batch 4: A 2, B 2."""
    w = Worker(lambda: (det, "test"), WorkerConfig(warmup_sectors=1, max_batch=4, deadline_ms=120_000))
    w.start()
    assert w.wait_ready(START_TIMEOUT_S), w.status
    sizes: list[list[int]] = []
    real = det.step

    def step(points: list[torch.Tensor], states: list[Any]) -> Any:
        sizes.append([int(p.shape[0]) for p in points])
        return real(points, states)

    gate = StepGate.install(det, monkeypatch)
    try:
        first = w.submit(sector_msg("a.s0", 0, POINTS[:100]))
        assert gate.entered.wait(START_TIMEOUT_S)
        monkeypatch.setattr(gate, "real", step)
        futs = [w.submit(sector_msg(f"a.s{i}", 0, POINTS[:100])) for i in range(1, 7)]
        futs += [w.submit(sector_msg(f"b.s{i}", 0, POINTS[:200])) for i in range(2)]
        gate.release()
        assert all(isinstance(f.result(120), DetectionsReply) for f in [first, *futs])
    finally:
        gate.release()
        w.close(10)
    assert sizes[1] == [100, 200, 100, 200]  # A's oldest, B's oldest, in turn (before: 4 of A)
