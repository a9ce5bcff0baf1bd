"""The client library against a real server on loopback (uvicorn + zenoh): both clients, sync and async,
get the same detections as each other and as StreamingDetector run directly; server errors and transport
failures come back as their typed exceptions."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import pytest
from client_helpers import Served, kitti_turns, serve_both, silent_http_server, silent_zenoh_worker
from server_helpers import START_TIMEOUT_S, assert_same_boxes, comparable_detector, run_direct

from clients.base import DetectorClient, RequestTimeout, ServerError, TransportError, sector_message
from clients.connect import Transport, make_client
from clients.http_client import HttpClient
from clients.zenoh_client import NotSupported, ZenohClient
from contract import DetectionsReply, ErrorCode
from model.stream import StreamingDetector

SCANS = range(6)  # every KITTI scan in shared/data/kitti_object


@pytest.fixture(scope="module")
def det() -> StreamingDetector:
    return comparable_detector()


@pytest.fixture(scope="module")
def turns() -> list[list[tuple[int, np.ndarray]]]:
    return kitti_turns(SCANS)


@pytest.fixture(scope="module")
def ref(det: StreamingDetector, turns: list[list[tuple[int, np.ndarray]]]) -> list[Any]:
    return run_direct(det, [p for turn in turns for _, p in turn])


@pytest.fixture(scope="module")
def served(det: StreamingDetector) -> Iterator[Served]:
    with serve_both(det) as s:
        yield s


def sectors(turns: list[list[tuple[int, np.ndarray]]]) -> list[tuple[int, np.ndarray]]:
    return [s for turn in turns for s in turn]


def send_all(client: DetectorClient, stream: str, turns: list[Any]) -> list[DetectionsReply]:
    return [client.send_points(stream, seq, k, p) for seq, (k, p) in enumerate(sectors(turns))]


async def send_all_async(client: DetectorClient, stream: str, turns: list[Any]) -> list[DetectionsReply]:
    out = []
    for seq, (k, p) in enumerate(sectors(turns)):
        out.append(await client.send_async(sector_message(stream, seq, k, p)))
    return out


def test_both_clients_sync_and_async_equal_the_model(
    served: Served, turns: list[Any], ref: list[Any]
) -> None:
    with (
        make_client(served.connect(Transport.HTTP)) as http,
        make_client(served.connect(Transport.ZENOH)) as zen,
    ):
        assert isinstance(http, HttpClient) and isinstance(zen, ZenohClient)
        got = {
            "http-sync": send_all(http, "c-http-sync", turns),
            "zenoh-sync": send_all(zen, "c-zenoh-sync", turns),
        }

        async def both_async() -> list[list[DetectionsReply]]:
            try:  # two streams in flight at once, one per transport
                return list(
                    await asyncio.gather(
                        send_all_async(http, "c-http-async", turns),
                        send_all_async(zen, "c-zenoh-async", turns),
                    )
                )
            finally:
                await http.aclose()

        got["http-async"], got["zenoh-async"] = asyncio.run(both_async())
    for name, replies in got.items():
        assert len(replies) == len(ref), name
        for seq, (reply, expected) in enumerate(zip(replies, ref, strict=True)):
            assert reply.seq == seq and reply.stream_id.startswith("c-"), name
            assert reply.context_sectors == min(seq + 1, 4), (name, seq)
            assert_same_boxes(reply.boxes, reply.scores, reply.labels, expected)
            assert len(reply.class_names) == reply.boxes.shape[0]
    assert sum(r.boxes.shape[0] for r in got["http-sync"]) > 0, "the comparison needs some boxes"


def test_many_async_gets_in_flight_at_once(served: Served, turns: list[Any]) -> None:
    """The zenoh async path does not serialize: 8 streams' first sectors are in flight together."""
    k, points = turns[0][0]

    async def burst() -> list[DetectionsReply]:
        async with make_client(served.connect(Transport.ZENOH)) as zen:
            return list(
                await asyncio.gather(
                    *(zen.send_async(sector_message(f"burst-{i}", 0, k, points)) for i in range(8))
                )
            )

    replies = asyncio.run(burst())
    assert sorted(r.stream_id for r in replies) == sorted(f"burst-{i}" for i in range(8))
    for r in replies[1:]:
        np.testing.assert_allclose(r.boxes, replies[0].boxes, atol=1e-4)


@pytest.mark.parametrize("transport", [Transport.HTTP, Transport.ZENOH])
def test_server_errors_are_typed_with_the_servers_code(
    served: Served, turns: list[Any], transport: Transport
) -> None:
    k, points = turns[0][0]
    stream = f"errors-{transport.value}"
    with make_client(served.connect(transport)) as client:
        client.send_points(stream, 5, k, points)
        with pytest.raises(ServerError) as stale:
            client.send_points(stream, 5, k, points)
        assert stale.value.code is ErrorCode.STALE_SEQUENCE and stale.value.field == "seq"
        assert stale.value.seq == 5 and stale.value.stream_id == stream
        with pytest.raises(ServerError) as bad:
            client.send_points(stream, 6, k, points, fields=("x", "y", "z", "reflectance"))
        assert bad.value.code is ErrorCode.INVALID_FIELD and bad.value.field == "fields"
        with pytest.raises(ServerError) as index:
            client.send_points(stream, 7, 99, points)
        assert index.value.code is ErrorCode.INVALID_FIELD and index.value.field == "sector_index"
        if transport is Transport.HTTP:
            assert (stale.value.status, bad.value.status) == (409, 422)
        assert client.send_points(stream, 8, k, points).seq == 8  # the stream goes on


def test_one_http_client_serves_many_threads(served: Served, turns: list[Any], ref: list[Any]) -> None:
    """The sync path is thread-safe (httpx.Client's pool): 4 threads, a stream each, on one client with
    fewer connections than threads; every reply is its own request's and equals the model's."""
    flat = sectors(turns)[:6]
    with HttpClient(served.url, max_connections=2) as http, ThreadPoolExecutor(4) as pool:
        runs = list(pool.map(lambda i: send_all(http, f"mt-{i}", [flat]), range(4)))
    for i, replies in enumerate(runs):
        assert [(r.stream_id, r.seq) for r in replies] == [(f"mt-{i}", seq) for seq in range(len(flat))]
        for reply, expected in zip(replies, ref, strict=False):
            assert_same_boxes(reply.boxes, reply.scores, reply.labels, expected)


def test_http_control_routes(served: Served, turns: list[Any]) -> None:
    k, points = turns[0][0]
    with HttpClient(served.url) as http:
        assert http.ready()
        info = http.model_info()
        assert info["sectors_per_turn"] == 4 and info["point_fields"][:4] == ["x", "y", "z", "intensity"]
        http.send_points("ctl", 0, k, points)
        assert http.stream_info("ctl")["last_seq"] == 0
        assert "ctl" in [s["stream_id"] for s in http.streams()]
        http.end_stream("ctl")
        with pytest.raises(ServerError) as gone:
            http.stream_info("ctl")
        assert gone.value.code is ErrorCode.UNKNOWN_STREAM and gone.value.status == 404
        with pytest.raises(ServerError) as bad_id:
            http.send_points("no/slash", 0, k, points)
        assert bad_id.value.code is ErrorCode.INVALID_FIELD


def test_zenoh_control_goes_over_http_or_resets(served: Served, turns: list[Any]) -> None:
    k, points = turns[0][0]
    with ZenohClient(connect=(served.zenoh_endpoint,), http_url=served.url, timeout_s=START_TIMEOUT_S) as zen:
        assert zen.model_info()["sectors_per_turn"] == 4
        assert zen.workers() == ["test-worker"]
        zen.send_points("zctl", 0, k, points)
        zen.end_stream("zctl")  # over HTTP: the stream is gone, seq 0 is fresh again
        assert zen.send_points("zctl", 0, k, points).context_sectors == 1
    with ZenohClient(connect=(served.zenoh_endpoint,), timeout_s=START_TIMEOUT_S) as zen:
        with pytest.raises(NotSupported):
            zen.model_info()
        zen.send_points("zreset", 3, k, points)
        zen.end_stream("zreset")  # no HTTP: the next sector resets the stream
        assert zen.send_points("zreset", 0, k, points).context_sectors == 1


def test_a_timeout_raises_the_transport_exception(turns: list[Any]) -> None:
    k, points = turns[0][0]
    with silent_http_server() as url, HttpClient(url, timeout_s=0.3) as http, pytest.raises(RequestTimeout):
        http.send_points("t", 0, k, points)
    with silent_zenoh_worker() as endpoint, ZenohClient(connect=(endpoint,), timeout_s=0.3) as zen:
        with pytest.raises(RequestTimeout):
            zen.send_points("t", 0, k, points)

        async def one() -> None:
            await zen.send_async(sector_message("t", 1, k, points))

        with pytest.raises(RequestTimeout):
            asyncio.run(one())


def test_no_server_is_a_transport_error_not_a_timeout(turns: list[Any]) -> None:
    from server_helpers import free_endpoint, free_port

    k, points = turns[0][0]
    url = f"http://127.0.0.1:{free_port()}"
    with HttpClient(url, timeout_s=2) as http, pytest.raises(TransportError) as e:
        http.send_points("t", 0, k, points)
    assert not isinstance(e.value, RequestTimeout)
    with pytest.raises(TransportError):
        ZenohClient(connect=(free_endpoint(),), mode="client")
