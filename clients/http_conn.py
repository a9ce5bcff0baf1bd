"""Keep-alive HTTP/1.1 connections from the standard library, for the sync client.

`http.client` is used instead of a sync `httpx.Client` because it is leaner per request: on this project's
benchmark (a 455 KB sector, docs/benchmarks.md) the client side of a request costs about 1 ms less. One
request runs on a connection at a time; idle connections wait in a pool shared by threads. A pooled
connection the server has closed meanwhile (its keep-alive timeout) is noticed before reuse and replaced.
"""

from __future__ import annotations

import http.client
import select
import socket
import threading
import urllib.parse
from dataclasses import dataclass


@dataclass(frozen=True)
class Response:
    status: int
    content_type: str
    body: bytes


class ConnectionPool:
    """Connections to the server at `url` (http or https, optionally with a base path)."""

    def __init__(self, url: str, timeout_s: float, connect_timeout_s: float, max_idle: int = 8):
        parts = urllib.parse.urlsplit(url)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ValueError(f"url: {url!r}; expected http://host[:port][/base] or https://...")
        self._https = parts.scheme == "https"
        self._host = parts.hostname
        self._port = parts.port
        self._base = parts.path.rstrip("/")
        self._timeout_s = timeout_s
        self._connect_timeout_s = connect_timeout_s
        self._max_idle = max_idle
        self._idle: list[http.client.HTTPConnection] = []
        self._lock = threading.Lock()

    def request(self, method: str, path: str, body: bytes | None, headers: dict[str, str]) -> Response:
        """One request and its whole response. Socket errors propagate: TimeoutError, OSError,
        http.client.HTTPException."""
        conn = self._take()
        try:
            # a memoryview is sent after the headers as it is; bytes would be copied onto them first
            view = None if body is None else memoryview(body)
            conn.request(method, self._base + path, body=view, headers=headers)
            r = conn.getresponse()
            out = Response(r.status, r.getheader("Content-Type", ""), r.read())
        except BaseException:
            conn.close()
            raise
        if r.will_close:
            conn.close()
        else:
            self._give(conn)
        return out

    def close(self) -> None:
        with self._lock:
            idle, self._idle = self._idle, []
        for conn in idle:
            conn.close()

    def _take(self) -> http.client.HTTPConnection:
        while True:
            with self._lock:
                conn = self._idle.pop() if self._idle else None
            if conn is None:
                return self._connect()
            if not _dropped(conn):
                return conn
            conn.close()

    def _give(self, conn: http.client.HTTPConnection) -> None:
        with self._lock:
            if len(self._idle) < self._max_idle:
                self._idle.append(conn)
                return
        conn.close()

    def _connect(self) -> http.client.HTTPConnection:
        kind = http.client.HTTPSConnection if self._https else http.client.HTTPConnection
        conn = kind(self._host, self._port, timeout=self._connect_timeout_s)
        conn.connect()
        assert conn.sock is not None
        conn.sock.settimeout(self._timeout_s)  # from now on: each send and receive
        conn.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # headers and body go out at once
        return conn


def _dropped(conn: http.client.HTTPConnection) -> bool:
    """An idle connection with something to read was closed by the server (or is out of step): unusable."""
    if conn.sock is None:
        return True
    if hasattr(select, "poll"):  # select.select fails for descriptors >= FD_SETSIZE (1024)
        poller = select.poll()
        poller.register(conn.sock, select.POLLIN)
        return bool(poller.poll(0))
    readable, _, _ = select.select([conn.sock], [], [], 0)
    return bool(readable)
