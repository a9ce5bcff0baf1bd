"""The wire contract between the server and its clients, owned by neither: sectors in, detections or errors
out (msgpack), the limits, the error codes, the zenoh key space, the point fields and the media types.

Arrays travel as maps {"dtype": "<f4", "shape": [N, C], "data": <raw little-endian bytes>}: never pickle,
never lists of floats, never msgpack extension types. Decoding is strict and every failure is a
`ServiceError` whose message names the field and says what was expected. numpy + msgpack only (no torch):
a client needs nothing else. See docs/protocol.md.
"""

from __future__ import annotations

import enum
import math
import re
from dataclasses import dataclass
from typing import Any, NoReturn

import msgpack
import numpy as np

POINT_DTYPE = "<f4"
# the point columns a sector may carry, in the order the model reads them; each sector starts with the first 4
POINT_FIELDS: tuple[str, ...] = ("x", "y", "z", "intensity", "elongation")
REQUIRED_FIELDS: tuple[str, ...] = POINT_FIELDS[:4]
MSGPACK = "application/msgpack"  # the sector and reply media type (HTTP Content-Type, zenoh encoding)
MSGPACK_TYPES = (MSGPACK, "application/x-msgpack", "application/vnd.msgpack")  # accepted as the same
JSON = "application/json"
STREAM_ID_RE = re.compile(r"[A-Za-z0-9_.\-]+")
INT64_MAX = 2**63 - 1
SECTOR_KEYS = ("stream_id", "seq", "sector_index", "timestamp_ns", "points", "fields", "reset")
ARRAY_KEYS = ("dtype", "shape", "data")


class ErrorCode(enum.StrEnum):
    BAD_REQUEST = "bad_request"  # undecodable body                      HTTP 400
    TOO_LARGE = "too_large"  # body / points / strings over limit         HTTP 413
    INVALID_FIELD = "invalid_field"  # a field has a wrong type/value     HTTP 422
    STALE_SEQUENCE = "stale_sequence"  # seq <= last seq of the stream    HTTP 409
    UNKNOWN_STREAM = "unknown_stream"  #                                  HTTP 404
    OVERLOADED = "overloaded"  # queue full / stream table full           HTTP 503 + Retry-After
    NOT_READY = "not_ready"  # warming up / shutting down                 HTTP 503
    DEADLINE_EXCEEDED = "deadline_exceeded"  # waited past its deadline   HTTP 504
    INTERNAL = "internal"  # model failure for this batch                 HTTP 500


HTTP_STATUS: dict[ErrorCode, int] = {
    ErrorCode.BAD_REQUEST: 400,
    ErrorCode.TOO_LARGE: 413,
    ErrorCode.INVALID_FIELD: 422,
    ErrorCode.STALE_SEQUENCE: 409,
    ErrorCode.UNKNOWN_STREAM: 404,
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


DEFAULT_KEY_PREFIX = "phim/v1"


@dataclass(frozen=True)
class KeySpace:
    """The key expressions under one prefix."""

    prefix: str = DEFAULT_KEY_PREFIX

    @property
    def sector_queryable(self) -> str:  # request/reply: get with a sector as payload
        return f"{self.prefix}/streams/*/sector"

    @property
    def sector_subscriber(self) -> str:  # pub/sub: put a sector
        return f"{self.prefix}/streams/*/sectors"

    def sector(self, stream_id: str) -> str:
        return f"{self.prefix}/streams/{stream_id}/sector"

    def sectors(self, stream_id: str) -> str:
        return f"{self.prefix}/streams/{stream_id}/sectors"

    def detections(self, stream_id: str) -> str:
        return f"{self.prefix}/streams/{stream_id}/detections"

    def errors(self, stream_id: str) -> str:
        return f"{self.prefix}/streams/{stream_id}/errors"

    def worker(self, worker_id: str) -> str:
        return f"{self.prefix}/workers/{worker_id}"

    def stream_id_of(self, key: str) -> str:
        """The stream-ID chunk of `{prefix}/streams/{id}/...` ('' if the key has another shape)."""
        head = f"{self.prefix}/streams/"
        return key[len(head) :].split("/", 1)[0] if key.startswith(head) else ""


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
        return ErrorReply(e.code, e.message, e.field, stream_id, seq, e.retry_after_s)


# ----------------------------------------------------------------------------------------------- helpers


def _fail(code: ErrorCode, field: str | None, message: str) -> NoReturn:
    raise ServiceError(code, f"{field}: {message}" if field else message, field)


def _reject_ext(code: int, data: bytes) -> NoReturn:
    raise ValueError(f"msgpack extension type {code} is not allowed")


def _unpack(data: bytes, limits: Limits, max_array_len: int | None = None) -> Any:
    if not isinstance(data, bytes | bytearray | memoryview):
        _fail(ErrorCode.BAD_REQUEST, "body", f"got {type(data).__name__}; expected bytes")
    if len(data) > limits.max_body_bytes:
        _fail(ErrorCode.TOO_LARGE, "body", f"{len(data)} bytes; the limit is {limits.max_body_bytes}")
    try:
        return msgpack.unpackb(
            data,
            raw=False,
            strict_map_key=True,
            ext_hook=_reject_ext,
            max_bin_len=limits.max_body_bytes,
            max_str_len=max(limits.max_string_len, 1024) * 4,
            max_array_len=max_array_len or max(limits.max_fields, 8) * 8,
            max_map_len=64,
        )
    except Exception as e:  # msgpack raises ValueError, TypeError, ExtraData, FormatError, StackError...
        if isinstance(e, ValueError) and " exceeds max_" in str(e):
            _fail(ErrorCode.TOO_LARGE, "body", f"a string, array or map over the limit ({e})")
        _fail(ErrorCode.BAD_REQUEST, "body", f"not a valid msgpack message ({type(e).__name__}: {e})")


def _map(obj: Any, field: str, keys: tuple[str, ...]) -> dict[str, Any]:
    if not isinstance(obj, dict):
        _fail(ErrorCode.INVALID_FIELD, field, f"got {_kind(obj)}; expected a map with keys {list(keys)}")
    unknown = sorted(set(obj) - set(keys))
    if unknown:
        _fail(ErrorCode.INVALID_FIELD, field, f"unknown keys {unknown}; expected only {list(keys)}")
    return obj


def _kind(obj: Any) -> str:
    return {dict: "a map", list: "an array", str: "a string", bytes: "binary"}.get(
        type(obj), type(obj).__name__
    )


def _required(obj: dict[str, Any], key: str, prefix: str = "") -> Any:
    if key not in obj:
        _fail(ErrorCode.INVALID_FIELD, prefix + key, "missing; it is required")
    return obj[key]


def _int(value: Any, field: str, lo: int = 0, hi: int = INT64_MAX) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        _fail(ErrorCode.INVALID_FIELD, field, f"got {_kind(value)}; expected an integer in [{lo}, {hi}]")
    if not lo <= value <= hi:
        _fail(ErrorCode.INVALID_FIELD, field, f"got {value}; expected an integer in [{lo}, {hi}]")
    return value


def _str(value: Any, field: str, limits: Limits) -> str:
    if not isinstance(value, str):
        _fail(ErrorCode.INVALID_FIELD, field, f"got {_kind(value)}; expected a string")
    if len(value) > limits.max_string_len:
        _fail(ErrorCode.TOO_LARGE, field, f"{len(value)} characters; the limit is {limits.max_string_len}")
    return value


def check_stream_id(value: Any, limits: Limits = Limits(), field: str = "stream_id") -> str:
    """A stream ID: a non-empty string of [A-Za-z0-9_.-], at most `max_string_len` characters."""
    value = _str(value, field, limits)
    if not STREAM_ID_RE.fullmatch(value):
        _fail(ErrorCode.INVALID_FIELD, field, f"{value!r}; expected a non-empty string of [A-Za-z0-9_.-]")
    return value


def _fields(value: Any, limits: Limits) -> tuple[str, ...]:
    if not isinstance(value, list):
        _fail(ErrorCode.INVALID_FIELD, "fields", f"got {_kind(value)}; expected an array of column names")
    if len(value) > limits.max_fields:
        _fail(ErrorCode.TOO_LARGE, "fields", f"{len(value)} names; the limit is {limits.max_fields}")
    names = tuple(_str(v, f"fields[{i}]", limits) for i, v in enumerate(value))
    if names[:4] != REQUIRED_FIELDS:
        _fail(
            ErrorCode.INVALID_FIELD,
            "fields",
            f"{list(names)}; expected to start with {list(REQUIRED_FIELDS)}",
        )
    if len(set(names)) != len(names) or not all(names):
        _fail(ErrorCode.INVALID_FIELD, "fields", f"{list(names)}; expected unique non-empty names")
    return names


def _points(value: Any, n_fields: int, limits: Limits) -> np.ndarray:
    arr = _map(value, "points", ARRAY_KEYS)
    dtype = _required(arr, "dtype", "points.")
    if dtype != POINT_DTYPE:
        _fail(ErrorCode.INVALID_FIELD, "points.dtype", f"{dtype!r}; expected {POINT_DTYPE!r} (float32 LE)")
    shape = _required(arr, "shape", "points.")
    if not isinstance(shape, list) or len(shape) != 2:
        _fail(ErrorCode.INVALID_FIELD, "points.shape", f"{shape!r}; expected [N, C] (two integers)")
    n = _int(shape[0], "points.shape[0]")
    c = _int(shape[1], "points.shape[1]", lo=4, hi=limits.max_fields)
    if c != n_fields:
        _fail(ErrorCode.INVALID_FIELD, "points.shape[1]", f"{c} columns but {n_fields} names in fields")
    if n > limits.max_points:
        _fail(ErrorCode.TOO_LARGE, "points", f"{n} points; the limit is {limits.max_points}")
    data = _required(arr, "data", "points.")
    if not isinstance(data, bytes):
        _fail(ErrorCode.INVALID_FIELD, "points.data", f"got {_kind(data)}; expected binary (raw bytes)")
    if len(data) != n * c * 4:
        _fail(ErrorCode.INVALID_FIELD, "points.data", f"{len(data)} bytes; shape {[n, c]} needs {n * c * 4}")
    return np.frombuffer(data, dtype=POINT_DTYPE).reshape(n, c)


# ------------------------------------------------------------------------------------------------ sectors


def array_to_wire(a: np.ndarray) -> dict[str, Any]:
    """An array -> {"dtype", "shape", "data"} with explicit little-endian dtype and C-order bytes (a view)."""
    a = np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("<"))
    data = memoryview(a.reshape(-1).view(np.uint8))  # msgpack packs it as bin without a copy first
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": data}


def encode_sector(msg: SectorMessage) -> bytes:
    points = np.ascontiguousarray(msg.points, dtype=POINT_DTYPE)
    if points.ndim != 2 or points.shape[1] != len(msg.fields):
        raise ValueError(f"points: shape {points.shape}; expected (N, {len(msg.fields)}) to match fields")
    body = {
        "stream_id": msg.stream_id,
        "seq": int(msg.seq),
        "sector_index": int(msg.sector_index),
        "timestamp_ns": int(msg.timestamp_ns),
        "points": array_to_wire(points),
        "fields": list(msg.fields),
        "reset": bool(msg.reset),
    }
    return msgpack.packb(body, use_bin_type=True)


def decode_sector(data: bytes, limits: Limits = Limits(), stream_id: str | None = None) -> SectorMessage:
    """Bytes -> SectorMessage, or ServiceError naming the field.

    `stream_id` (from the URL or the zenoh key) is authoritative: the body's stream_id must be absent or
    equal.
    `points` is a read-only view into `data` (no copy).
    """
    obj = _map(_unpack(data, limits), "body", SECTOR_KEYS)
    if stream_id is not None:
        stream_id = check_stream_id(stream_id, limits)
        if obj.get("stream_id", stream_id) != stream_id:
            body_id = check_stream_id(obj["stream_id"], limits)
            _fail(
                ErrorCode.INVALID_FIELD, "stream_id", f"{body_id!r} in the body but {stream_id!r} in the key"
            )
    else:
        stream_id = check_stream_id(_required(obj, "stream_id"), limits)
    reset = obj.get("reset", False)
    if not isinstance(reset, bool):
        _fail(ErrorCode.INVALID_FIELD, "reset", f"got {_kind(reset)}; expected true or false")
    fields = _fields(_required(obj, "fields"), limits)
    return SectorMessage(
        stream_id=stream_id,
        seq=_int(_required(obj, "seq"), "seq"),
        sector_index=_int(_required(obj, "sector_index"), "sector_index"),
        timestamp_ns=_int(_required(obj, "timestamp_ns"), "timestamp_ns"),
        points=_points(_required(obj, "points"), len(fields), limits),
        fields=fields,
        reset=reset,
    )


# ------------------------------------------------------------------------------------------------ replies


def encode_reply(r: DetectionsReply) -> bytes:
    body = {
        "kind": "detections",
        "stream_id": r.stream_id,
        "seq": r.seq,
        "boxes": array_to_wire(np.asarray(r.boxes, dtype=np.float32).reshape(-1, 7)),
        "scores": array_to_wire(np.asarray(r.scores, dtype=np.float32)),
        "labels": array_to_wire(np.asarray(r.labels, dtype=np.int32)),
        "class_names": list(r.class_names),
        "context_sectors": r.context_sectors,
        "gap": r.gap,
        "timings": _timings_dict(r.timings),
    }
    return msgpack.packb(body, use_bin_type=True)


def encode_error(e: ErrorReply) -> bytes:
    return msgpack.packb(error_to_json(e), use_bin_type=True)


def _timings_dict(t: Timings) -> dict[str, float]:
    return {"queue_ms": float(t.queue_ms), "model_ms": float(t.model_ms), "total_ms": float(t.total_ms)}


def _array(obj: dict[str, Any], key: str, dtype: str, shape_tail: tuple[int, ...]) -> np.ndarray:
    arr = _map(_required(obj, key), key, ARRAY_KEYS)
    if arr.get("dtype") != dtype:
        _fail(ErrorCode.INVALID_FIELD, f"{key}.dtype", f"{arr.get('dtype')!r}; expected {dtype!r}")
    shape = arr.get("shape")
    if not isinstance(shape, list) or len(shape) != 1 + len(shape_tail) or tuple(shape[1:]) != shape_tail:
        _fail(ErrorCode.INVALID_FIELD, f"{key}.shape", f"{shape!r}; expected [K, *{list(shape_tail)}]")
    k = _int(shape[0], f"{key}.shape[0]")
    data = arr.get("data")
    itemsize = np.dtype(dtype).itemsize * math.prod(shape_tail)
    if not isinstance(data, bytes) or len(data) != k * itemsize:
        _fail(ErrorCode.INVALID_FIELD, f"{key}.data", f"expected {k * itemsize} raw bytes")
    return np.frombuffer(data, dtype=dtype).reshape(k, *shape_tail)


def _decode_error(obj: dict[str, Any]) -> ErrorReply:
    code = _required(obj, "code")
    try:
        code = ErrorCode(code)
    except ValueError:
        _fail(ErrorCode.INVALID_FIELD, "code", f"{code!r}; expected one of {[c.value for c in ErrorCode]}")
    retry = obj.get("retry_after_s")
    return ErrorReply(
        code=code,
        message=str(_required(obj, "message")),
        field=obj.get("field"),
        stream_id=obj.get("stream_id"),
        seq=obj.get("seq"),
        retry_after_s=None if retry is None else float(retry),
    )


def decode_response(data: bytes, limits: Limits = Limits()) -> DetectionsReply | ErrorReply:
    """A server's reply bytes -> DetectionsReply or ErrorReply (the "kind" key tells which)."""
    obj = _unpack(data, limits, max_array_len=limits.max_points)
    if not isinstance(obj, dict):
        _fail(ErrorCode.BAD_REQUEST, "body", f"got {_kind(obj)}; expected a map")
    kind = obj.get("kind")
    if kind == "error":
        return _decode_error(obj)
    if kind != "detections":
        _fail(ErrorCode.INVALID_FIELD, "kind", f"{kind!r}; expected 'detections' or 'error'")
    boxes = _array(obj, "boxes", "<f4", (7,))
    timings = _required(obj, "timings")
    if not isinstance(timings, dict):
        _fail(ErrorCode.INVALID_FIELD, "timings", "expected a map")
    return DetectionsReply(
        stream_id=str(_required(obj, "stream_id")),
        seq=_int(_required(obj, "seq"), "seq"),
        boxes=boxes,
        scores=_array(obj, "scores", "<f4", ()),
        labels=_array(obj, "labels", "<i4", ()),
        class_names=tuple(_required(obj, "class_names")),
        context_sectors=_int(_required(obj, "context_sectors"), "context_sectors"),
        gap=_int(_required(obj, "gap"), "gap"),
        timings=Timings(
            **{k: float(_required(timings, k, "timings.")) for k in ("queue_ms", "model_ms", "total_ms")}
        ),
    )


def reply_to_json(r: DetectionsReply) -> dict[str, Any]:
    """A DetectionsReply as plain JSON-able data (for HTTP clients that send Accept: application/json)."""
    return {
        "kind": "detections",
        "stream_id": r.stream_id,
        "seq": r.seq,
        "boxes": np.asarray(r.boxes, dtype=np.float64).reshape(-1, 7).tolist(),
        "scores": np.asarray(r.scores, dtype=np.float64).tolist(),
        "labels": np.asarray(r.labels).astype(int).tolist(),
        "class_names": list(r.class_names),
        "context_sectors": r.context_sectors,
        "gap": r.gap,
        "timings": _timings_dict(r.timings),
    }


def error_to_json(e: ErrorReply) -> dict[str, Any]:
    return {
        "kind": "error",
        "code": e.code.value,
        "message": e.message,
        "field": e.field,
        "stream_id": e.stream_id,
        "seq": e.seq,
        "retry_after_s": e.retry_after_s,
    }
