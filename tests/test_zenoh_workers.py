"""Forged worker tokens, without the ACL, against a real worker (ZenohTransport around the real Worker, a
zenoh peer on loopback) and real clients: a token naming the worker's session under another worker ID
displaces nothing (whichever came first), its withdrawal removes nothing, and a flood of 3,000 forged
tokens neither makes routing fail nor grows the client's table past its bound (clients/zenoh_workers.py)."""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import pytest
import zenoh
from server_helpers import START_TIMEOUT_S, default_detector, free_endpoint, sector_msg

from clients.zenoh_client import ZenohClient
from clients.zenoh_workers import MAX_CLAIMS, LiveWorkers, State
from contract import ErrorCode, KeySpace, Limits
from server.worker import Worker, WorkerConfig
from server.zenoh_transport import ZenohConfig, ZenohTransport, open_session

KEYS = KeySpace()
LIMITS = Limits(max_body_bytes=2**20, max_points=50_000, max_string_len=64)
REAL = "real-w"
POINTS = np.random.default_rng(5).uniform(-20, 20, (300, 4)).astype(np.float32)
WAIT_S = 30.0  # bounded waits for what zenoh propagates; generous for a busy machine


@dataclass
class Hub:
    endpoint: str
    transport: ZenohTransport
    rejected: list[ErrorCode]

    @property
    def zid(self) -> str:
        session = self.transport.session
        assert session is not None
        return str(session.zid())


@pytest.fixture(scope="module")
def worker() -> Iterator[Worker]:
    det = default_detector()
    w = Worker(lambda: (det, "test"), WorkerConfig(worker_id=REAL, warmup_sectors=1, deadline_ms=60_000))
    w.start()
    assert w.wait_ready(START_TIMEOUT_S), w.status
    yield w
    w.close(10)


def start_hub(worker: Worker, announce: bool = True) -> Hub:
    endpoint, rejected = free_endpoint(), []
    transport = ZenohTransport(
        worker.submit, ZenohConfig(listen=(endpoint,)), REAL, LIMITS, on_reject=rejected.append
    )
    transport.start(announce=announce)
    return Hub(endpoint, transport, rejected)


def attacker(endpoint: str) -> zenoh.Session:
    return open_session(ZenohConfig(mode="client", listen=(), connect=(endpoint,)))


def wait_until(what: Callable[[], bool], timeout_s: float = WAIT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not what():
        assert time.monotonic() < deadline, f"not within {timeout_s} s"
        time.sleep(0.02)


def stream(tag: str) -> str:
    return f"car-{tag}-{uuid.uuid4().hex[:6]}"


@pytest.mark.parametrize("forged_first", [True, False])
def test_a_token_naming_the_workers_session_displaces_nothing(worker: Worker, forged_first: bool):
    hub = start_hub(worker, announce=not forged_first)
    try:
        with attacker(hub.endpoint) as rogue:
            # worker IDs sorting before and after the real one: neither order of arrival may matter
            forged = [rogue.liveliness().declare_token(KEYS.worker(w, hub.zid)) for w in ("0-fake", "z-fake")]
            if forged_first:
                time.sleep(0.3)
                hub.transport.announce()
            with (
                ZenohClient(connect=(hub.endpoint,), worker=REAL, timeout_s=20) as pinned,
                ZenohClient(connect=(hub.endpoint,), auto_workers=True, timeout_s=20) as auto,
            ):
                sid = stream("pinned")
                assert pinned.send(sector_msg(sid, 0, POINTS)).worker_id == REAL
                for i in range(4):
                    assert auto.send(sector_msg(stream(f"auto{i}"), 0, POINTS)).worker_id == REAL
                assert pinned.ignored_replies == 0 and auto.ignored_replies == 0
                assert auto.workers() == [REAL]  # the forged IDs are refuted by their probes
                claims = auto._live.claims()
                assert claims[(REAL, hub.zid)] is State.CONFIRMED
                assert claims[("0-fake", hub.zid)] is claims[("z-fake", hub.zid)] is State.REFUTED

                for token in forged:  # the forged tokens go: the real worker stays
                    token.undeclare()
                wait_until(lambda: ("z-fake", hub.zid) not in auto._live.claims())
                assert auto.workers() == [REAL]
                assert pinned.send(sector_msg(sid, 1, POINTS)).worker_id == REAL
                assert auto.send(sector_msg(stream("after"), 0, POINTS)).worker_id == REAL
        assert hub.rejected == []  # the probes are answered, counted nowhere
    finally:
        hub.transport.close(drain_timeout_s=10)


def test_three_thousand_forged_tokens_do_not_make_routing_fail(worker: Worker):
    hub = start_hub(worker)
    try:
        with attacker(hub.endpoint) as rogue:
            liveliness = rogue.liveliness()
            tokens = []
            for i in range(1000):  # made-up workers, made-up sessions, the worker's own session's ID
                made_up = uuid.uuid4().hex
                tokens.append(liveliness.declare_token(KEYS.worker(f"fake-{i}", made_up)))
                tokens.append(liveliness.declare_token(KEYS.worker(f"fake-s-{i}", hub.zid)))
                tokens.append(liveliness.declare_token(KEYS.worker(REAL, uuid.uuid4().hex)))
            with ZenohClient(connect=(hub.endpoint,), auto_workers=True, timeout_s=20) as auto:
                for i in range(8):
                    assert auto.send(sector_msg(stream(f"flood{i}"), 0, POINTS)).worker_id == REAL
                live = auto._live
                wait_until(lambda: len(live.claims()) >= 3001)  # all seen (the history may come late)
                wait_until(lambda: State.PENDING not in live.claims().values(), 120)
                claims = live.claims()
                assert len(claims) <= MAX_CLAIMS and live.dropped == 0
                assert [c for c, s in claims.items() if s is State.CONFIRMED] == [(REAL, hub.zid)]
                assert auto.workers() == [REAL]
            for token in tokens:
                token.undeclare()
    finally:
        hub.transport.close(drain_timeout_s=10)


def test_the_claim_table_is_bounded(worker: Worker, caplog: pytest.LogCaptureFixture):
    hub = start_hub(worker)
    try:
        with attacker(hub.endpoint) as rogue, attacker(hub.endpoint) as client:
            declare = rogue.liveliness().declare_token
            tokens = [declare(KEYS.worker(f"f-{i}", uuid.uuid4().hex)) for i in range(200)]
            live = LiveWorkers(client, KEYS, probe_timeout_s=5.0, max_claims=16)
            try:
                seen = []
                deadline = time.monotonic() + 3.0
                while time.monotonic() < deadline:  # never more than the bound, whatever arrives when
                    seen.append(len(live.claims()))
                    time.sleep(0.01)
                with caplog.at_level("WARNING", logger="clients.zenoh_workers"):
                    live.refresh(5.0)  # 201 claims at once: 16 kept, the rest dropped, counted and logged
                assert max([*seen, len(live.claims())]) <= 16
                assert live.dropped > 0 and "dropped so far" in caplog.text
            finally:
                live.close()
            for token in tokens:
                token.undeclare()
    finally:
        hub.transport.close(drain_timeout_s=10)
