"""`phim bench server`: the server's own overhead per sector, over each transport, beside the model's time.

Starts `phim serve` as a subprocess on free loopback ports (or uses a running server), then per transport
sends the sectors of one scan in order on one stream, one request in flight, and records per sector:

    end_to_end = client clock: request built and sent -> reply decoded
    model      = the forward the worker timed around `StreamingDetector.step` (reply timings.model_ms)
    overhead   = end_to_end - model: encode, transport, decode, queueing and scheduling, reply

so the overhead of each request is measured against its own forward, whatever the load on the machine.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from clients.base import DetectorClient, sector_message
from clients.connect import ConnectConfig, Transport, make_client
from clients.sectorizer import split_scan
from model.data.readers import read_scan

READY_TIMEOUT_S = 300.0


@dataclass(frozen=True)
class TransportBench:
    transport: str
    sectors: int  # timed requests
    points_per_sector: int  # median
    end_to_end_p50_ms: float
    end_to_end_p90_ms: float
    model_p50_ms: float
    overhead_p50_ms: float
    overhead_p90_ms: float
    overhead_p99_ms: float
    queue_p50_ms: float  # reply timings.queue_ms: submitted to the worker -> forward started
    worker_p50_ms: float  # reply timings.total_ms - model_ms: the worker's part of the overhead

    def to_dict(self) -> dict:
        return asdict(self)


def _pct(values: list[float], q: float) -> float:
    return round(float(np.percentile(np.asarray(values), q)), 3)


def bench_transport(
    client: DetectorClient, sectors: list[np.ndarray], turns: int, warmup_turns: int, stream_id: str
) -> TransportBench:
    """Send `warmup_turns + turns` turns of `sectors` (in order, one in flight); time the last `turns`."""
    e2e, model, queue, total = [], [], [], []
    seq = 0
    for turn in range(warmup_turns + turns):
        for index, points in enumerate(sectors):
            msg = sector_message(stream_id, seq, index, points, reset=seq == 0)
            t0 = time.perf_counter()
            reply = client.send(msg)
            dt = (time.perf_counter() - t0) * 1e3
            seq += 1
            if turn >= warmup_turns:
                e2e.append(dt)
                model.append(reply.timings.model_ms)
                queue.append(reply.timings.queue_ms)
                total.append(reply.timings.total_ms)
    overhead = [a - b for a, b in zip(e2e, model, strict=True)]
    return TransportBench(
        transport=client.transport,
        sectors=len(e2e),
        points_per_sector=int(statistics.median(s.shape[0] for s in sectors)),
        end_to_end_p50_ms=_pct(e2e, 50),
        end_to_end_p90_ms=_pct(e2e, 90),
        model_p50_ms=_pct(model, 50),
        overhead_p50_ms=_pct(overhead, 50),
        overhead_p90_ms=_pct(overhead, 90),
        overhead_p99_ms=_pct(overhead, 99),
        queue_p50_ms=_pct(queue, 50),
        worker_p50_ms=_pct([a - b for a, b in zip(total, model, strict=True)], 50),
    )


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def spawned_server(threads: int, extra: list[str]) -> Iterator[ConnectConfig]:
    """`phim serve` in a subprocess on free loopback ports; yields how to reach it; SIGTERM at the end."""
    http, zport = free_port(), free_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    cmd = [sys.executable, "-m", "server.cli", "serve", "--port", str(http), "--zenoh-listen", endpoint]
    cmd += ["--threads", str(threads), *extra]
    proc = subprocess.Popen(cmd, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    url = f"http://127.0.0.1:{http}"
    try:
        _wait_ready(url, proc)
        yield ConnectConfig(url=url, zenoh_connect=(endpoint,))
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _wait_ready(url: str, proc: subprocess.Popen) -> None:
    import httpx  # the clients' dependency; `phim serve` itself does not need it

    deadline = time.monotonic() + READY_TIMEOUT_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"phim serve exited with code {proc.returncode} before it was ready")
        with contextlib.suppress(httpx.HTTPError):
            if httpx.get(f"{url}/health/ready", timeout=2.0).status_code == 200:
                return
        time.sleep(0.25)
    raise RuntimeError(f"phim serve at {url} not ready after {READY_TIMEOUT_S:.0f} s")


def load_sectors(scan_path: Path, sectors: int = 4) -> list[np.ndarray]:
    """A recorded scan (KITTI .bin, nuScenes .pcd.bin, .npz) -> its sectors (N_k, 4), in sweep order."""
    scan = read_scan(scan_path)
    return [s.points for s in split_scan(scan.points, scan.fields, sectors, scan.spin)]


def run_bench(
    connect: ConnectConfig, transports: list[Transport], sectors: list[np.ndarray], turns: int, warmup: int
) -> list[TransportBench]:
    results = []
    for transport in transports:
        cfg = ConnectConfig(**{**asdict(connect), "transport": transport})
        with make_client(cfg) as client:
            stream = f"bench-{transport.value}-{os.getpid()}"
            results.append(bench_transport(client, sectors, turns, warmup, stream))
            client.end_stream(stream)  # one live stream at a time: no transport waits on another's
    return results


def table(results: list[TransportBench]) -> str:
    head = (
        "| transport | sectors | points | end-to-end p50 | model p50 | overhead p50 | p90 | p99 "
        "| in worker p50 | of it queued p50 |"
    )
    rows = [head, "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        rows.append(
            f"| {r.transport} | {r.sectors} | {r.points_per_sector} | {r.end_to_end_p50_ms:.2f} ms "
            f"| {r.model_p50_ms:.2f} ms | **{r.overhead_p50_ms:.2f} ms** | {r.overhead_p90_ms:.2f} ms "
            f"| {r.overhead_p99_ms:.2f} ms | {r.worker_p50_ms:.2f} ms | {r.queue_p50_ms:.2f} ms |"
        )
    return "\n".join(rows)


def bench_server_cmd(
    url: Annotated[
        str | None, typer.Option(help="a running server (default: start `phim serve` here)")
    ] = None,
    zenoh_connect: Annotated[str, typer.Option(help="its zenoh endpoint, with --url")] = "tcp/127.0.0.1:7447",
    transport: Annotated[list[Transport] | None, typer.Option(help="repeatable; default: both")] = None,
    points: Annotated[
        Path | None, typer.Option(help="a KITTI-style .bin scan (default: KITTI 000000)")
    ] = None,
    turns: Annotated[int, typer.Option(help="timed turns per transport (4 sectors each)")] = 25,
    warmup_turns: Annotated[int, typer.Option(help="untimed turns first")] = 3,
    threads: Annotated[int, typer.Option(help="torch CPU threads of the spawned server")] = 2,
    as_json: Annotated[bool, typer.Option("--json", help="print JSON only")] = False,
) -> None:
    """End-to-end latency per sector beside the model's own time: the server's overhead per transport."""
    from model.cli import KITTI_000000
    from model.runtime import tune_malloc

    tune_malloc()  # the client side too: sector-sized buffers stay on the heap
    scan = points or KITTI_000000
    if not scan.is_file():
        raise typer.BadParameter(f"{scan}: no such file (give --points)")
    sectors = load_sectors(scan)
    chosen = transport or [Transport.HTTP, Transport.ZENOH]
    if url:
        results = run_bench(
            ConnectConfig(url=url, zenoh_connect=(zenoh_connect,)), chosen, sectors, turns, warmup_turns
        )
    else:
        with spawned_server(threads, ["--log-level", "warning"]) as connect:
            results = run_bench(connect, chosen, sectors, turns, warmup_turns)
    if as_json:
        typer.echo(json.dumps({"scan": str(scan), "results": [r.to_dict() for r in results]}))
        return
    typer.echo(f"scan: {scan}; one stream per transport, one request in flight")
    typer.echo(table(results))
