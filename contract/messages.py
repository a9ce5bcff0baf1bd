"""The wire contract's messages as the server and its clients hold them (decoded, numpy arrays), its limits,
its errors and their HTTP statuses, the point fields and the media types; `contract.codec` turns them into
bytes and back."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from contract.wire import STREAM_ID_PATTERN, ErrorCode

POINT_DTYPE = "<f4"
# the point columns a sector may carry, in the order the model reads them; each sector starts with the first 4
POINT_FIELDS: tuple[str, ...] = ("x", "y", "z", "intensity", "elongation")
REQUIRED_FIELDS: tuple[str, ...] = POINT_FIELDS[:4]
# the coordinate range a sector's points may have: finite, |x|, |y|, |z| <= MAX_COORDINATE_M metres (no LiDAR
# returns past a few hundred); a server answers a sector with any point beyond it INVALID_FIELD on `points`,
# whole (docs/protocol.md, "A sector")
MAX_COORDINATE_M = 10_000.0
MSGPACK = "application/msgpack"  # the sector and reply media type (HTTP Content-Type, zenoh encoding)
MSGPACK_TYPES = (MSGPACK, "application/x-msgpack", "application/vnd.msgpack")  # accepted as the same
JSON = "application/json"  # HTTP only: the same messages, bytes as base64
STREAM_ID_RE = re.compile(STREAM_ID_PATTERN)


HTTP_STATUS: dict[ErrorCode, int] = {
    ErrorCode.BAD_REQUEST: 400,
    ErrorCode.TOO_LARGE: 413,
    ErrorCode.INVALID_FIELD: 422,
    ErrorCode.STALE_SEQUENCE: 409,
    ErrorCode.UNKNOWN_STREAM: 404,
    ErrorCode.UNAUTHORIZED: 401,
    ErrorCode.FORBIDDEN: 403,
    ErrorCode.OVERLOADED: 503,
    ErrorCode.NOT_READY: 503,
    ErrorCode.DEADLINE_EXCEEDED: 504,
    ErrorCode.INTERNAL: 500,
}


class ServiceError(Exception):
    """A request's own failure: a stable code, a message naming the field, and when to retry (overload)."""

    def __init__(
        self, code: ErrorCode, message: str, field: str | None = None, retry_after_s: float | None = None
    ):
        super().__init__(message)
        self.code = ErrorCode(code)
        self.message = message
        self.field = field
        self.retry_after_s = retry_after_s

    def __repr__(self) -> str:
        return f"ServiceError({self.code.value!r}, {self.message!r}, field={self.field!r})"


@dataclass(frozen=True)
class Limits:
    max_body_bytes: int = 64 * 2**20
    max_points: int = 1_000_000
    max_string_len: int = 256
    max_fields: int = 16


@dataclass(frozen=True)
class SectorMessage:
    stream_id: str
    seq: int
    sector_index: int
    timestamp_ns: int
    points: np.ndarray  # (N, C) float32, C >= 4
    fields: tuple[str, ...]  # names of the C columns: ("x", "y", "z", "intensity"[, "elongation", ...])
    reset: bool = False
    # the reply keeps the boxes scored at least this (0..1); None: the server's min_score
    min_score: float | None = None


@dataclass(frozen=True)
class Timings:
    queue_ms: float
    model_ms: float
    total_ms: float


@dataclass(frozen=True)
class DetectionsReply:
    stream_id: str
    seq: int
    boxes: np.ndarray  # (K, 7) float32 x, y, z, l, w, h, yaw
    scores: np.ndarray  # (K,) float32
    labels: np.ndarray  # (K,) int32
    class_names: tuple[str, ...]  # (K,) name of each box's class
    context_sectors: int  # sectors the prediction saw (the new one plus the buffered ones)
    gap: int  # sectors missed since the stream's last processed seq
    timings: Timings
    cold_start: bool = False  # ran on a fresh state (first on this worker, or reset): no earlier context
    worker_id: str = ""  # the worker that ran it


@dataclass(frozen=True)
class ErrorReply:
    code: ErrorCode
    message: str
    field: str | None = None
    stream_id: str | None = None
    seq: int | None = None
    retry_after_s: float | None = None

    @staticmethod
    def from_error(e: ServiceError, stream_id: str | None = None, seq: int | None = None) -> ErrorReply:
        """The reply to `e`; `stream_id` is echoed only when it is a stream ID (an oversized or malformed one
        from a path or key would make the reply itself unreadable, and no stream owns it)."""
        if stream_id is not None and not (
            len(stream_id) <= Limits.max_string_len and STREAM_ID_RE.fullmatch(stream_id)
        ):
            stream_id = None
        return ErrorReply(e.code, e.message, e.field, stream_id, seq, e.retry_after_s)
