"""Faults with real parts: thousands of idle streams (bounded, evicted, the limit's clear error), a worker
killed with SIGKILL under load (every client call ends with an error within its timeout, none hangs), and
a zenoh router killed and restarted (errors while it is down, everyone reconnects), and a slow pub/sub
consumer (nobody else waits for it)."""

from __future__ import annotations

import gc
import os
import signal
import subprocess
import sys
import threading
import time
import weakref
from concurrent.futures import Future
from pathlib import Path

import httpx
import numpy as np
import pytest
import zenoh
from conftest import rss_bytes
from server_helpers import LATE_S, START_TIMEOUT_S, default_detector, free_endpoint, free_port, sector_msg

from clients.base import ClientError
from clients.bench.fleet import start_router
from clients.connect import ConnectConfig, Transport, make_client
from clients.zenoh_client import ZenohClient
from contract import DetectionsReply, ErrorCode, KeySpace, Limits, SectorMessage, ServiceError, encode_sector
from server.worker import Worker, WorkerConfig
from server.zenoh_transport import MSGPACK_ENCODING, ZenohConfig, ZenohTransport, open_session

REPO = Path(__file__).resolve().parents[1]
KEYS = KeySpace()
SMALL = np.random.default_rng(1).uniform(-10, 10, (20, 4)).astype(np.float32)


def test_thousands_of_idle_streams_are_bounded_and_evicted() -> None:
    n = 2000
    w = Worker(
        lambda: (default_detector(), "test"),
        WorkerConfig(
            warmup_sectors=1,
            max_streams=n,
            idle_timeout_s=600.0,
            max_batch=32,
            queue_size=n,
            deadline_ms=START_TIMEOUT_S * 1e3,  # no sector may expire: this is about memory, not time
        ),
    )
    w.start()
    assert w.wait_ready(START_TIMEOUT_S), w.status
    try:
        before = rss_bytes()
        futures = [w.submit(sector_msg(f"idle-{i}", 0, SMALL)) for i in range(n)]
        assert all(f.result(START_TIMEOUT_S).context_sectors == 1 for f in futures)  # bounded, not timed
        grown = (rss_bytes() - before) / 2**20  # MB: n small states (~7 KB each) and the allocator's pools
        assert len(w.streams()) == n and grown < 1000, grown  # 200-550 MB measured
        states = [weakref.ref(e.state) for e in list(w.table.entries.values())]
        with pytest.raises(ServiceError) as full:
            w.submit(sector_msg("one-more", 0, SMALL)).result(START_TIMEOUT_S)
        assert full.value.code is ErrorCode.OVERLOADED and f"max_streams={n}" in full.value.message
        w.table.idle_timeout_s = 1.0  # now let them idle out (filled under a long timeout, however slow)
        deadline = time.monotonic() + START_TIMEOUT_S
        while w.streams() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert w.streams() == [] and w.metrics.evictions._value.get() == n
        gc.collect()
        assert sum(s() is not None for s in states) == 0  # nothing holds an evicted stream's state
        assert w.submit(sector_msg("one-more", 0, SMALL)).result(START_TIMEOUT_S).context_sectors == 1
    finally:
        w.close(10)


def test_a_killed_worker_gives_every_client_call_an_error_within_its_timeout(tmp_path: Path) -> None:
    port, zport = free_port(), free_port()
    url, zenoh = f"http://127.0.0.1:{port}", f"tcp/127.0.0.1:{zport}"
    env = {**os.environ, "PHIM_PORT": str(port), "PHIM_ZENOH_LISTEN": zenoh, "PHIM_WARMUP_SECTORS": "1"}
    log = (tmp_path / "serve.log").open("w")
    server = subprocess.Popen(
        [sys.executable, "-m", "phim", "serve"], cwd=REPO, env=env, stdout=log, stderr=log
    )
    try:
        deadline = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < deadline:
            assert server.poll() is None, (tmp_path / "serve.log").read_text()[-2000:]
            try:
                if httpx.get(f"{url}/health/ready", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.3)
        timeout_s = 3.0
        cfg = {
            t: ConnectConfig(transport=t, url=url, zenoh_connect=(zenoh,), timeout_s=timeout_s)
            for t in Transport
        }
        after_kill: dict[str, list[float]] = {t.value: [] for t in Transport}
        killed = threading.Event()

        def drive(t: Transport) -> None:
            with make_client(cfg[t]) as client:
                seq = 0
                while len(after_kill[t.value]) < 3:  # three calls after the kill
                    t0 = time.monotonic()
                    try:
                        client.send(sector_msg(f"kill-{t.value}", seq, SMALL))
                        ok = True
                    except ClientError:
                        ok = False
                    if killed.is_set() and not ok:
                        after_kill[t.value].append(time.monotonic() - t0)
                    seq += 1

        drivers = [threading.Thread(target=drive, args=(t,), daemon=True) for t in Transport]
        for d in drivers:
            d.start()
        time.sleep(1.5)  # under load
        server.send_signal(signal.SIGKILL)
        killed.set()
        for d in drivers:
            d.join(4 * (timeout_s + LATE_S))
            assert not d.is_alive(), "a client call hung after the worker died"
        for transport, seconds in after_kill.items():
            assert len(seconds) == 3 and max(seconds) <= timeout_s + LATE_S, (transport, seconds)
    finally:
        if server.poll() is None:
            server.kill()
        server.wait(30)
        log.close()


def test_a_router_restart_errors_what_was_in_flight_and_everyone_reconnects(tmp_path: Path) -> None:
    """Worker and vehicle are both clients of `phim router`. SIGKILL the router: the sector in flight and
    the sectors sent while it is down end with an error within the client's timeout; the router comes back
    on the same endpoint: both sessions reconnect by themselves, the worker is seen again and the stream
    goes on where it was (its state lived in the worker)."""
    endpoint, timeout_s = free_endpoint(), 2.0
    log = (tmp_path / "router.log").open("w")
    router = start_router(endpoint, log)
    worker = Worker(lambda: (default_detector(), "test"), WorkerConfig(worker_id="w-rr", warmup_sectors=1))
    worker.start()
    assert worker.wait_ready(START_TIMEOUT_S), worker.status
    arrived, release = threading.Event(), threading.Event()

    def submit(msg: SectorMessage) -> Future[DetectionsReply]:
        if msg.seq == 1:  # held in the worker while the router dies
            arrived.set()
            release.wait(START_TIMEOUT_S)
        return worker.submit(msg)

    joined = ZenohConfig(mode="client", listen=(), connect=(endpoint,))
    transport = ZenohTransport(submit, joined, worker.worker_id, Limits())
    transport.start()
    try:
        # `car` times out quickly (the errors); `patient` sends what must be answered, however busy it is
        with (
            ZenohClient(connect=(endpoint,), timeout_s=timeout_s) as car,
            ZenohClient(connect=(endpoint,), timeout_s=START_TIMEOUT_S) as patient,
        ):
            assert patient.send(sector_msg("rr-1", 0, SMALL)).cold_start
            errors: list[tuple[BaseException, float]] = []

            def in_flight() -> None:
                t0 = time.monotonic()
                try:
                    car.send(sector_msg("rr-1", 1, SMALL))
                except ClientError as e:
                    errors.append((e, time.monotonic() - t0))

            sender = threading.Thread(target=in_flight, daemon=True)
            sender.start()
            assert arrived.wait(START_TIMEOUT_S)
            router.send_signal(signal.SIGKILL)
            router.wait(10)
            release.set()
            sender.join(timeout_s + LATE_S)
            assert len(errors) == 1 and errors[0][1] <= timeout_s + LATE_S, errors
            for seq in (2, 3):  # while the router is down
                t0 = time.monotonic()
                with pytest.raises(ClientError):
                    car.send(sector_msg("rr-1", seq, SMALL))
                assert time.monotonic() - t0 <= timeout_s + LATE_S  # an error within the timeout, no hang
            router = start_router(endpoint, log)
            back = time.monotonic()
            while car.workers(timeout_s=1.0) != ["w-rr"] or patient.workers(timeout_s=1.0) != ["w-rr"]:
                assert time.monotonic() - back < START_TIMEOUT_S, "the sessions did not come back"
                time.sleep(0.2)
            reply = patient.send(sector_msg("rr-1", 4, SMALL))
            assert not reply.cold_start and reply.context_sectors > 1, reply
            print(f"router back: worker seen again after {time.monotonic() - back:.1f} s")
    finally:
        transport.close(10)
        worker.close(10)
        router.kill()
        router.wait(10)
        log.close()


def test_a_slow_pub_sub_consumer_harms_no_other_stream() -> None:
    """A vehicle puts 120 sectors at once and does not read its answers (its subscriber's callback is stuck
    on the first one). Meanwhile another vehicle's request/reply sectors are all answered, and once the slow
    one reads again (50 ms each) it gets exactly one answer per sector (the queue holds them all: this is
    about reading). Accounting, not timing: the fast vehicle's times are printed, not asserted."""
    n, endpoint = 120, free_endpoint()
    cfg = WorkerConfig(
        worker_id="w-slow", warmup_sectors=1, queue_size=n + 64, deadline_ms=START_TIMEOUT_S * 1e3
    )
    worker = Worker(lambda: (default_detector(), "test"), cfg)
    worker.start()
    assert worker.wait_ready(START_TIMEOUT_S), worker.status
    transport = ZenohTransport(worker.submit, ZenohConfig(listen=(endpoint,)), worker.worker_id, Limits())
    transport.start()
    joined = ZenohConfig(mode="client", listen=(), connect=(endpoint,))
    answers: list[str] = []
    reading = threading.Event()  # set once the fast vehicle is done: until then the reader is stuck

    def read_slowly(sample: zenoh.Sample) -> None:
        answers.append(str(sample.key_expr).rsplit("/", 1)[1])
        reading.wait(START_TIMEOUT_S)
        time.sleep(0.05)

    try:
        with open_session(joined) as slow, ZenohClient(connect=(endpoint,), timeout_s=START_TIMEOUT_S) as car:
            before = [_timed(car, "fast-1", seq) for seq in range(10)]
            subs = [
                slow.declare_subscriber(key, read_slowly)
                for key in (KEYS.detections("slow-1"), KEYS.errors("slow-1"))
            ]
            time.sleep(0.3)
            for seq in range(n):
                body = encode_sector(sector_msg("slow-1", seq, SMALL))
                slow.put(KEYS.sectors("slow-1"), body, encoding=MSGPACK_ENCODING)
            during = [_timed(car, "fast-1", seq) for seq in range(10, 40)]  # each answered (else ClientError)
            assert len(answers) <= 1  # ... while the slow reader is stuck on its first answer
            print(f"fast vehicle: max {max(before):.3f} s a sector before, {max(during):.3f} s during")
            reading.set()
            deadline = time.monotonic() + START_TIMEOUT_S
            while len(answers) < n and time.monotonic() < deadline:
                time.sleep(0.1)
            time.sleep(0.5)
            assert answers == ["detections"] * n, answers.count("errors")
            for sub in subs:
                sub.undeclare()
    finally:
        transport.close(10)
        worker.close(10)


def _timed(client: ZenohClient, stream: str, seq: int) -> float:
    t0 = time.monotonic()
    client.send(sector_msg(stream, seq, SMALL))
    return time.monotonic() - t0
