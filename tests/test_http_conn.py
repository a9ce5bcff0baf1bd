"""The sync client's keep-alive connections (`clients.http_conn`) against a real stdlib HTTP/1.1 server."""

from __future__ import annotations

import contextlib
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


@pytest.mark.parametrize("url", ["ftp://host/", "127.0.0.1:8080", "http://"])
def test_a_bad_url_names_the_expected_form(url: str) -> None:
    with pytest.raises(ValueError, match="expected http://host"):
        ConnectionPool(url, timeout_s=1, connect_timeout_s=1)
