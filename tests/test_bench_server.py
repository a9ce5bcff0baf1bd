"""`phim bench server` as a command, and its transport floor's bare responder (real processes, real
uvicorn and zenoh; the numbers are benchmarks, not checked here beyond being consistent)."""

from __future__ import annotations

import json
import time

import pytest
from click.testing import CliRunner

from clients.bench.echo import request_header
from clients.bench.server import Floor, spawned_echo
from clients.connect import Transport
from phim.cli import main as app


@pytest.mark.parametrize("transport", [Transport.HTTP, Transport.ZENOH])
def test_the_echo_holds_for_the_time_asked_and_answers_over_each_transport(transport: Transport) -> None:
    with spawned_echo() as echo:
        floor = Floor(transport, echo.url, echo.zenoh_connect[0])
        try:
            for hold_ms in (0.0, 20.0):
                t0 = time.perf_counter()
                held = floor.round_trip(request_header(hold_ms, 500) + bytes(100_000))
                elapsed = time.perf_counter() - t0
                assert hold_ms / 1e3 <= held < elapsed
        finally:
            floor.close()


def test_bench_server_reports_overhead_and_floor_per_transport() -> None:
    args = ["bench", "server", "--turns", "1", "--warmup-turns", "1", "--threads", "1", "--json"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    out = json.loads(result.output.strip().splitlines()[-1])
    rows = {r["transport"]: r for r in out["results"]}
    assert set(rows) == {"http", "zenoh"}
    for r in rows.values():
        assert r["sectors"] == 4 and r["points_per_sector"] > 20_000  # one turn of the KITTI scan
        assert r["end_to_end_p50_ms"] > r["overhead_p50_ms"] > 0 and r["model_p50_ms"] > 0
        assert r["floor_p50_ms"] > 0 and r["own_p50_ms"] is not None
