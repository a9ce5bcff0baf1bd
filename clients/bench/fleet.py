"""A fleet on one machine: a zenoh router (`phim router`) and N workers (`phim serve`) joined to it as
zenoh clients, each with its own worker ID and HTTP port, the shared keys off (clients use --workers auto).

`phim bench fleet` measures the throughput of 1..N workers in one run: for each N it starts a fresh fleet
and runs a closed-loop load test through the router (`--workers auto`), then prints a table. The tests use
the same helpers (tests/test_fleet.py).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import click

from clients.bench.server import free_port, spawned
from clients.connect import ConnectConfig, Transport
from phim.options import json_option
from phim.progress import Progress

ROUTER_START_S = 60.0


@dataclass
class FleetWorker:
    worker_id: str
    url: str
    process: subprocess.Popen[bytes]


@dataclass
class Fleet:
    router: str  # the router's zenoh endpoint
    workers: dict[str, FleetWorker] = field(default_factory=dict)
    stack: contextlib.ExitStack = field(default_factory=contextlib.ExitStack)
    log: IO[str] | None = None
    extra_env: dict[str, str] = field(default_factory=dict)

    def connect(self, **overrides: Any) -> ConnectConfig:
        """How a client reaches the fleet: zenoh through the router, each stream to its owner."""
        first = next(iter(self.workers.values()))
        base = ConnectConfig(
            transport=Transport.ZENOH, zenoh_connect=(self.router,), url=first.url, auto_workers=True
        )
        return dataclasses.replace(base, **overrides)

    def add(self, worker_id: str) -> FleetWorker:
        """Start a worker and join it to the router; returns once it is ready (its token is declared)."""
        port = free_port()
        env = {**worker_env(worker_id, self.router, port), **self.extra_env}
        url = f"http://127.0.0.1:{port}"
        cmd = [sys.executable, "-m", "phim", "serve"]
        proc = self.stack.enter_context(spawned(cmd, f"{url}/health/ready", env=env, log=self.log))
        self.workers[worker_id] = FleetWorker(worker_id, url, proc)
        return self.workers[worker_id]


def worker_env(worker_id: str, router: str, port: int) -> dict[str, str]:
    """A fleet worker's settings: zenoh client of the router, its own keys only, one torch thread."""
    return {
        "PHIM_WORKER_ID": worker_id,
        "PHIM_PORT": str(port),
        "PHIM_ZENOH_MODE": "client",
        "PHIM_ZENOH_CONNECT": router,
        "PHIM_ZENOH_LISTEN": "",
        "PHIM_ZENOH_SHARED_KEYS": "0",
        "PHIM_THREADS": "1",
        "PHIM_WARMUP_SECTORS": "1",
        "PHIM_LOG_LEVEL": "warning",
    }


def start_router(endpoint: str, log: IO[str] | None = None) -> subprocess.Popen[bytes]:
    """`phim router --listen endpoint` (a TCP endpoint), once it accepts connections."""
    cmd = [sys.executable, "-m", "phim", "router", "--listen", endpoint]
    router = subprocess.Popen(cmd, stdout=log, stderr=log)
    host, port = endpoint.removeprefix("tcp/").rsplit(":", 1)
    deadline = time.monotonic() + ROUTER_START_S
    while router.poll() is None and time.monotonic() < deadline:
        with contextlib.suppress(OSError), socket.create_connection((host, int(port)), timeout=1):
            return router
        time.sleep(0.1)
    router.kill()
    raise RuntimeError(f"the router on {endpoint} did not start")


@contextlib.contextmanager
def spawned_router(endpoint: str, log: IO[str] | None = None) -> Iterator[subprocess.Popen[bytes]]:
    """`start_router`, killed at the end."""
    router = start_router(endpoint, log)
    try:
        yield router
    finally:
        router.kill()
        router.wait(30)


@contextlib.contextmanager
def spawned_fleet(
    worker_ids: list[str], log: IO[str] | None = None, extra_env: dict[str, str] | None = None
) -> Iterator[Fleet]:
    """A router on a free loopback port and one worker per ID, all ready."""
    fleet = Fleet(f"tcp/127.0.0.1:{free_port()}", log=log, extra_env=extra_env or {})
    with fleet.stack:
        fleet.stack.enter_context(spawned_router(fleet.router, log))
        for worker_id in worker_ids:  # one after the other: two warm-ups at once would share the cores
            fleet.add(worker_id)
        yield fleet


def fleet_throughput(workers: int, vehicles: int, duration_s: float, every: int) -> dict[str, Any]:
    """A fresh fleet of `workers`, a closed-loop load test of `vehicles` through it: the report's headline."""
    from clients.loadtest.config import LoadTestConfig, Mode, OutputConfig, SourceConfig
    from clients.loadtest.report import to_json
    from clients.loadtest.run import run_loadtest

    with (
        open(os.devnull, "w") as quiet,
        spawned_fleet([f"worker-{i}" for i in range(workers)], quiet) as fleet,
    ):
        cfg = LoadTestConfig(
            connect=fleet.connect(),
            source=SourceConfig(folder=None, every=every),
            mode=Mode.CLOSED,
            vehicles=(vehicles,),
            duration_s=duration_s,
            warmup_s=2.0,
        )
        report = to_json(run_loadtest(cfg, OutputConfig(progress=False)))
    keys = ("achieved_sectors_per_s", "p50_ms", "p99_ms", "sent", "errors", "lost", "by_worker", "retried")
    return {"workers": workers, "vehicles": vehicles, **{k: report[k] for k in keys}}


def table(rows: list[dict[str, Any]]) -> str:
    base = rows[0]["achieved_sectors_per_s"]
    lines = [
        "| workers | vehicles | sectors/s | x 1 worker | p50 ms | p99 ms | errors | lost | by worker |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        spread = ", ".join(f"{n}" for n in r["by_worker"].values())
        lines.append(
            f"| {r['workers']} | {r['vehicles']} | {r['achieved_sectors_per_s']:.1f} | "
            f"{r['achieved_sectors_per_s'] / base:.2f} | {r['p50_ms']:.1f} | {r['p99_ms']:.1f} | "
            f"{r['errors']} | {r['lost']} | {spread} |"
        )
    return "\n".join(lines)


@click.command()
@click.option(
    "--workers", default="1,2,3", show_default=True, help="Fleet sizes to measure, comma-separated."
)
@click.option(
    "--vehicles", type=click.IntRange(1), default=12, show_default=True, help="Closed-loop vehicles."
)
@click.option("--duration", type=click.FloatRange(1), default=10.0, show_default=True, help="Seconds each.")
@click.option("--every", type=click.IntRange(1), default=4, show_default=True, help="Keep every n-th point.")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), help="Also write the rows as JSON.")
@json_option
def bench_fleet_cmd(
    workers: str, vehicles: int, duration: float, every: int, out: Path | None, as_json: bool
) -> None:
    """Throughput of fleets of 1..N CPU workers behind one zenoh router, measured in one run."""
    sizes = [int(n) for n in workers.split(",") if n.strip()]
    progress = Progress("bench fleet")
    rows = []
    for n in sizes:
        progress(f"{n} workers: starting the router and the workers, then {duration:g} s of synthetic load")
        rows.append(fleet_throughput(n, vehicles, duration, every))
    if out is not None:
        out.write_text(json.dumps(rows, indent=2) + "\n")
    click.echo(json.dumps(rows) if as_json else table(rows))
