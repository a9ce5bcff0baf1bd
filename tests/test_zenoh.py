"""The zenoh transport over real zenoh sessions on loopback: a server-side ZenohTransport (peer, listening on
a free tcp port, multicast scouting off) around the real Worker with the default model, and client sessions
that connect to it. Every get has a timeout (a hang fails the test instead of blocking it)."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import httpx
import msgpack
import numpy as np
import pytest
import zenoh
from server_helpers import (
    START_TIMEOUT_S,
    StepGate,
    assert_same_boxes,
    default_detector,
    free_endpoint,
    sector_msg,
    serve,
)

from contract import DetectionsReply, ErrorCode, ErrorReply, KeySpace, Limits, decode_response, encode_sector
from model.stream import StreamingDetector
from server.worker import Worker, WorkerConfig
from server.zenoh_transport import MSGPACK_ENCODING, ZenohConfig, ZenohTransport, open_session

GET_TIMEOUT_S = START_TIMEOUT_S  # a guard against hangs (generous: a busy machine); replies come once done
BLOCK = zenoh.CongestionControl.BLOCK
KEYS = KeySpace("phim/v1")
LIMITS = Limits(max_body_bytes=2 * 2**20, max_points=50_000, max_string_len=64)


def server_config(endpoint: str) -> ZenohConfig:
    return ZenohConfig(mode="peer", listen=(endpoint,), multicast_scouting=False)


def client_session(endpoint: str, mode: str = "client") -> zenoh.Session:
    return open_session(ZenohConfig(mode=mode, listen=(), connect=(endpoint,), multicast_scouting=False))


def start_worker(det: StreamingDetector, **kw: Any) -> Worker:
    worker = Worker(
        lambda: (det, "test detector"),
        WorkerConfig(worker_id="zenoh-test", warmup_sectors=1, deadline_ms=60_000, **kw),
    )
    worker.start()
    assert worker.wait_ready(START_TIMEOUT_S), worker.status
    return worker


@contextlib.contextmanager
def transport_for(worker: Worker) -> Iterator[tuple[ZenohTransport, zenoh.Session]]:
    """A started transport around `worker` on a free port, and a client session connected to it."""
    endpoint = free_endpoint()
    transport = ZenohTransport(worker.submit, server_config(endpoint), worker.worker_id, LIMITS)
    transport.start()
    try:
        with client_session(endpoint) as client:
            yield transport, client
    finally:
        transport.close(drain_timeout_s=10.0)


def one_answer(replies: zenoh.handlers.Handler[zenoh.Reply], key: str) -> DetectionsReply | ErrorReply:
    """The single reply of a get, decoded; an ok reply comes on the query's key as msgpack."""
    got = list(replies)
    assert len(got) == 1, f"{len(got)} replies on {key}"
    if got[0].ok is not None:
        sample = got[0].ok
        assert str(sample.key_expr) == key
        assert sample.encoding == MSGPACK_ENCODING
        out = decode_response(sample.payload.to_bytes())
        assert isinstance(out, DetectionsReply)
        return out
    assert got[0].err is not None and got[0].err.encoding == MSGPACK_ENCODING
    out = decode_response(got[0].err.payload.to_bytes())
    assert isinstance(out, ErrorReply)
    return out


def send(client: zenoh.Session, key: str, body: bytes) -> zenoh.handlers.Handler[zenoh.Reply]:
    """Start a get (does not wait for the reply)."""
    return client.get(
        key, payload=body, encoding=MSGPACK_ENCODING, congestion_control=BLOCK, timeout=GET_TIMEOUT_S
    )


def send_sector(client: zenoh.Session, stream: str, seq: int, points: np.ndarray) -> Any:
    return send(client, KEYS.sector(stream), encode_sector(sector_msg(stream, seq, points)))


def ask(client: zenoh.Session, stream: str, body: bytes) -> DetectionsReply | ErrorReply:
    key = KEYS.sector(stream)
    return one_answer(send(client, key, body), key)


def ask_sector(client: zenoh.Session, stream: str, seq: int, points: np.ndarray, **kw: Any) -> Any:
    return ask(client, stream, encode_sector(sector_msg(stream, seq, points, **kw)))


def receive(sub: zenoh.Subscriber, n: int, timeout_s: float = GET_TIMEOUT_S) -> list[zenoh.Sample]:
    """n samples from a channel subscriber, polling until `timeout_s`."""
    out: list[zenoh.Sample] = []
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        sample = sub.try_recv()
        if sample is None:
            time.sleep(0.005)
        else:
            out.append(sample)
    assert len(out) == n, f"{len(out)} of {n} samples on {sub.key_expr}"
    return out


def is_error(out: Any, code: ErrorCode, field: str | None = None, stream: str | None = None) -> None:
    assert isinstance(out, ErrorReply), out
    assert (out.code, out.field) == (code, field), out
    if stream is not None:
        assert out.stream_id == stream, out


# ------------------------------------------------------------------------------------------------ fixtures


@pytest.fixture(scope="module")
def det() -> StreamingDetector:
    return default_detector()


@pytest.fixture(scope="module")
def worker(det: StreamingDetector) -> Iterator[Worker]:
    w = start_worker(det)
    yield w
    w.close(10)


@dataclass
class Served:
    transport: ZenohTransport
    client: zenoh.Session


@pytest.fixture(scope="module")
def served(worker: Worker) -> Iterator[Served]:
    with transport_for(worker) as (transport, client):
        yield Served(transport, client)


# ------------------------------------------------------------------------------------------ request/reply


def test_get_kitti_sectors_equal_direct(served: Served, scan_a: list[np.ndarray], ref_a: list[Any]) -> None:
    for seq, (points, ref) in enumerate(zip(scan_a, ref_a, strict=True)):
        out = ask_sector(served.client, "car-1", seq, points)
        assert isinstance(out, DetectionsReply), out
        assert (out.stream_id, out.seq, out.gap, out.context_sectors) == ("car-1", seq, 0, seq + 1)
        assert_same_boxes(out.boxes, out.scores, out.labels, ref)
        assert len(out.class_names) == len(out.boxes) > 0
        assert out.timings.total_ms >= out.timings.model_ms > 0


def test_bad_payloads_name_the_field_and_the_stream_goes_on(
    served: Served, scan_a: list[np.ndarray], ref_a: list[Any]
) -> None:
    c, stream = served.client, "car-2"
    assert isinstance(ask_sector(c, stream, 0, scan_a[0]), DetectionsReply)
    is_error(ask(c, stream, b"\xc1 not msgpack"), ErrorCode.BAD_REQUEST, "body", stream)
    is_error(ask(c, stream, b""), ErrorCode.BAD_REQUEST, "body", stream)
    wire = msgpack.unpackb(encode_sector(sector_msg(stream, 1, scan_a[1])))
    del wire["seq"]
    is_error(ask(c, stream, msgpack.packb(wire)), ErrorCode.INVALID_FIELD, "seq", stream)
    wire["seq"], wire["points"]["dtype"] = 1, "<f8"
    is_error(ask(c, stream, msgpack.packb(wire)), ErrorCode.INVALID_FIELD, "points.dtype", stream)
    nan = scan_a[1].copy()
    nan[0, 0] = np.nan
    is_error(ask_sector(c, stream, 1, nan), ErrorCode.INVALID_FIELD, "points", stream)
    stale = ask_sector(c, stream, 0, scan_a[0])
    is_error(stale, ErrorCode.STALE_SEQUENCE, "seq", stream)
    assert stale.seq == 0
    out = ask_sector(c, stream, 1, scan_a[1])  # the stream's state is untouched by the failures
    assert isinstance(out, DetectionsReply) and out.context_sectors == 2 and out.gap == 0
    assert_same_boxes(out.boxes, out.scores, out.labels, ref_a[1])


def test_key_and_body_stream_ids_must_agree(served: Served, scan_a: list[np.ndarray]) -> None:
    body = encode_sector(sector_msg("someone-else", 0, scan_a[0]))
    out = ask(served.client, "car-3", body)
    is_error(out, ErrorCode.INVALID_FIELD, "stream_id", "car-3")
    assert "someone-else" in out.message and "car-3" in out.message
    wildcard = KEYS.sector_queryable  # a get on phim/v1/streams/*/sector names no stream
    is_error(one_answer(send(served.client, wildcard, body), wildcard), ErrorCode.INVALID_FIELD, "stream_id")
    long_id = "x" * (LIMITS.max_string_len + 1)
    is_error(ask(served.client, long_id, body), ErrorCode.TOO_LARGE, "stream_id")


def test_queries_are_finalized_at_once(served: Served) -> None:
    """A get ends when the server drops the query after its one reply, not when the get times out."""
    t0 = time.monotonic()
    replies = list(served.client.get(KEYS.sector("car-4"), payload=b"garbage", timeout=GET_TIMEOUT_S))
    assert len(replies) == 1 and replies[0].err is not None
    assert time.monotonic() - t0 < GET_TIMEOUT_S / 3  # wide: no forward runs, only the drop ends it early


def test_concurrent_gets_from_many_streams_each_get_one_answer(
    served: Served, scan_a: list[np.ndarray], scan_b: list[np.ndarray], ref_a: list[Any], ref_b: list[Any]
) -> None:
    streams = {"mix-a0": (scan_a, ref_a), "mix-b0": (scan_b, ref_b), "mix-a1": (scan_a, ref_a)}
    pending = []
    for seq in range(2):  # all gets in flight at once, streams interleaved
        for stream, (scan, _) in streams.items():
            pending.append((stream, seq, send_sector(served.client, stream, seq, scan[seq])))
        pending.append(("mix-bad", seq, send(served.client, KEYS.sector("mix-bad"), b"garbage")))
    for stream, seq, replies in pending:
        out = one_answer(replies, KEYS.sector(stream))
        if stream == "mix-bad":
            is_error(out, ErrorCode.BAD_REQUEST, "body", stream)
            continue
        assert isinstance(out, DetectionsReply) and (out.stream_id, out.seq) == (stream, seq), out
        assert_same_boxes(out.boxes, out.scores, out.labels, streams[stream][1][seq])  # no state leaks


def test_overload_answers_every_get_once_and_recovers(
    det: StreamingDetector, scan_a: list[np.ndarray], monkeypatch: pytest.MonkeyPatch
) -> None:
    worker = start_worker(det, queue_size=2, max_batch=1)
    try:
        with transport_for(worker) as (_, client):
            gate = StepGate.install(det, monkeypatch)  # hold the forward: the queue fills up
            streams = [f"load-{i}" for i in range(8)]
            pending = [send_sector(client, s, 0, scan_a[0]) for s in streams]
            threading.Timer(0.5, gate.release).start()
            outs = [one_answer(r, KEYS.sector(s)) for r, s in zip(pending, streams, strict=True)]
            codes = [o.code if isinstance(o, ErrorReply) else "ok" for o in outs]
            assert set(codes) == {"ok", ErrorCode.OVERLOADED} and codes.count("ok") <= 3, codes
            assert all(o.retry_after_s for o in outs if isinstance(o, ErrorReply))
            assert isinstance(ask_sector(client, "load-after", 0, scan_a[0]), DetectionsReply)
    finally:
        worker.close(10)


# ------------------------------------------------------------------------------------------------ pub/sub


def test_pubsub_publishes_detections_and_errors(
    served: Served, scan_a: list[np.ndarray], ref_a: list[Any]
) -> None:
    c, stream = served.client, "bus-7"
    with (
        c.declare_subscriber(KEYS.detections(stream), zenoh.handlers.FifoChannel(16)) as dets,
        c.declare_subscriber(KEYS.errors(stream), zenoh.handlers.FifoChannel(16)) as errs,
        c.declare_publisher(KEYS.sectors(stream), encoding=MSGPACK_ENCODING, congestion_control=BLOCK) as pub,
    ):
        deadline = time.monotonic() + 5
        while not pub.matching_status and time.monotonic() < deadline:
            time.sleep(0.01)
        assert pub.matching_status, "the server's subscriber is not visible"
        pub.put(encode_sector(sector_msg(stream, 0, scan_a[0])))
        pub.put(b"garbage")
        pub.put(encode_sector(sector_msg(stream, 0, scan_a[0])))  # a duplicate: stale
        pub.put(encode_sector(sector_msg(stream, 1, scan_a[1])))
        got = [decode_response(s.payload.to_bytes()) for s in receive(dets, 2)]
        errors = [decode_response(s.payload.to_bytes()) for s in receive(errs, 2)]
    for seq, out in enumerate(got):
        assert isinstance(out, DetectionsReply) and (out.stream_id, out.seq) == (stream, seq), out
        assert_same_boxes(out.boxes, out.scores, out.labels, ref_a[seq])
    is_error(errors[0], ErrorCode.BAD_REQUEST, "body", stream)
    is_error(errors[1], ErrorCode.STALE_SEQUENCE, "seq", stream)
    assert errors[1].seq == 0


# ---------------------------------------------------------------------------------- liveliness and close


def busy(worker: Worker) -> int:
    """Sectors the worker holds: queued plus running."""
    return worker.queue_depth + sum(e.running for e in list(worker.table.entries.values()))


def wait_until(condition: Callable[[], bool], timeout_s: float = GET_TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.01)


def expect_live_workers(client: zenoh.Session, *worker_ids: str) -> None:
    """The workers' liveliness tokens (`phim/v1/workers/{worker_id}/{session}`) are those of `worker_ids`,
    asked again until they are or GET_TIMEOUT_S has passed: the app announces its worker on a thread of its
    own once warmed up, and a withdrawn token takes a moment to leave, so one query may come too early."""
    expected = [f"phim/v1/workers/{w}" for w in worker_ids]
    deadline = time.monotonic() + GET_TIMEOUT_S
    while True:
        replies = client.liveliness().get("phim/v1/workers/*/*", timeout=2.0)
        keys = [str(r.ok.key_expr).rsplit("/", 1)[0] for r in replies if r.ok is not None]
        if keys == expected or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    assert keys == expected


def test_liveliness_token_visible_until_close(worker: Worker) -> None:
    endpoint = free_endpoint()
    transport = ZenohTransport(worker.submit, server_config(endpoint), "w-live", LIMITS)
    transport.start()
    with client_session(endpoint, mode="peer") as client:
        try:
            expect_live_workers(client, "w-live")
        finally:
            transport.close()
        transport.close()  # idempotent
        expect_live_workers(client)


@pytest.mark.parametrize("drain_timeout_s", [GET_TIMEOUT_S, 0.2])
def test_close_answers_every_sector_in_flight(
    worker: Worker,
    det: StreamingDetector,
    scan_a: list[np.ndarray],
    monkeypatch: pytest.MonkeyPatch,
    drain_timeout_s: float,
) -> None:
    """Sectors settled within the drain timeout get their detections; the rest get NOT_READY; none is lost."""
    with transport_for(worker) as (transport, client):
        gate = StepGate.install(det, monkeypatch)
        streams = [f"close-{drain_timeout_s}-{i}" for i in range(2)]
        pending = [send_sector(client, s, 0, scan_a[0]) for s in streams]
        wait_until(lambda: busy(worker) == len(streams))  # both submitted, one forward held
        if drain_timeout_s > 1:
            threading.Timer(0.2, gate.release).start()
        transport.close(drain_timeout_s)
        outs = [one_answer(r, KEYS.sector(s)) for r, s in zip(pending, streams, strict=True)]
    gate.release()
    if drain_timeout_s > 1:
        assert all(isinstance(o, DetectionsReply) for o in outs), outs
    else:
        for o, s in zip(outs, streams, strict=True):
            is_error(o, ErrorCode.NOT_READY, None, s)
    wait_until(lambda: busy(worker) == 0)  # let the held forward finish before the next test


def test_worker_and_client_meet_through_a_router(
    worker: Worker, scan_b: list[np.ndarray], ref_b: list[Any]
) -> None:
    """The deployment shape: a zenoh router; the worker and the client are both clients of it."""
    endpoint = free_endpoint()
    with open_session(ZenohConfig(mode="router", listen=(endpoint,))):
        cfg = ZenohConfig(mode="client", listen=(), connect=(endpoint,))
        transport = ZenohTransport(worker.submit, cfg, "w-routed", LIMITS)
        transport.start()
        try:
            with client_session(endpoint) as client:
                expect_live_workers(client, "w-routed")
                out = ask_sector(client, "routed-1", 0, scan_b[0])
                assert isinstance(out, DetectionsReply), out
                assert_same_boxes(out.boxes, out.scores, out.labels, ref_b[0])
        finally:
            transport.close()


# ------------------------------------------------------------------------------------------ the whole app


def test_app_serves_zenoh_like_http(det: StreamingDetector, scan_a: list[np.ndarray]) -> None:
    """`phim serve`'s app with zenoh on: a stream over zenoh gets the same boxes as one over HTTP."""
    endpoint = free_endpoint()
    with serve(det, zenoh_listen=(endpoint,), zenoh_enabled=True) as server, client_session(endpoint) as c:
        expect_live_workers(c, "test-worker")
        for seq in range(2):
            body = encode_sector(sector_msg("via-http", seq, scan_a[seq]))
            r = httpx.post(
                f"{server.url}/v1/streams/via-http/sectors",
                content=body,
                headers={"Content-Type": "application/msgpack"},
                timeout=GET_TIMEOUT_S,
            )
            assert r.status_code == 200, r.content[:300]
            over_http = decode_response(r.content)
            over_zenoh = ask_sector(c, "via-zenoh", seq, scan_a[seq])
            assert isinstance(over_http, DetectionsReply) and isinstance(over_zenoh, DetectionsReply)
            assert over_zenoh.context_sectors == over_http.context_sectors == seq + 1
            np.testing.assert_array_equal(over_zenoh.boxes, over_http.boxes)
            np.testing.assert_array_equal(over_zenoh.scores, over_http.scores)
            np.testing.assert_array_equal(over_zenoh.labels, over_http.labels)
        # a sector rejected before it reaches the worker is counted in the app's metrics too
        is_error(ask(c, "via-zenoh", b"\xc1garbage"), ErrorCode.BAD_REQUEST, "body")
        metrics = httpx.get(f"{server.url}/metrics", timeout=GET_TIMEOUT_S).text
        assert 'phim_sectors_total{outcome="bad_request",transport="zenoh"} 1.0' in metrics


def test_a_put_on_a_wildcard_key_publishes_nothing_to_every_stream(served: Served) -> None:
    """A put on `.../streams/*/sectors` names no stream: its error would be published on `.../*/errors`,
    which every vehicle's error subscription matches (amplification). It is dropped; a put on a real
    stream's key still gets its error there (the control: the subscriber works)."""
    c = served.client
    with c.declare_subscriber(KEYS.errors("*"), zenoh.handlers.FifoChannel(16)) as errs:
        for stream in ("*", "**", "bad id", "car-9"):  # car-9 last: the replier answers in order
            c.put(KEYS.sectors(stream), b"garbage", congestion_control=BLOCK)
        got = receive(errs, 1)
        time.sleep(0.3)
        assert errs.try_recv() is None
    is_error(decode_response(got[0].payload.to_bytes()), ErrorCode.BAD_REQUEST, "body", "car-9")
