"""`phim bench server`: the server's own overhead per sector, over each transport, beside the model's time.

Starts `phim serve` as a subprocess on free loopback ports (or uses a running server), then per transport
sends the sectors of one scan in order on one stream, one request in flight, and records per sector:

    end_to_end = client clock: request built and sent -> reply decoded
    model      = the forward the worker timed around `StreamingDetector.step` (reply timings.model_ms)
    overhead   = end_to_end - model: encode, transport, decode, queueing and scheduling, reply

so the overhead of each request is measured against its own forward, whatever the load on the machine.

The transport floor: after each request the same client stack sends a payload of the sector's size to a
bare responder (`clients.bench.echo`, its own process) that keeps the CPU busy for that request's model
time and answers with as many bytes as the reply had. What that round trip costs beyond the hold is what
the transport itself costs on this machine; overhead minus floor is what this server's code adds.
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
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import IO

import click
import httpx
import numpy as np
import zenoh

from clients.base import DetectorClient, sector_message
from clients.bench.echo import ECHO_KEY, ECHO_PATH, HELD, request_header
from clients.connect import ConnectConfig, Transport, make_client
from clients.options import zenoh_connect_option
from clients.zenoh_session import open_session
from contract import REQUIRED_FIELDS, encode_reply, encode_sector
from lidar.readers import Spin, read_scan
from lidar.samples import KITTI_000000
from lidar.sectorizer import split_scan
from lidar.synthetic import synthetic_turn
from phim.options import EnumValue, json_option
from phim.progress import Progress, note

READY_TIMEOUT_S = 900.0  # a start and warm-up, bounded: one forward took 42 s on a 2-core machine at load 20


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
    floor_p50_ms: float | None = None  # the bare transport's round trip beyond the hold (None: not run)
    own_p50_ms: float | None = None  # p50 of (overhead - floor) over paired requests: this server's code

    def to_dict(self) -> dict:
        return asdict(self)


def _pct(values: list[float], q: float) -> float:
    return round(float(np.percentile(np.asarray(values), q)), 3)


class Floor:
    """Bare round trips over one transport to `clients.bench.echo`: send `body`, get the seconds it held."""

    def __init__(self, transport: Transport, url: str, zenoh_endpoint: str):
        self._http: httpx.Client | None = None  # the same stack as HttpClient's sync path
        self._session: zenoh.Session | None = None
        if transport is Transport.HTTP:
            self._http = httpx.Client(base_url=url, timeout=httpx.Timeout(10.0, connect=5.0))
        else:
            self._session = open_session((zenoh_endpoint,))

    def round_trip(self, body: bytes) -> float:
        if self._http is not None:
            headers = {"Content-Type": "application/octet-stream"}
            r = self._http.post(ECHO_PATH, content=body, headers=headers)
            answer = r.raise_for_status().content
        else:
            assert self._session is not None
            block = zenoh.CongestionControl.BLOCK
            replies = self._session.get(ECHO_KEY, payload=body, congestion_control=block, timeout=10.0)
            answer = b"".join(r.ok.payload.to_bytes() for r in replies if r.ok is not None)
        return HELD.unpack_from(answer)[0]

    def close(self) -> None:
        if self._http is not None:
            self._http.close()
        if self._session is not None:
            self._session.close()


def bench_transport(
    client: DetectorClient,
    sectors: list[np.ndarray],
    turns: int,
    warmup_turns: int,
    stream_id: str,
    floor: Floor | None = None,
) -> TransportBench:
    """Send `warmup_turns + turns` turns of `sectors` (in order, one in flight); time the last `turns`.
    With `floor`, each request is followed by a bare round trip of the same size holding its model time."""
    e2e, model, queue, total, bare = [], [], [], [], []
    seq = 0
    for turn in range(warmup_turns + turns):
        for index, points in enumerate(sectors):
            msg = sector_message(stream_id, seq, index, points, reset=seq == 0)
            t0 = time.perf_counter()
            reply = client.send(msg)
            dt = (time.perf_counter() - t0) * 1e3
            seq += 1
            if floor is not None:
                size = len(encode_sector(msg))
                body = request_header(reply.timings.model_ms, len(encode_reply(reply))) + bytes(size)
                t0 = time.perf_counter()
                held = floor.round_trip(body)
                bare.append((time.perf_counter() - t0 - held) * 1e3)
            if turn >= warmup_turns:
                e2e.append(dt)
                model.append(reply.timings.model_ms)
                queue.append(reply.timings.queue_ms)
                total.append(reply.timings.total_ms)
    overhead = [a - b for a, b in zip(e2e, model, strict=True)]
    bare = bare[len(bare) - len(e2e) :]  # the timed turns' round trips
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
        floor_p50_ms=_pct(bare, 50) if bare else None,
        own_p50_ms=_pct([a - b for a, b in zip(overhead, bare, strict=True)], 50) if bare else None,
    )


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def spawned(
    cmd: list[str], ready_url: str, env: dict[str, str] | None = None, log: IO[str] | None = None
) -> Iterator[subprocess.Popen[bytes]]:
    """`cmd` in a subprocess (extra `env`, output to `log` if given) until `ready_url` answers 200; SIGTERM
    at the end (SIGKILL if it has not exited 60 s later)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
    proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=log)
    try:
        _wait_ready(ready_url, proc)
        yield proc
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@contextlib.contextmanager
def spawned_server(threads: int, extra: list[str]) -> Iterator[ConnectConfig]:
    """`phim serve` in a subprocess on free loopback ports; yields how to reach it."""
    http, endpoint = free_port(), f"tcp/127.0.0.1:{free_port()}"
    cmd = [sys.executable, "-m", "phim", "serve", "--port", str(http), "--zenoh-listen", endpoint]
    url = f"http://127.0.0.1:{http}"
    with spawned([*cmd, "--threads", str(threads), *extra], f"{url}/health/ready"):
        yield ConnectConfig(url=url, zenoh_connect=(endpoint,))


@contextlib.contextmanager
def spawned_echo() -> Iterator[ConnectConfig]:
    """`clients.bench.echo` (the transport floor's responder) on free loopback ports."""
    http, endpoint = free_port(), f"tcp/127.0.0.1:{free_port()}"
    cmd = [sys.executable, "-m", "clients.bench.echo", "--port", str(http), "--zenoh-listen", endpoint]
    url = f"http://127.0.0.1:{http}"
    with spawned(cmd, f"{url}/ready"):
        yield ConnectConfig(url=url, zenoh_connect=(endpoint,))


def _wait_ready(url: str, proc: subprocess.Popen) -> None:
    deadline = time.monotonic() + READY_TIMEOUT_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"{proc.args[2]} exited with code {proc.returncode} before it was ready")
        with contextlib.suppress(httpx.HTTPError):
            if httpx.get(url, timeout=2.0).status_code == 200:
                return
        time.sleep(0.25)
    raise RuntimeError(f"{url} not ready after {READY_TIMEOUT_S:.0f} s")


def load_sectors(scan_path: Path | None, sectors: int = 4) -> list[np.ndarray]:
    """A recorded scan (KITTI .bin, nuScenes .pcd.bin, .npz; None: a synthetic turn) -> its sectors (N_k, 4),
    in sweep order."""
    if scan_path is None:
        points, fields, spin = synthetic_turn(seed=0), REQUIRED_FIELDS, Spin.CCW
    else:
        scan = read_scan(scan_path)
        points, fields, spin = scan.points, scan.fields, scan.spin
    return [s.points for s in split_scan(points, fields, sectors, spin)]


def run_bench(
    connect: ConnectConfig,
    transports: list[Transport],
    sectors: list[np.ndarray],
    turns: int,
    warmup: int,
    echo: ConnectConfig | None = None,
    progress: Callable[[str], None] = lambda what: None,
) -> list[TransportBench]:
    """Per transport, the server's requests (and with `echo`, each one's bare round trip after it)."""
    results = []
    for transport in transports:
        progress(f"{transport.value}: {warmup} warm-up and {turns} timed turns of {len(sectors)} sectors")
        cfg = ConnectConfig(**{**asdict(connect), "transport": transport})
        floor = None if echo is None else Floor(transport, echo.url, echo.zenoh_connect[0])
        try:
            with make_client(cfg) as client:
                stream = f"bench-{transport.value}-{os.getpid()}"
                results.append(bench_transport(client, sectors, turns, warmup, stream, floor))
                client.end_stream(stream)  # one live stream at a time: no transport waits on another's
        finally:
            if floor is not None:
                floor.close()
    return results


def _ms(value: float | None) -> str:
    return "–" if value is None else f"{value:.2f} ms"


def table(results: list[TransportBench]) -> str:
    head = (
        "| transport | sectors | points | end-to-end p50 | model p50 | overhead p50 | p90 | p99 "
        "| in worker p50 | of it queued p50 | bare transport p50 | server's own p50 |"
    )
    rows = [head, "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        rows.append(
            f"| {r.transport} | {r.sectors} | {r.points_per_sector} | {r.end_to_end_p50_ms:.2f} ms "
            f"| {r.model_p50_ms:.2f} ms | **{r.overhead_p50_ms:.2f} ms** | {r.overhead_p90_ms:.2f} ms "
            f"| {r.overhead_p99_ms:.2f} ms | {r.worker_p50_ms:.2f} ms | {r.queue_p50_ms:.2f} ms "
            f"| {_ms(r.floor_p50_ms)} | {_ms(r.own_p50_ms)} |"
        )
    return "\n".join(rows)


@click.command()
@click.option(
    "--url", envvar="PHIM_URL", show_envvar=True, help="A running server [default: start `phim serve` here]."
)
@zenoh_connect_option
@click.option(
    "--transport", type=EnumValue(Transport), multiple=True, help="Repeatable [default: http and zenoh]."
)
@click.option(
    "--points",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="A scan file [default: KITTI 000000 if present, else a synthetic turn].",
)
@click.option(
    "--turns", type=click.IntRange(1), default=25, show_default=True, help="Timed turns per transport."
)
@click.option(
    "--warmup-turns", type=click.IntRange(0), default=3, show_default=True, help="Untimed turns first."
)
@click.option("--threads", type=click.IntRange(1), default=2, show_default=True, help="The spawned server's.")
@click.option(
    "--floor/--no-floor",
    default=True,
    show_default=True,
    help="After each request, a bare round trip of its size (the transport floor).",
)
@json_option
def bench_server_cmd(
    url: str | None,
    zenoh_connect: str,
    transport: tuple[Transport, ...],
    points: Path | None,
    turns: int,
    warmup_turns: int,
    threads: int,
    floor: bool,
    as_json: bool,
) -> None:
    """The server's own overhead per sector: end-to-end latency beside the model's time, per transport."""
    progress = Progress("bench server")
    scan = points or (KITTI_000000 if KITTI_000000.is_file() else None)
    if scan is None:
        note(
            "bench server",
            f"the real samples' KITTI scan is not at {KITTI_000000} (PHIM_SAMPLES_DIR; README, Quick start): "
            "sending synthetic_turn(seed=0) instead (--points FILE: a scan of your own)",
        )
    sectors = load_sectors(scan)
    chosen = list(transport) or [Transport.HTTP, Transport.ZENOH]
    with contextlib.ExitStack() as stack:
        if floor:
            progress("starting the bare responder (the transport floor)")
        echo = stack.enter_context(spawned_echo()) if floor else None
        if url:
            connect = ConnectConfig(url=url, zenoh_connect=(zenoh_connect,))
        else:
            progress("starting `phim serve` and waiting for its warm-up (/health/ready)")
            connect = stack.enter_context(spawned_server(threads, ["--log-level", "warning"]))
        results = run_bench(connect, chosen, sectors, turns, warmup_turns, echo, progress)
    source = str(scan) if scan else "synthetic_turn(seed=0)"
    if as_json:
        click.echo(json.dumps({"scan": source, "results": [r.to_dict() for r in results]}))
        return
    click.echo(f"scan: {source}; one stream per transport, one request in flight")
    click.echo(table(results))
