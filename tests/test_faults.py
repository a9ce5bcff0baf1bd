"""Faults with real parts: thousands of idle streams (bounded, evicted, the limit's clear error) and a worker
killed with SIGKILL under load (every client call ends with an error within its timeout, none hangs)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from conftest import rss_bytes
from server_helpers import default_detector, free_port, sector_msg

from clients.base import ClientError
from clients.connect import ConnectConfig, Transport, make_client
from contract import ErrorCode, ServiceError
from server.worker import Worker, WorkerConfig

REPO = Path(__file__).resolve().parents[1]
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
            deadline_ms=120_000,
        ),
    )
    w.start()
    assert w.wait_ready(60), w.status
    try:
        before = rss_bytes()
        futures = [w.submit(sector_msg(f"idle-{i}", 0, SMALL)) for i in range(n)]
        assert all(f.result(120).context_sectors == 1 for f in futures)
        grown = (rss_bytes() - before) / 2**20  # MB
        assert len(w.streams()) == n and grown < 500, grown  # ~n small states, not a leak per stream
        with pytest.raises(ServiceError) as full:
            w.submit(sector_msg("one-more", 0, SMALL)).result(10)
        assert full.value.code is ErrorCode.OVERLOADED and f"max_streams={n}" in full.value.message
        w.table.idle_timeout_s = 1.0  # now let them idle out (filled under a long timeout, however slow)
        deadline = time.monotonic() + 60
        while w.streams() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert w.streams() == [] and w.metrics.evictions._value.get() == n
        assert w.submit(sector_msg("one-more", 0, SMALL)).result(30).context_sectors == 1  # room again
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
        deadline = time.monotonic() + 120
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
            d.join(4 * (timeout_s + 1))
            assert not d.is_alive(), "a client call hung after the worker died"
        for transport, seconds in after_kill.items():
            assert len(seconds) == 3 and max(seconds) <= timeout_s + 1.0, (transport, seconds)
    finally:
        if server.poll() is None:
            server.kill()
        server.wait(30)
        log.close()
