"""HTTP client (httpx): msgpack sectors to `POST /v1/streams/{id}/sectors`, JSON for the other routes.

One `httpx.Client` (sync) and one `httpx.AsyncClient` (async, made on first use) keep their connections
open between requests. Timeouts apply per request; `RequestTimeout` when one passes.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import httpx

from clients.base import DetectorClient, RequestTimeout, ServerError, TransportError, answer
from server.protocol import (
    DetectionsReply,
    ErrorCode,
    SectorMessage,
    ServiceError,
    check_stream_id,
    decode_response,
    encode_sector,
)

MSGPACK = "application/msgpack"
SECTOR_HEADERS = {"Content-Type": MSGPACK, "Accept": MSGPACK}


@dataclass(frozen=True)
class HttpConfig:
    url: str = "http://127.0.0.1:8080"
    timeout_s: float = 10.0  # per request: connect, write, read, and waiting for a pooled connection
    connect_timeout_s: float = 5.0
    max_connections: int = 256  # open connections the async client may hold (requests in flight)
    trust_env: bool = False  # honour HTTP(S)_PROXY etc. from the environment


class HttpClient(DetectorClient):
    """The detector over HTTP. Thread-safe on the sync path; the async path belongs to one event loop."""

    transport = "http"

    def __init__(self, url: str = HttpConfig.url, config: HttpConfig | None = None, **overrides: Any):
        cfg = config or HttpConfig(url=url, **overrides)
        self.config = cfg
        self._timeout = httpx.Timeout(cfg.timeout_s, connect=cfg.connect_timeout_s)
        self._limits = httpx.Limits(
            max_connections=cfg.max_connections, max_keepalive_connections=cfg.max_connections
        )
        self._sync: httpx.Client | None = None
        self._async: httpx.AsyncClient | None = None
        self._closed = False

    # ------------------------------------------------------------------------------------------ sectors

    def send(self, msg: SectorMessage) -> DetectionsReply:
        body = encode_sector(msg)
        with _errors(self.config.url):
            r = self._client().post(_sector_path(msg.stream_id), content=body, headers=SECTOR_HEADERS)
        return _sector_answer(r)

    async def send_async(self, msg: SectorMessage) -> DetectionsReply:
        body = encode_sector(msg)
        with _errors(self.config.url):
            r = await self._aclient().post(_sector_path(msg.stream_id), content=body, headers=SECTOR_HEADERS)
        return _sector_answer(r)

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
        with _errors(self.config.url):
            return self._client().get("/health/ready").status_code == 200

    def _get_json(self, method: str, path: str) -> dict[str, Any]:
        with _errors(self.config.url):
            r = self._client().request(method, path, headers={"Accept": "application/json"})
        try:
            body = r.json()
        except json.JSONDecodeError as e:
            raise TransportError(f"{method} {path}: HTTP {r.status_code}, not JSON ({e})") from None
        if r.is_success:
            return body
        raise _json_error(body, r.status_code, f"{method} {path}")

    # ------------------------------------------------------------------------------------------ plumbing

    def _options(self) -> dict[str, Any]:
        """What both httpx clients are built with (raises once this client is closed)."""
        if self._closed:
            raise TransportError("the client is closed")
        url, trust_env = self.config.url, self.config.trust_env
        return {"base_url": url, "timeout": self._timeout, "limits": self._limits, "trust_env": trust_env}

    def _client(self) -> httpx.Client:
        options = self._options()
        if self._sync is None:
            self._sync = httpx.Client(**options)
        return self._sync

    def _aclient(self) -> httpx.AsyncClient:
        options = self._options()
        if self._async is None:
            self._async = httpx.AsyncClient(**options)
        return self._async

    def close(self) -> None:
        """Close the sync connections. The async client (if used) needs `aclose()` from its event loop."""
        self._closed = True
        if self._sync is not None:
            self._sync.close()
            self._sync = None

    async def aclose(self) -> None:
        self.close()
        if self._async is not None:
            await self._async.aclose()
            self._async = None


@contextlib.contextmanager
def _errors(url: str) -> Iterator[None]:
    """httpx's exceptions -> RequestTimeout / TransportError naming the server."""
    try:
        yield
    except httpx.TimeoutException as e:
        raise RequestTimeout(f"{url}: {type(e).__name__}: no answer in time") from e
    except httpx.TransportError as e:
        raise TransportError(f"{url}: {type(e).__name__}: {e}") from e


def _path_id(stream_id: str) -> str:
    try:
        return check_stream_id(stream_id)
    except ServiceError as e:
        raise ServerError(e.code, e.message, e.field) from None  # the server would refuse it the same way


def _sector_path(stream_id: str) -> str:
    return f"/v1/streams/{_path_id(stream_id)}/sectors"


def _sector_answer(r: httpx.Response) -> DetectionsReply:
    try:
        outcome = decode_response(r.content)
    except ServiceError as e:
        raise TransportError(f"HTTP {r.status_code}: the reply is not a PHiM message ({e.message})") from None
    return answer(outcome, r.status_code)


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
