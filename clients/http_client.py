"""HTTP client: msgpack sectors to `POST /v1/streams/{id}/sectors`, JSON for the other routes.

One stack, httpx: the sync path on an `httpx.Client` (its connection pool is thread-safe: "it can be shared
between threads"), the async path on an `httpx.AsyncClient` (made on first use, bound to that event loop).
Both keep their connections open between requests (keep-alive, TCP_NODELAY). The timeout applies to each
send and receive (and to waiting for a pooled connection); `RequestTimeout` when one passes.

`send_async(msg, on_sent)` calls `on_sent` once the request's body has been written to its connection
(httpcore's `trace` extension, event `http11.send_request_body.complete`): from then on a later request,
on another connection, reaches the server after this one. That is how the load tester keeps one stream's
sectors in order without waiting for their answers.
"""

from __future__ import annotations

import contextlib
import json
import ssl
import urllib.parse
from collections.abc import Awaitable, Callable, Iterator
from dataclasses import dataclass
from typing import Any

import httpx

from clients.base import DetectorClient, OnSent, RequestTimeout, ServerError, TransportError, answer
from contract import (
    DEFAULT_URL,
    MSGPACK,
    DetectionsReply,
    ErrorCode,
    SectorMessage,
    ServiceError,
    check_stream_id,
    decode_response,
    encode_sector,
)

SECTOR_HEADERS = {"Content-Type": MSGPACK, "Accept": MSGPACK}
BODY_WRITTEN = "http11.send_request_body.complete"  # httpcore's trace event (HTTP/1.1)


@dataclass(frozen=True)
class HttpConfig:
    url: str = DEFAULT_URL
    timeout_s: float = 10.0  # each send and receive, and waiting for a pooled connection
    connect_timeout_s: float = 5.0
    max_connections: int | None = 256  # open connections, idle or busy, per path (sync, async); None: any
    # an idle connection is dropped after this, before the server's keep-alive timeout (uvicorn: 5 s) closes
    # it: a request sent on a connection the server is closing at that moment is lost (seen once in a
    # 10-minute soak with httpx's default, 5 s, the same as the server's)
    keepalive_expiry_s: float = 2.0
    token: str | None = None  # a bearer token (`phim serve --auth-tokens`), sent on every request
    ca_cert: str | None = None  # https: trust this CA (PEM) instead of the system's


class HttpClient(DetectorClient):
    """The detector over HTTP. Thread-safe on the sync path; the async path belongs to one event loop."""

    transport = "http"

    def __init__(self, url: str = HttpConfig.url, config: HttpConfig | None = None, **overrides: Any):
        cfg = config or HttpConfig(url=url, **overrides)
        _check_url(cfg.url)
        self.config = cfg
        self._timeout = httpx.Timeout(cfg.timeout_s, connect=cfg.connect_timeout_s)
        self._limits = httpx.Limits(
            max_connections=cfg.max_connections,
            max_keepalive_connections=cfg.max_connections,
            keepalive_expiry=cfg.keepalive_expiry_s,
        )
        self._headers = {"Authorization": f"Bearer {cfg.token}"} if cfg.token else {}
        self._verify: ssl.SSLContext | bool = (
            ssl.create_default_context(cafile=cfg.ca_cert) if cfg.ca_cert else True
        )
        self._sync = httpx.Client(
            base_url=cfg.url,
            timeout=self._timeout,
            limits=self._limits,
            headers=self._headers,
            verify=self._verify,
        )
        self._async: httpx.AsyncClient | None = None
        self._closed = False

    # ------------------------------------------------------------------------------------------ sectors

    def send(self, msg: SectorMessage) -> DetectionsReply:
        r = self._request("POST", _sector_path(msg.stream_id), encode_sector(msg), SECTOR_HEADERS)
        return _sector_answer(r.status_code, r.content)

    async def send_async(self, msg: SectorMessage, on_sent: OnSent | None = None) -> DetectionsReply:
        body = encode_sector(msg)
        extensions = None if on_sent is None else {"trace": _body_written(on_sent)}
        with _errors(self.config.url, "POST", _sector_path(msg.stream_id)):
            r = await self._aclient().post(
                _sector_path(msg.stream_id), content=body, headers=SECTOR_HEADERS, extensions=extensions
            )
        return _sector_answer(r.status_code, r.content)

    # ------------------------------------------------------------------------------------------ control

    def end_stream(self, stream_id: str) -> None:
        self._get_json("DELETE", f"/v1/streams/{_path_id(stream_id)}")

    def model_info(self) -> dict[str, Any]:
        return self._get_json("GET", "/v1/model")

    def streams(self) -> list[dict[str, Any]]:
        """Summaries of the live streams (sectors run, last seq, gaps, pending, buffered, idle time)."""
        return list(self._get_json("GET", "/v1/streams")["streams"])

    def stream_info(self, stream_id: str) -> dict[str, Any]:
        return self._get_json("GET", f"/v1/streams/{_path_id(stream_id)}")

    def ready(self) -> bool:
        """True once the server has warmed up (GET /health/ready is 200)."""
        return self._request("GET", "/health/ready", None, {}).status_code == 200

    def _get_json(self, method: str, path: str) -> dict[str, Any]:
        r = self._request(method, path, None, {"Accept": "application/json"})
        try:
            body = json.loads(r.content)
        except json.JSONDecodeError as e:
            raise TransportError(f"{method} {path}: HTTP {r.status_code}, not JSON ({e})") from None
        if r.is_success:
            return body
        raise _json_error(body, r.status_code, f"{method} {path}")

    # ------------------------------------------------------------------------------------------ plumbing

    def _request(self, method: str, path: str, body: bytes | None, headers: dict[str, str]) -> httpx.Response:
        """One sync request on a pooled connection; httpx's errors -> RequestTimeout / TransportError."""
        if self._closed:
            raise TransportError("the client is closed")
        with _errors(self.config.url, method, path):
            return self._sync.request(method, path, content=body, headers=headers)

    def _aclient(self) -> httpx.AsyncClient:
        if self._closed:
            raise TransportError("the client is closed")
        if self._async is None:
            self._async = httpx.AsyncClient(
                base_url=self.config.url,
                timeout=self._timeout,
                limits=self._limits,
                headers=self._headers,
                verify=self._verify,
            )
        return self._async

    def close(self) -> None:
        """Close the sync connections. The async client (if used) needs `aclose()` from its event loop."""
        self._closed = True
        self._sync.close()

    async def aclose(self) -> None:
        self.close()
        if self._async is not None:
            await self._async.aclose()
            self._async = None


def _check_url(url: str) -> None:
    parts = urllib.parse.urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"url: {url!r}; expected http://host[:port][/base] or https://...")


def _body_written(on_sent: OnSent) -> Callable[[str, dict[str, Any]], Awaitable[None]]:
    """An httpcore trace callback that calls `on_sent` when the request's body has been written."""

    async def trace(event: str, info: dict[str, Any]) -> None:
        if event == BODY_WRITTEN:
            on_sent()

    return trace


@contextlib.contextmanager
def _errors(url: str, method: str, path: str) -> Iterator[None]:
    """httpx's exceptions -> RequestTimeout / TransportError naming the server and the request."""
    try:
        yield
    except httpx.TimeoutException as e:
        raise RequestTimeout(f"{url}: {method} {path}: {type(e).__name__}: no answer in time") from e
    except httpx.RequestError as e:  # connection refused or dropped, a malformed or undecodable reply
        raise TransportError(f"{url}: {method} {path}: {type(e).__name__}: {e}") from e


def _path_id(stream_id: str) -> str:
    try:
        return check_stream_id(stream_id)
    except ServiceError as e:
        raise ServerError(e.code, e.message, e.field) from None  # the server would refuse it the same way


def _sector_path(stream_id: str) -> str:
    return f"/v1/streams/{_path_id(stream_id)}/sectors"


def _sector_answer(status: int, content: bytes) -> DetectionsReply:
    try:
        outcome = decode_response(content)
    except ServiceError as e:
        raise TransportError(f"HTTP {status}: the reply is not a PHiM message ({e.message})") from None
    return answer(outcome, status)


def _json_error(body: Any, status: int, what: str) -> ClientErrorT:
    if isinstance(body, dict) and body.get("kind") == "error":
        try:
            code = ErrorCode(body.get("code"))
        except ValueError:
            code = ErrorCode.INTERNAL
        retry = body.get("retry_after_s")
        return ServerError(
            code,
            str(body.get("message")),
            body.get("field"),
            None if retry is None else float(retry),
            body.get("stream_id"),
            body.get("seq"),
            status,
        )
    return TransportError(f"{what}: HTTP {status}: {str(body)[:200]}")


ClientErrorT = ServerError | TransportError
