"""The one client interface (HTTP and zenoh alike) and its typed errors.

A client sends one sector of a stream (`contract.SectorMessage`) and returns the server's
`contract.DetectionsReply` (boxes (K, 7) x, y, z, l, w, h, yaw; scores (K,); labels (K,); class names),
or raises:
  - `ServerError`: the server answered with an error (its `code`, `message`, `field`, `retry_after_s`);
  - `TransportError`: no answer came (connection failed, the request timed out: `RequestTimeout`, or the
    reply could not be read).
"""

from __future__ import annotations

import abc
import time
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import Any, Self

import numpy as np

from contract import REQUIRED_FIELDS, DetectionsReply, ErrorCode, ErrorReply, SectorMessage, ServiceError

OnSent = Callable[[], None]  # called once a sector is on its way, in order, to the server


class ClientError(Exception):
    """Base of every error a client raises."""


class ServerError(ServiceError, ClientError):
    """The server answered this request with an error (docs/protocol.md "An error")."""

    def __init__(
        self,
        code: ErrorCode,
        message: str,
        field: str | None = None,
        retry_after_s: float | None = None,
        stream_id: str | None = None,
        seq: int | None = None,
        status: int | None = None,
    ):
        super().__init__(code, message, field, retry_after_s)
        self.stream_id = stream_id
        self.seq = seq
        self.status = status  # the HTTP status, None over zenoh

    @staticmethod
    def from_reply(e: ErrorReply, status: int | None = None) -> ServerError:
        return ServerError(e.code, e.message, e.field, e.retry_after_s, e.stream_id, e.seq, status)

    def __repr__(self) -> str:
        return f"ServerError({self.code.value!r}, {self.message!r}, field={self.field!r}, seq={self.seq!r})"


class TransportError(ClientError):
    """No answer from the server: it could not be reached, or its reply could not be read."""


class RequestTimeout(TransportError):
    """The request's timeout passed before the server answered."""


def answer(outcome: DetectionsReply | ErrorReply, status: int | None = None) -> DetectionsReply:
    """A decoded reply -> the detections, or raise its ServerError."""
    if isinstance(outcome, ErrorReply):
        raise ServerError.from_reply(outcome, status)
    return outcome


def sector_message(
    stream_id: str,
    seq: int,
    sector_index: int,
    points: np.ndarray,
    fields: Sequence[str] = REQUIRED_FIELDS,
    timestamp_ns: int | None = None,
    reset: bool = False,
) -> SectorMessage:
    """A SectorMessage from plain arguments; points (N, C) are converted to float32, time defaults to now."""
    return SectorMessage(
        stream_id=stream_id,
        seq=seq,
        sector_index=sector_index,
        timestamp_ns=time.time_ns() if timestamp_ns is None else timestamp_ns,
        points=np.ascontiguousarray(points, dtype=np.float32),
        fields=tuple(fields),
        reset=reset,
    )


class DetectorClient(abc.ABC):
    """Send sectors, get detections: the interface both transports implement.

    Use as a context manager (`with HttpClient(...) as c:`), or `async with` in asyncio code; `close()` /
    `aclose()` release connections and sessions.
    """

    transport: str  # "http" or "zenoh"
    retries: int = 0  # sectors sent once more to another worker after theirs left (zenoh, auto_workers)

    @abc.abstractmethod
    def send(self, msg: SectorMessage) -> DetectionsReply:
        """Send one sector and wait for its detections (raises ServerError / TransportError)."""

    @abc.abstractmethod
    async def send_async(self, msg: SectorMessage, on_sent: OnSent | None = None) -> DetectionsReply:
        """The same without blocking the event loop; many may be in flight at once.

        `on_sent` (called at most once, on the event loop) says the sector is on its way: a sector of the
        same stream sent after that reaches the server after this one (HTTP: this request's body has been
        written to its connection; zenoh: the get is queued on the session, whose one link keeps order).
        Not called when the send failed before that; the caller must not wait for it then."""

    @abc.abstractmethod
    def end_stream(self, stream_id: str) -> None:
        """End a stream: the server drops its state (its next sector starts fresh)."""

    @abc.abstractmethod
    def model_info(self) -> dict[str, Any]:
        """The served model: name, config, classes, sectors_per_turn, point_fields, ..."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the connections or the session (idempotent)."""

    async def aclose(self) -> None:
        """Release what the async path holds as well (default: the same as close)."""
        self.close()

    def send_points(
        self,
        stream_id: str,
        seq: int,
        sector_index: int,
        points: np.ndarray,
        fields: Sequence[str] = REQUIRED_FIELDS,
        timestamp_ns: int | None = None,
        reset: bool = False,
    ) -> DetectionsReply:
        """Send a sector given as an (N, C) array whose columns are named by `fields`."""
        return self.send(sector_message(stream_id, seq, sector_index, points, fields, timestamp_ns, reset))

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.aclose()
