"""Keep-alive HTTP/1.1 connections for the sync client, on plain sockets.

Neither a sync `httpx.Client` nor `http.client` is used: both cost more per request than this project's
benchmark leaves (a 455 KB sector, docs/benchmarks.md): httpx about 1 ms more on the client side, and
`http.client` parses a response's headers with the `email` package (about 0.2 ms in place). A connection
here sends the request line and headers, then the body as it is (no copy onto the headers), and reads a
response whose body has a Content-Length, is chunked, or runs to the end of a connection the server closes;
1xx responses are skipped. One request runs on a connection at a time; idle connections wait in a pool
shared by threads. A pooled connection the server has closed meanwhile (its keep-alive timeout) is noticed
before reuse and replaced. Protocol errors raise `http.client`'s exception types, socket errors `OSError`.
"""

from __future__ import annotations

import http.client
import select
import socket
import ssl
import threading
import urllib.parse
from dataclasses import dataclass

MAX_HEAD_BYTES = 64 * 1024  # status line and headers of one response
RECV_BYTES = 256 * 1024


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
        self._connect_s = connect_timeout_s
        self._max_idle = max_idle
        self._idle: list[Connection] = []
        self._lock = threading.Lock()

    def request(self, method: str, path: str, body: bytes | None, headers: dict[str, str]) -> Response:
        """One request and its whole response. Socket errors propagate: TimeoutError, OSError,
        http.client.HTTPException."""
        conn = self._take()
        try:
            out, reusable = conn.exchange(method, self._base + path, body, headers)
        except BaseException:
            conn.close()
            raise
        if reusable:
            self._give(conn)
        else:
            conn.close()
        return out

    def close(self) -> None:
        with self._lock:
            idle, self._idle = self._idle, []
        for conn in idle:
            conn.close()

    def _take(self) -> Connection:
        while True:
            with self._lock:
                conn = self._idle.pop() if self._idle else None
            if conn is None:
                return Connection(self._host, self._port, self._https, self._timeout_s, self._connect_s)
            if not conn.dropped():
                return conn
            conn.close()

    def _give(self, conn: Connection) -> None:
        with self._lock:
            if len(self._idle) < self._max_idle:
                self._idle.append(conn)
                return
        conn.close()


class Connection:
    """One HTTP/1.1 connection (TCP_NODELAY; TLS for https), one exchange at a time."""

    def __init__(self, host: str, port: int | None, https: bool, timeout_s: float, connect_timeout_s: float):
        port = port or (443 if https else 80)
        sock = socket.create_connection((host, port), timeout=connect_timeout_s)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # headers and body go out at once
        if https:
            sock = ssl.create_default_context().wrap_socket(sock, server_hostname=host)
        sock.settimeout(timeout_s)  # from now on: each send and receive
        self._sock = sock
        self._host = host if port == (443 if https else 80) else f"{host}:{port}"
        self._buf = bytearray()  # received, not yet consumed

    def exchange(
        self, method: str, target: str, body: bytes | None, headers: dict[str, str]
    ) -> tuple[Response, bool]:
        """Send one request, read its response -> (response, whether the connection can be reused)."""
        fields = {"Host": self._host, **headers}
        if body is not None:
            fields["Content-Length"] = str(len(body))
        if any("\r" in x or "\n" in x for x in (target, *fields, *fields.values())):
            raise ValueError(f"{method} {target!r}: a line break in the target or a header")
        lines = [f"{method} {target} HTTP/1.1", *(f"{k}: {v}" for k, v in fields.items()), "", ""]
        self._sock.sendall("\r\n".join(lines).encode("latin-1"))
        if body:
            self._sock.sendall(memoryview(body))
        status, version, fields_in = self._read_head()
        while 100 <= status < 200:  # informational (100 Continue): the real response follows
            status, version, fields_in = self._read_head()
        close = fields_in.get("connection", "").lower() == "close" or version == "HTTP/1.0"
        if method == "HEAD" or status in (204, 304):
            data = b""
        elif "chunked" in fields_in.get("transfer-encoding", "").lower():
            data = self._read_chunked()
        elif "content-length" in fields_in:
            data = self._read_exact(_length(fields_in["content-length"]))
        else:  # the body runs to the end of the connection
            data, close = self._read_to_end(), True
        return Response(status, fields_in.get("content-type", ""), data), not close

    def dropped(self) -> bool:
        """An idle connection with something to read was closed by the server (or is out of step)."""
        if self._buf:
            return True
        if hasattr(select, "poll"):  # select.select fails for descriptors >= FD_SETSIZE (1024)
            poller = select.poll()
            poller.register(self._sock, select.POLLIN)
            return bool(poller.poll(0))
        readable, _, _ = select.select([self._sock], [], [], 0)
        return bool(readable)

    def close(self) -> None:
        self._sock.close()

    def _fill(self) -> bool:
        """Receive more into the buffer; False at the end of the connection."""
        chunk = self._sock.recv(RECV_BYTES)
        self._buf += chunk
        return bool(chunk)

    def _read_line(self) -> bytes:
        at = self._buf.find(b"\r\n")
        while at < 0:
            if len(self._buf) > MAX_HEAD_BYTES:
                raise http.client.LineTooLong(f"a response line over {MAX_HEAD_BYTES} bytes")
            if not self._fill():
                raise http.client.IncompleteRead(bytes(self._buf))
            at = self._buf.find(b"\r\n")
        line = bytes(self._buf[:at])
        del self._buf[: at + 2]
        return line

    def _read_head(self) -> tuple[int, str, dict[str, str]]:
        """The status line and headers -> (status, HTTP version, {lower-case name: value})."""
        end = self._buf.find(b"\r\n\r\n")
        while end < 0:
            if len(self._buf) > MAX_HEAD_BYTES:
                raise http.client.LineTooLong(f"response headers over {MAX_HEAD_BYTES} bytes")
            if not self._fill():
                if self._buf:
                    raise http.client.IncompleteRead(bytes(self._buf))
                raise http.client.RemoteDisconnected("the server closed the connection without a response")
            end = self._buf.find(b"\r\n\r\n")
        lines = self._buf[:end].decode("latin-1").split("\r\n")
        del self._buf[: end + 4]
        version, _, rest = lines[0].partition(" ")
        code = rest[:3]
        if not version.startswith("HTTP/1.") or not code.isdigit():
            raise http.client.BadStatusLine(lines[0])
        fields = {}
        for line in lines[1:]:
            name, colon, value = line.partition(":")
            if not colon:
                raise http.client.HTTPException(f"a malformed response header: {line!r}")
            fields[name.strip().lower()] = value.strip()
        return int(code), version, fields

    def _read_exact(self, n: int) -> bytes:
        while len(self._buf) < n:
            if not self._fill():
                raise http.client.IncompleteRead(bytes(self._buf), n - len(self._buf))
        data = bytes(self._buf[:n])
        del self._buf[:n]
        return data

    def _read_chunked(self) -> bytes:
        parts = []
        while True:
            size = self._read_line().split(b";", 1)[0].strip()
            try:
                n = int(size, 16)
            except ValueError:
                raise http.client.HTTPException(f"a malformed chunk size: {size!r}") from None
            if n == 0:
                while self._read_line():  # trailers, up to the empty line
                    pass
                return b"".join(parts)
            parts.append(self._read_exact(n))
            if self._read_line():
                raise http.client.HTTPException("a chunk not followed by CRLF")

    def _read_to_end(self) -> bytes:
        while self._fill():
            pass
        data = bytes(self._buf)
        self._buf.clear()
        return data


def _length(value: str) -> int:
    if not value.strip().isdigit():
        raise http.client.HTTPException(f"Content-Length: {value!r}; expected an integer")
    return int(value)
