"""uvicorn's HTTP protocol with read deadlines: no connection holds the server while sending nothing.

uvicorn (0.54, httptools) times a connection out only while it idles between requests (`timeout_keep_alive`,
armed after a response): a connection that never sends a byte, sends half of its headers, or stops halfway
through a body stays open for as long as the peer likes (slowloris; 200 such connections were held in the
probe of 2026-11-24). This subclass adds two deadlines and closes the connection when one passes:
- headers: a request's headers must be complete within `header_timeout_s` of the connection opening or of
  the previous response;
- body: its body must be complete within `body_timeout_s` of its headers.
A sector route reading the body then sees the client gone (`ClientDisconnect`) and answers nobody.

Nor does a request's head grow without bound: httptools (llhttp) buffers a header of any size and any number
of headers (a probe grew 32 headers for 10 s each and took 370 MB, never given back). A request line and
headers over `max_header_bytes` together, or more than `max_headers` header fields, are answered 431 and the
connection is closed (counted as they arrive, and measured once complete: a connection holds at most the
limit plus one read).
"""

from __future__ import annotations

import asyncio
import logging

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

log = logging.getLogger(__name__)


class DeadlineHttpProtocol(HttpToolsProtocol):
    """HttpToolsProtocol with a header and a body deadline (class attributes: `with_deadlines` sets them)."""

    header_timeout_s: float = 10.0
    body_timeout_s: float = 30.0
    max_header_bytes: int = 32768
    max_headers: int = 100
    _deadline: asyncio.TimerHandle | None = None
    _in_head = True  # reading a request line and headers (not a body, not between requests)
    _head_bytes = 0  # bytes read of this request's head so far
    _head_fields = 0
    _message_ended = False  # a request ended inside the read being parsed
    _refusal: str | None = None  # why this request's head is refused (431)

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm(self.header_timeout_s, "headers")

    def data_received(self, data: bytes) -> None:
        self._message_ended = False
        super().data_received(data)
        # a read in which a request ended may hold the next one's first bytes: those are not counted
        if self._in_head and not self._message_ended and not self.transport.is_closing():
            self._head_bytes += len(data)
            if self._head_bytes > self.max_header_bytes:
                self._refuse(f"request line and headers: over {self.max_header_bytes} bytes (the limit)")

    def on_header(self, name: bytes, value: bytes) -> None:
        self._head_fields += 1
        if self._head_fields > self.max_headers:
            self._refusal = f"headers: over {self.max_headers} header fields (the limit)"
            raise ValueError(self._refusal)  # httptools stops parsing; uvicorn calls send_400_response
        super().on_header(name, value)

    def send_400_response(self, msg: str) -> None:
        if self._refusal is not None:
            self._refuse(self._refusal)
        else:
            super().send_400_response(msg)

    def _refuse(self, why: str) -> None:
        """431 Request Header Fields Too Large, then close the connection."""
        log.info("http: refusing a request from %s: %s", self.client, why)
        body = why.encode()
        self.transport.write(
            b"HTTP/1.1 431 Request Header Fields Too Large\r\ncontent-type: text/plain; charset=utf-8\r\n"
            b"connection: close\r\ncontent-length: %d\r\n\r\n%s" % (len(body), body)
        )
        self.transport.close()

    def on_headers_complete(self) -> None:
        self._in_head = False
        # a head that came whole in one read was not counted as it arrived: measure what was parsed
        if len(self.url) + sum(len(n) + len(v) + 4 for n, v in self.headers) > self.max_header_bytes:
            self._refusal = f"request line and headers: over {self.max_header_bytes} bytes (the limit)"
            raise ValueError(self._refusal)
        super().on_headers_complete()
        self._arm(self.body_timeout_s, "body")

    def on_message_complete(self) -> None:
        super().on_message_complete()
        self._disarm()
        self._in_head, self._head_bytes, self._head_fields, self._message_ended = True, 0, 0, True

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing() and not self.pipeline:
            self._arm(self.header_timeout_s, "headers")  # the next request's, beside the keep-alive timeout

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def _arm(self, seconds: float, what: str) -> None:
        self._disarm()
        self._deadline = self.loop.call_later(seconds, self._expired, what, seconds)

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None

    def _expired(self, what: str, seconds: float) -> None:
        self._deadline = None
        if not self.transport.is_closing():
            log.info("http: closing a connection from %s: its %s took over %g s", self.client, what, seconds)
            self.transport.close()


def with_deadlines(
    header_timeout_s: float, body_timeout_s: float, max_header_bytes: int = 32768, max_headers: int = 100
) -> type[DeadlineHttpProtocol]:
    """The protocol class for `uvicorn.Config(http=...)` with these deadlines and header limits."""
    return type(
        "DeadlineHttpProtocol",
        (DeadlineHttpProtocol,),
        {
            "header_timeout_s": header_timeout_s,
            "body_timeout_s": body_timeout_s,
            "max_header_bytes": max_header_bytes,
            "max_headers": max_headers,
        },
    )
