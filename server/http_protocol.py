"""uvicorn's HTTP protocol with read deadlines: no connection holds the server while sending nothing.

uvicorn (0.54, httptools) times a connection out only while it idles between requests (`timeout_keep_alive`,
armed after a response): a connection that never sends a byte, sends half of its headers, or stops halfway
through a body stays open for as long as the peer likes (slowloris; 200 such connections were held in the
probe of 2026-11-24). This subclass adds two deadlines and closes the connection when one passes:
- headers: a request's headers must be complete within `header_timeout_s` of the connection opening or of
  the previous response;
- body: its body must be complete within `body_timeout_s` of its headers.
A sector route reading the body then sees the client gone (`ClientDisconnect`) and answers nobody.
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
    _deadline: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm(self.header_timeout_s, "headers")

    def on_headers_complete(self) -> None:
        super().on_headers_complete()
        self._arm(self.body_timeout_s, "body")

    def on_message_complete(self) -> None:
        super().on_message_complete()
        self._disarm()

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


def with_deadlines(header_timeout_s: float, body_timeout_s: float) -> type[DeadlineHttpProtocol]:
    """The protocol class for `uvicorn.Config(http=...)` with these deadlines."""
    return type(
        "DeadlineHttpProtocol",
        (DeadlineHttpProtocol,),
        {"header_timeout_s": header_timeout_s, "body_timeout_s": body_timeout_s},
    )
