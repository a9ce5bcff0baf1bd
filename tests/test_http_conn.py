"""The sync client's keep-alive connections (`clients.http_conn`) against a real stdlib HTTP/1.1 server."""

from __future__ import annotations

import contextlib
import http.client
import http.server
import threading
from collections.abc import Iterator
from typing import ClassVar

import pytest

from clients.http_conn import ConnectionPool


class _Handler(http.server.BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"  # keep-alive unless a side says close
    connections: ClassVar[list[object]] = []  # one entry per accepted connection (the handler's socket)
    drop_after_reply = False  # close the socket after answering, without saying so (a keep-alive timeout)

    def setup(self) -> None:
        super().setup()
        _Handler.connections.append(self.connection)

    def do_POST(self) -> None:
        body = self.rfile.read(int(self.headers["Content-Length"]))
        out = f"{self.path} {len(body)} {body[:3]!r}".encode()
        self.send_response(200)
        self.send_header("Content-Type", "text/plain")
        self.send_header("Content-Length", str(len(out)))
        self.end_headers()
        self.wfile.write(out)
        self.wfile.flush()
        if _Handler.drop_after_reply:
            self.close_connection = True

    def do_GET(self) -> None:
        """Raw responses of the shapes a server may send: chunked, to the end of the connection, after a
        1xx, without a body, or not HTTP at all."""
        raw = {
            "/base/chunked": b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\nContent-Type: a/b\r\n\r\n"
            b"3\r\nabc\r\n4;ext=1\r\ndefg\r\n0\r\nX-Trailer: 1\r\n\r\n",
            "/base/to-end": b"HTTP/1.1 200 OK\r\nConnection: close\r\n\r\nall of it",
            "/base/continue": b"HTTP/1.1 100 Continue\r\n\r\n"
            b"HTTP/1.1 201 Created\r\nContent-Length: 2\r\n\r\nok",
            "/base/empty": b"HTTP/1.1 204 No Content\r\n\r\n",
            "/base/garbage": b"SSH-2.0-OpenSSH\r\n\r\n",
        }[self.path]
        self.wfile.write(raw)
        self.wfile.flush()
        self.close_connection = self.path in ("/base/to-end", "/base/garbage")

    def log_message(self, format: str, *args: object) -> None:  # quiet
        pass


class _Server(http.server.ThreadingHTTPServer):
    closed = threading.Semaphore(0)  # released each time the server has closed a connection

    def shutdown_request(self, request: object) -> None:
        super().shutdown_request(request)  # type: ignore[arg-type]
        _Server.closed.release()


@contextlib.contextmanager
def http_server(drop_after_reply: bool) -> Iterator[str]:
    _Handler.connections, _Handler.drop_after_reply = [], drop_after_reply
    _Server.closed = threading.Semaphore(0)
    server = _Server(("127.0.0.1", 0), _Handler)
    t = threading.Thread(target=server.serve_forever, daemon=True)
    t.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/base"
    finally:
        server.shutdown()
        server.server_close()
        t.join(5)


def test_requests_share_one_kept_alive_connection() -> None:
    with http_server(drop_after_reply=False) as url:
        pool = ConnectionPool(url, timeout_s=5, connect_timeout_s=5)
        for i in range(3):
            r = pool.request("POST", f"/p{i}", b"abc" * 100_000, {"Content-Type": "x"})
            assert (r.status, r.content_type, r.body) == (
                200,
                "text/plain",
                f"/base/p{i} 300000 b'abc'".encode(),
            )
        pool.close()
        assert len(_Handler.connections) == 1


def test_a_connection_the_server_closed_is_replaced_before_reuse() -> None:
    with http_server(drop_after_reply=True) as url:
        pool = ConnectionPool(url, timeout_s=5, connect_timeout_s=5)
        bodies = []
        for _ in range(3):
            bodies.append(pool.request("POST", "/x", b"123", {}).body)
            assert _Server.closed.acquire(timeout=5)  # the pooled connection is now closed at the far end
        pool.close()
    assert bodies == [b"/base/x 3 b'123'"] * 3
    assert len(_Handler.connections) == 3  # each reply's connection was dropped by the server


def test_responses_of_every_framing_are_read_whole() -> None:
    with http_server(drop_after_reply=False) as url:
        pool = ConnectionPool(url, timeout_s=5, connect_timeout_s=5)
        got = [pool.request("GET", f"/{p}", None, {}) for p in ("chunked", "empty", "continue", "to-end")]
        assert [(r.status, r.content_type, r.body) for r in got] == [
            (200, "a/b", b"abcdefg"),
            (204, "", b""),
            (201, "", b"ok"),
            (200, "", b"all of it"),
        ]
        assert len(_Handler.connections) == 1  # kept alive until the server said close
        assert pool.request("POST", "/after", b"x", {}).body == b"/base/after 1 b'x'"
        assert len(_Handler.connections) == 2
        with pytest.raises(http.client.BadStatusLine):
            pool.request("GET", "/garbage", None, {})
        with pytest.raises(ValueError, match="line break"):
            pool.request("GET", "/x", None, {"X-Bad": "a\r\nInjected: 1"})
        pool.close()


@pytest.mark.parametrize("url", ["ftp://host/", "127.0.0.1:8080", "http://"])
def test_a_bad_url_names_the_expected_form(url: str) -> None:
    with pytest.raises(ValueError, match="expected http://host"):
        ConnectionPool(url, timeout_s=1, connect_timeout_s=1)
