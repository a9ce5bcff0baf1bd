"""The HTTP transport: a real uvicorn server on a loopback port, the real default model, httpx as client."""

from __future__ import annotations

import http.client
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import httpx
import msgpack
import numpy as np
import pytest
from server_helpers import (
    LATE_S,
    START_TIMEOUT_S,
    RunningServer,
    StepGate,
    assert_same_boxes,
    comparable_detector,
    kitti_sectors,
    run_direct,
    sector_msg,
    serve,
)

from contract import DetectionsReply, ErrorReply, decode_response, encode_sector
from model.stream import StreamingDetector

MSGPACK = {"Content-Type": "application/msgpack"}
LIMITS = dict(max_body_bytes=2 * 2**20, max_points=50_000, max_string_len=64)


@pytest.fixture(scope="module")
def det() -> StreamingDetector:
    return comparable_detector()


@pytest.fixture(scope="module")
def scan() -> list[np.ndarray]:
    return kitti_sectors(0)  # full sectors, 26k-33k points each


@pytest.fixture(scope="module")
def ref(det: StreamingDetector, scan: list[np.ndarray]) -> list[Any]:
    return run_direct(det, scan)


@pytest.fixture(scope="module")
def server(det: StreamingDetector) -> Iterator[RunningServer]:
    with serve(det, **LIMITS) as s:
        yield s


def post(
    url: str,
    stream: str,
    seq: int,
    points: np.ndarray,
    body: bytes | None = None,
    headers: dict[str, str] = MSGPACK,
    **kw: Any,
) -> httpx.Response:
    """POST one sector (or the given raw body) to a stream's sectors route."""
    if body is None:
        body = encode_sector(sector_msg(stream, seq, points, **kw))
    return httpx.post(f"{url}/v1/streams/{stream}/sectors", content=body, headers=headers, timeout=60)


def detections(r: httpx.Response) -> DetectionsReply:
    assert r.status_code == 200, r.content[:300]
    assert r.headers["content-type"] == "application/msgpack"
    out = decode_response(r.content)
    assert isinstance(out, DetectionsReply)
    return out


def error(
    r: httpx.Response, status: int, code: str, field: str | None = None, needle: str = ""
) -> ErrorReply:
    assert r.status_code == status, (r.status_code, r.content[:300])
    out = decode_response(r.content)
    assert isinstance(out, ErrorReply), out
    assert out.code == code and out.field == field, out
    assert (field or "") in out.message and needle in out.message, out.message
    return out


def metric(url: str, name: str) -> float:
    text = httpx.get(f"{url}/metrics", timeout=10).text
    return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines() if line.startswith(name))


def test_kitti_sectors_over_http_equal_the_model(server, scan, ref):
    replies = [detections(post(server.url, "car-1", i, s)) for i, s in enumerate(scan)]
    assert all(len(r.scores) > 0 for r in replies[1:])  # boxes once the buffer holds the cars ahead
    for i, (r, d) in enumerate(zip(replies, ref, strict=True)):
        assert_same_boxes(r.boxes, r.scores, r.labels, d)
        assert (r.stream_id, r.seq, r.context_sectors, r.gap) == ("car-1", i, i + 1, 0)
    js = post(server.url, "car-1", 9, scan[1], index=1, headers={**MSGPACK, "Accept": "application/json"})
    assert js.status_code == 200 and js.headers["content-type"] == "application/json"
    body = js.json()
    assert body["gap"] == 5 and len(body["boxes"]) == len(body["scores"]) == len(body["class_names"]) > 0
    summary = httpx.get(f"{server.url}/v1/streams/car-1").json()
    assert summary["sectors"] == 5 and summary["last_seq"] == 9 and summary["gaps"] == 5
    assert summary["last_timestamp_ns"] == 9000 and summary["buffered_sectors"] == 3


def test_info_endpoints(server):
    model = httpx.get(f"{server.url}/v1/model").json()
    assert model["config"] == "tiny" and model["classes"] == ["VEHICLE", "PEDESTRIAN", "CYCLIST"]
    assert model["sectors_per_turn"] == 4 and model["point_fields"] == ["x", "y", "z", "intensity"]
    assert model["fields_read"] == model["point_fields"][: model["config_detail"]["vfe"]["point_features"]]
    assert httpx.get(f"{server.url}/health/live").json()["status"] == "live"
    assert httpx.get(f"{server.url}/health/ready").json() == {"status": "ready", "worker_id": "test-worker"}
    assert "phim_batch_sectors_bucket" in httpx.get(f"{server.url}/metrics").text


def test_every_bad_input_gets_its_error_and_harms_no_stream(server, scan, ref):
    url, good = server.url, scan[0][::8]
    assert detections(post(url, "victim", 0, scan[0])).context_sectors == 1
    error(post(url, "x", 0, good, body=b"\x93garbage"), 400, "bad_request", "body", "msgpack")
    error(post(url, "x", 0, good, headers={"Content-Type": "text/plain"}), 400, "bad_request", "Content-Type")
    body = msgpack.unpackb(encode_sector(sector_msg("x", 0, good)))
    for key, change, field, needle in [
        ("seq", None, "seq", "missing"),
        ("points", {"dtype": "<f8"}, "points.dtype", "'<f4'"),
        ("points", {"shape": [10, 4]}, "points.data", "needs 160"),
    ]:
        bad = {k: v for k, v in body.items() if k != key}
        if change is not None:
            bad[key] = {**body[key], **change}
        error(post(url, "x", 0, good, body=msgpack.packb(bad)), 422, "invalid_field", field, needle)
    nan = good.copy()
    nan[3, 0] = np.inf
    error(post(url, "x", 0, nan), 422, "invalid_field", "points", "NaN or inf")
    error(post(url, "x", 0, np.concatenate(scan)), 413, "too_large", "points", "limit is 50000")
    error(post(url, "car$1", 0, good), 422, "invalid_field", "stream_id", "[A-Za-z0-9_.-]")
    error(post(url, "c" * 65, 0, good), 413, "too_large", "stream_id", "limit is 64")
    detections(post(url, "victim", 1, scan[1]))
    error(post(url, "victim", 1, scan[1]), 409, "stale_sequence", "seq", "greater than 1")
    r = httpx.delete(f"{url}/v1/streams/ghost", headers={"Accept": "application/json"})
    assert r.status_code == 404 and r.json()["code"] == "unknown_stream" and "ghost" in r.json()["message"]
    error(
        httpx.get(f"{url}/v1/streams/ghost", headers={"Accept": "application/msgpack"}),
        404,
        "unknown_stream",
        "stream_id",
    )
    for i in (2, 3):  # the victim stream goes on exactly as if nothing had happened
        r = detections(post(url, "victim", i, scan[i]))
        assert_same_boxes(r.boxes, r.scores, r.labels, ref[i])
    assert metric(url, 'phim_sectors_total{outcome="invalid_field"') >= 5


def test_body_over_the_limit_is_refused_before_and_while_reading(server):
    host, port = server.url.removeprefix("http://").split(":")
    conn = http.client.HTTPConnection(host, int(port), timeout=30)
    try:  # only the headers are sent: the server answers from Content-Length alone
        conn.putrequest("POST", "/v1/streams/big/sectors")
        conn.putheader("Content-Type", "application/msgpack")
        conn.putheader("Content-Length", str(100 * 2**20))
        conn.endheaders()
        resp = conn.getresponse()
        reply = decode_response(resp.read())
    finally:
        conn.close()
    assert (
        resp.status == 413 and isinstance(reply, ErrorReply) and "Content-Length 104857600" in reply.message
    )

    def chunks() -> Iterator[bytes]:  # no Content-Length: chunked, counted while reading
        for _ in range(12):
            yield b"\0" * 2**18

    r = httpx.post(f"{server.url}/v1/streams/big/sectors", content=chunks(), headers=MSGPACK, timeout=30)
    error(r, 413, "too_large", "body", "more than 2097152 bytes")


def test_two_streams_interleaved_over_http_equal_each_alone(det, monkeypatch, scan):
    scan_b = kitti_sectors(1, every=2)
    ref_a, ref_b = run_direct(det, scan), run_direct(det, scan_b)
    with serve(det) as s:
        gate = StepGate.install(det, monkeypatch)
        with ThreadPoolExecutor(3) as pool:
            blocker = pool.submit(post, s.url, "z", 0, scan[0])
            assert gate.entered.wait(START_TIMEOUT_S)
            first = [pool.submit(post, s.url, "a", 0, scan[0]), pool.submit(post, s.url, "b", 0, scan_b[0])]
            wait_for(lambda: metric(s.url, "phim_queued_sectors") == 2)
            gate.release()
            detections(blocker.result())
            replies = [[detections(f.result())] for f in first]
            for i in range(1, 4):
                fa, fb = (
                    pool.submit(post, s.url, "a", i, scan[i]),
                    pool.submit(post, s.url, "b", i, scan_b[i]),
                )
                replies[0].append(detections(fa.result()))
                replies[1].append(detections(fb.result()))
    assert gate.batches[:2] == [1, 2]  # a and b shared a forward
    for got, want in ((replies[0], ref_a), (replies[1], ref_b)):
        for r, d in zip(got, want, strict=True):
            assert_same_boxes(r.boxes, r.scores, r.labels, d)


def wait_for(cond: Any, timeout_s: float = START_TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, "condition never became true"
        time.sleep(0.02)


def test_overload_is_503_with_retry_after_and_nothing_is_lost(det, monkeypatch, scan):
    small = scan[0][::8]
    with serve(det, queue_size=2) as s:
        gate = StepGate.install(det, monkeypatch)
        with ThreadPoolExecutor(8) as pool:
            futs = [pool.submit(post, s.url, "s0", 0, small)]
            assert gate.entered.wait(START_TIMEOUT_S)
            futs += [pool.submit(post, s.url, f"s{i}", 0, small) for i in range(1, 8)]
            wait_for(lambda: sum(f.done() for f in futs) == 5)  # rejected while the model is still blocked
            early = [f.result() for f in futs if f.done()]
            gate.release()
            responses = [f.result() for f in futs]
        for r in early:
            error(r, 503, "overloaded", None, "queue_size=2")
            assert int(r.headers["Retry-After"]) >= 1
        assert sorted(r.status_code for r in responses) == [200] * 3 + [503] * 5
        detections(post(s.url, "s1", 1, small, index=1))  # recovered
        assert metric(s.url, 'phim_sectors_total{outcome="ok",transport="http"}') == 4
        assert metric(s.url, 'phim_sectors_total{outcome="overloaded",transport="http"}') == 5


def test_deadline_is_504_and_a_failed_batch_is_500(det, monkeypatch, scan):
    small = scan[0][::8]
    with serve(det, deadline_ms=100) as s:
        gate = StepGate.install(det, monkeypatch)
        gate.fail_at = {1}
        with ThreadPoolExecutor(2) as pool:
            blocker = pool.submit(post, s.url, "z", 0, small)
            assert gate.entered.wait(START_TIMEOUT_S)
            late = pool.submit(post, s.url, "car", 0, small)
            wait_for(lambda: metric(s.url, "phim_queued_sectors") == 1)
            time.sleep(0.25)
            gate.release()
            detections(blocker.result())
            error(late.result(), 504, "deadline_exceeded", None, "deadline is 100 ms")
        error(post(s.url, "car", 0, small), 500, "internal", None, "injected fault")
        assert detections(post(s.url, "car", 0, small)).context_sectors == 1  # retried, state was untouched
        assert metric(s.url, "phim_batch_failures_total") == 1


def test_not_ready_until_warm(det, monkeypatch, scan):
    gate = StepGate.install(det, monkeypatch)  # holds the warm-up forward
    with serve(det, wait_ready=False) as s:
        assert httpx.get(f"{s.url}/health/live").status_code == 200
        r = httpx.get(f"{s.url}/health/ready")
        assert (
            r.status_code == 503 and r.json()["code"] == "not_ready" and "warming up" in r.json()["message"]
        )
        error(post(s.url, "car", 0, scan[0][::8]), 503, "not_ready", None, "warming up")
        gate.release()
        wait_for(lambda: httpx.get(f"{s.url}/health/ready").status_code == 200)


def test_idle_eviction_shows_in_metrics(det, scan):
    with serve(det, idle_timeout_s=0.2) as s:
        assert detections(post(s.url, "parked", 0, scan[0][::8])).context_sectors == 1  # a new stream
        wait_for(lambda: metric(s.url, "phim_stream_evictions_total") == 1)
        assert metric(s.url, "phim_live_streams") == 0
        assert httpx.get(f"{s.url}/v1/streams/parked").status_code == 404


def test_shutdown_answers_everything_in_flight(det, monkeypatch, scan):
    small = scan[0][::8]
    with serve(det) as s:
        gate = StepGate.install(det, monkeypatch)
        with ThreadPoolExecutor(4) as pool:
            futs = [pool.submit(post, s.url, "s0", 0, small)]
            assert gate.entered.wait(START_TIMEOUT_S)  # s0's forward is held; the next two queue behind it
            futs += [pool.submit(post, s.url, f"s{i}", 0, small) for i in (1, 2)]
            wait_for(lambda: metric(s.url, "phim_queued_sectors") == 2)
            stopper = threading.Thread(target=s.stop)
            stopper.start()  # uvicorn stops accepting, waits for the requests in flight
            time.sleep(0.2)
            gate.release()
            assert [detections(f.result()).seq for f in futs] == [0, 0, 0]
            stopper.join(60)
        assert not s.thread.is_alive()


def test_an_oversized_or_malformed_stream_id_is_not_echoed(server):
    """A 10 KB (or malformed) stream ID in the path names no stream: the error says what is wrong without
    echoing it, so the reply stays small and readable with the default limits."""
    for sid in ("a" * 10_000, "bad:id"):
        r = post(server.url, sid, 0, np.zeros((0, 4), np.float32), body=msgpack.packb({}))
        out = decode_response(r.content)
        assert isinstance(out, ErrorReply) and out.stream_id is None and len(r.content) < 1000, out
        r = httpx.get(f"{server.url}/v1/streams/{sid}", timeout=10)
        out = decode_response(r.content, media_type="application/json")
        assert r.status_code in (413, 422) and out.stream_id is None and len(r.content) < 1000, out
    ok = post(server.url, "fine-id", 0, np.zeros((0, 4), np.float32), body=msgpack.packb({}))
    assert decode_response(ok.content).stream_id == "fine-id"  # a valid ID is still echoed


def test_a_client_leaving_mid_body_is_no_error(server, caplog: pytest.LogCaptureFixture):
    """A client that closes its connection halfway through a body: no ERROR log (a traceback), nothing
    counted as answered, and the server goes on serving."""
    import socket

    host, port = server.url.removeprefix("http://").split(":")
    with caplog.at_level("DEBUG"):
        for _ in range(3):
            with socket.create_connection((host, int(port)), timeout=10) as sock:
                head = (
                    "POST /v1/streams/leaver/sectors HTTP/1.1\r\nHost: x\r\nContent-Type: application/msgpack"
                )
                sock.sendall(f"{head}\r\nContent-Length: 100000\r\n\r\n".encode() + b"\0" * 1000)
                time.sleep(0.2)  # the server is reading the body when the client goes
        time.sleep(0.5)
        assert httpx.get(f"{server.url}/health/live", timeout=10).status_code == 200
    errors = [r for r in caplog.records if r.levelno >= 40]
    assert not errors, [r.getMessage() for r in errors]


def test_a_client_leaving_while_its_sector_runs_leaves_the_stream_consistent(det, monkeypatch, scan, caplog):
    """A client sends a whole sector and closes the connection while its forward runs: the sector still
    counts for its stream (the next seq goes on with it as context, the same seq is stale), nothing stays
    queued, and nothing is logged as an error."""
    import socket

    small = scan[0][::8]
    with serve(det) as s, caplog.at_level("DEBUG"):
        gate = StepGate.install(det, monkeypatch)
        host, port = s.url.removeprefix("http://").split(":")
        body = encode_sector(sector_msg("left", 0, small))
        head = "POST /v1/streams/left/sectors HTTP/1.1\r\nHost: x\r\nContent-Type: application/msgpack\r\n"
        with socket.create_connection((host, int(port)), timeout=10) as sock:
            sock.sendall(f"{head}Content-Length: {len(body)}\r\n\r\n".encode() + body)
            assert gate.entered.wait(START_TIMEOUT_S)  # its forward runs, and the client goes
        gate.release()
        wait_for(lambda: metric(s.url, "phim_queued_sectors") == 0)
        assert detections(post(s.url, "left", 1, small)).context_sectors == 2
        assert post(s.url, "left", 0, small).status_code == 409
    errors = [r for r in caplog.records if r.levelno >= 40]
    assert not errors, [r.getMessage() for r in errors]


def test_connections_that_stall_are_closed_and_a_slow_honest_one_is_served(det, caplog):
    """Read deadlines (server/http_protocol.py): a connection that sends nothing, half its headers or half
    its body is closed once its deadline passes (before: held open for good); a body sent in slow chunks
    within the deadline is served. Nothing is logged as an error. Behaviour, not speed: a stall is closed
    not before its deadline and within a generous bound; the slow body pauses a tenth of its deadline."""
    import socket

    header_s, body_s = 0.5, 4.0
    with serve(det, http_header_timeout_s=header_s, http_body_timeout_s=body_s) as s:
        host, port = s.url.removeprefix("http://").split(":")
        head = "POST /v1/streams/slow/sectors HTTP/1.1\r\nHost: x\r\nContent-Type: application/msgpack\r\n"
        body = encode_sector(sector_msg("slow", 0, np.zeros((10, 4), np.float32)))
        stalls = {
            "idle": b"",
            "half headers": head.encode(),
            "half body": f"{head}Content-Length: {len(body)}\r\n\r\n".encode() + body[:10],
        }
        with caplog.at_level("INFO"):
            for name, sent in stalls.items():
                t0 = time.monotonic()  # before the connection opens: no deadline can start earlier
                with socket.create_connection((host, int(port)), timeout=body_s + 2 * LATE_S) as sock:
                    sock.sendall(sent)
                    assert sock.recv(1024) == b"", name  # closed by the server, no reply
                    waited = time.monotonic() - t0
                    assert 0.8 * header_s < waited < body_s + LATE_S, (
                        name,
                        waited,
                    )  # not before its deadline
            with socket.create_connection((host, int(port)), timeout=START_TIMEOUT_S) as sock:
                sock.sendall(f"{head}Content-Length: {len(body)}\r\n\r\n".encode())
                for k in range(0, len(body), len(body) // 3 + 1):
                    time.sleep(body_s / 10)
                    sock.sendall(body[k : k + len(body) // 3 + 1])
                reply = sock.recv(65536)
        assert reply.startswith(b"HTTP/1.1 200"), reply[:200]
    assert not [r for r in caplog.records if r.levelno >= 40]
    assert sum("closing a connection" in r.getMessage() for r in caplog.records) == 3


def test_a_request_head_over_its_limits_is_431_and_the_server_keeps_serving(det, caplog):
    """httptools buffers a header of any size and any number of headers (before: 32 connections growing a
    header for 10 s took 370 MB, never given back). A head over `--http-max-header-bytes` or with more than
    `--http-max-headers` fields is answered 431 and closed, however it arrives; the server serves on."""
    import socket

    with serve(det, http_max_header_bytes=4096, http_max_headers=20) as s:
        host, port = s.url.removeprefix("http://").split(":")
        start = b"GET /v1/model HTTP/1.1\r\nHost: x\r\n"
        heads = {
            "one huge header, in pieces": [start + b"X-Big: "] + [b"a" * 1000] * 5,  # over at the last
            "a huge request line": [b"GET /" + b"a" * 5000],
            "a huge head, whole in one piece": [start + b"X-Big: " + b"a" * 6000 + b"\r\n\r\n"],
            "many headers at once": [start + b"".join(b"X-%d: 1\r\n" % i for i in range(30)) + b"\r\n"],
        }
        with caplog.at_level("INFO"):
            for name, pieces in heads.items():
                with socket.create_connection((host, int(port)), timeout=10) as sock:
                    reply = b""
                    for piece in pieces:  # each head crosses its limit with its last piece
                        sock.sendall(piece)
                    while chunk := sock.recv(65536):  # read to the server's close
                        reply += chunk
                assert reply.startswith(b"HTTP/1.1 431 "), (name, reply[:200])
                assert b"the limit" in reply, name
        # within the limits: served, on the same kind of connection, after all that
        ok = httpx.get(f"{s.url}/v1/model", headers={f"X-{i}": "1" * 100 for i in range(15)}, timeout=10)
        assert ok.status_code == 200
    assert sum("refusing a request" in r.getMessage() for r in caplog.records) == 4
    assert not [r for r in caplog.records if r.levelno >= 40]
