"""Shared pieces of the client tests: a real server (uvicorn thread + zenoh transport on free loopback
ports), KITTI scans cut by the client sectorizer, and endpoints that accept but never answer."""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from conftest import KITTI_VELODYNE, require_samples
from server_helpers import START_TIMEOUT_S, RunningServer, free_endpoint, serve

from clients.connect import ConnectConfig, Transport
from clients.loadtest.config import LoadTestConfig, SourceConfig
from lidar.readers import read_scan
from lidar.sectorizer import split_scan
from model.stream import StreamingDetector
from server.zenoh_transport import ZenohConfig, open_session

EVERY = 8  # every 8th point of a KITTI scan: ~15k points a turn, fast CPU forwards
# the load tests' sectors: synthetic turns (no samples needed), every 8th point: 16k points a turn
LOADTEST_SOURCE = SourceConfig(folder=None, synthetic_turns=3, every=EVERY)


@dataclass(frozen=True)
class Served:
    server: RunningServer
    zenoh_endpoint: str

    @property
    def url(self) -> str:
        return self.server.url

    def connect(self, transport: Transport, timeout_s: float = START_TIMEOUT_S) -> ConnectConfig:
        return ConnectConfig(
            transport=transport, url=self.url, zenoh_connect=(self.zenoh_endpoint,), timeout_s=timeout_s
        )


def loadtest_config(served: Served, transport: Transport, **kw: Any) -> LoadTestConfig:
    """A short load test of `served` at 1 turn/s per vehicle (the tests' defaults; `kw` overrides them)."""
    base: dict[str, Any] = dict(
        connect=served.connect(transport),
        source=LOADTEST_SOURCE,
        duration_s=1.0,
        turns_per_s=1.0,
        drain_timeout_s=START_TIMEOUT_S,  # ends once every answer is in: generous for a busy machine
    )
    return LoadTestConfig(**{**base, **kw})


@contextlib.contextmanager
def serve_both(det: StreamingDetector, **overrides: object) -> Iterator[Served]:
    """A real server on loopback: HTTP (uvicorn thread) and zenoh (a peer listening on a free port)."""
    endpoint = free_endpoint()
    with serve(det, zenoh_enabled=True, zenoh_listen=(endpoint,), **overrides) as running:
        yield Served(running, endpoint)


def kitti_turns(indices: range | list[int], every: int = EVERY) -> list[list[tuple[int, np.ndarray]]]:
    """KITTI scans -> per scan, (sector_index, (N, 4) float32 points) in sweep order (client sectorizer)."""
    turns = []
    for i in indices:
        scan = read_scan(require_samples(KITTI_VELODYNE / f"{i:06d}.bin"))
        turns.append([(s.index, s.points[::every].copy()) for s in split_scan(scan.points, scan.fields, 4)])
    return turns


@contextlib.contextmanager
def silent_http_server() -> Iterator[str]:
    """A TCP server that accepts connections and never answers: every request to it times out."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen(16)
    sock.settimeout(0.1)  # the accept loop checks `stop` this often
    conns: list[socket.socket] = []
    stop = threading.Event()

    def accept() -> None:
        while not stop.is_set():
            try:
                conn, _ = sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            conns.append(conn)

    t = threading.Thread(target=accept, daemon=True)
    t.start()
    try:
        yield f"http://127.0.0.1:{sock.getsockname()[1]}"
    finally:
        stop.set()
        t.join(5)
        sock.close()
        for c in conns:
            c.close()


@contextlib.contextmanager
def silent_zenoh_worker(prefix: str = "phim/v1") -> Iterator[str]:
    """A zenoh peer whose sector queryable takes queries and never answers them: gets time out."""
    endpoint = free_endpoint()
    with open_session(ZenohConfig(mode="peer", listen=(endpoint,))) as session:
        queryable = session.declare_queryable(f"{prefix}/streams/*/sector", zenoh.handlers.FifoChannel(64))
        try:
            yield endpoint
        finally:
            queryable.undeclare()


def png_is_a_picture(path: Path) -> None:
    """The file is a PNG with real content (not blank)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.image

    assert path.is_file() and path.stat().st_size > 10_000, path
    img = matplotlib.image.imread(path)
    assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 200
    assert float(img[..., :3].std()) > 0.05, f"{path} looks blank"
