"""The codec of the wire contract: sector messages and replies to msgpack or JSON bytes and back, through
typed msgspec decoders that refuse unknown keys; the `Limits` are checked after decoding; every failure is a
`ServiceError` whose message names the field."""

from __future__ import annotations

import math
from typing import Any, NoReturn

import msgspec
import numpy as np
from msgspec import UNSET, UnsetType

from contract.messages import (
    JSON,
    MSGPACK,
    MSGPACK_TYPES,
    POINT_DTYPE,
    REQUIRED_FIELDS,
    STREAM_ID_RE,
    DetectionsReply,
    ErrorReply,
    Limits,
    SectorMessage,
    ServiceError,
    Timings,
)
from contract.wire import (
    ErrorCode,
    JsonDetections,
    WireArray,
    WireDetections,
    WireError,
    WireSector,
    WireTimings,
    violation,
)

DEFAULT_LIMITS = Limits()  # frozen: one instance is every call's default
# the keys of a sector's maps, named when a body has an unknown one
_SECTOR_MAPS = {"body": WireSector.__struct_fields__, "points": WireArray.__struct_fields__}


def _numpy_scalar(obj: Any) -> Any:  # the encoders' hook: numpy scalars (np.int64, np.float32) as Python's
    if isinstance(obj, np.generic):
        return obj.item()
    raise NotImplementedError(f"cannot encode {type(obj).__name__}")


class _Format:
    """A wire format: its codec (msgspec.msgpack or msgspec.json), encoder, and typed decoders."""

    def __init__(self, name: str, codec: Any, detections: type) -> None:
        self.name, self.codec = name, codec
        self.encoder = codec.Encoder(enc_hook=_numpy_scalar)
        self.sector = codec.Decoder(WireSector)
        self.response = codec.Decoder(detections | WireError)


_MSGPACK = _Format("msgpack", msgspec.msgpack, WireDetections)
_JSON = _Format("JSON", msgspec.json, JsonDetections)  # replies in JSON: arrays as lists


def _format(media_type: str) -> _Format:
    if media_type == JSON:
        return _JSON
    if media_type in MSGPACK_TYPES:
        return _MSGPACK
    raise ValueError(f"media type {media_type!r}; expected {JSON!r} or one of {list(MSGPACK_TYPES)}")


# ------------------------------------------------------------------------------------------------ helpers


def _error(code: ErrorCode, field: str | None, message: str) -> ServiceError:
    return ServiceError(code, f"{field}: {message}" if field else message, field)


def _fail(code: ErrorCode, field: str | None, message: str) -> NoReturn:
    raise _error(code, field, message)


def _decode(fmt: _Format, decoder: Any, data: bytes, limits: Limits, maps: dict[str, tuple[str, ...]]) -> Any:
    if not isinstance(data, bytes | bytearray | memoryview):
        _fail(ErrorCode.BAD_REQUEST, "body", f"got {type(data).__name__}; expected bytes")
    if len(data) > limits.max_body_bytes:
        _fail(ErrorCode.TOO_LARGE, "body", f"{len(data)} bytes; the limit is {limits.max_body_bytes}")
    try:
        try:
            return decoder.decode(data)
        except msgspec.ValidationError as e:
            fmt.codec.decode(data, type=msgspec.Raw)  # a malformed body (trailing bytes) is told first
            raise _error(*violation(e, maps)) from None
    except msgspec.DecodeError as e:
        _fail(ErrorCode.BAD_REQUEST, "body", f"not a valid {fmt.name} message ({e})")
    except UnicodeDecodeError as e:  # msgspec raises it for a msgpack string that is not UTF-8
        _fail(ErrorCode.BAD_REQUEST, "body", f"a string is not valid UTF-8 ({e.reason} at byte {e.start})")


def _str(value: Any, field: str, limits: Limits) -> str:
    if not isinstance(value, str):
        _fail(ErrorCode.INVALID_FIELD, field, f"got {type(value).__name__}; expected a string")
    if len(value) > limits.max_string_len:
        _fail(ErrorCode.TOO_LARGE, field, f"{len(value)} characters; the limit is {limits.max_string_len}")
    return value


def check_stream_id(value: Any, limits: Limits = DEFAULT_LIMITS, field: str = "stream_id") -> str:
    """A stream ID: a non-empty string of [A-Za-z0-9_.-], at most `max_string_len` characters."""
    value = _str(value, field, limits)
    if not STREAM_ID_RE.fullmatch(value):
        _fail(ErrorCode.INVALID_FIELD, field, f"{value!r}; expected a non-empty string of [A-Za-z0-9_.-]")
    return value


def _stream_id(in_body: str | UnsetType, in_key: str | None, limits: Limits) -> str:
    if in_key is None:
        if in_body is UNSET:
            _fail(ErrorCode.INVALID_FIELD, "stream_id", "missing; it is required")
        return check_stream_id(in_body, limits)
    in_key = check_stream_id(in_key, limits)
    if in_body is not UNSET and in_body != in_key:
        body_id = check_stream_id(in_body, limits)
        _fail(ErrorCode.INVALID_FIELD, "stream_id", f"{body_id!r} in the body but {in_key!r} in the key")
    return in_key


def _fields(names: list[str], limits: Limits) -> tuple[str, ...]:
    if len(names) > limits.max_fields:
        _fail(ErrorCode.TOO_LARGE, "fields", f"{len(names)} names; the limit is {limits.max_fields}")
    fields = tuple(_str(v, f"fields[{i}]", limits) for i, v in enumerate(names))
    if fields[:4] != REQUIRED_FIELDS:
        _fail(ErrorCode.INVALID_FIELD, "fields", f"{names}; expected to start with {list(REQUIRED_FIELDS)}")
    if len(set(fields)) != len(fields) or not all(fields):
        _fail(ErrorCode.INVALID_FIELD, "fields", f"{names}; expected unique non-empty names")
    return fields


def _dtype(arr: WireArray, field: str, dtype: str) -> None:
    if arr.dtype != dtype:
        _fail(ErrorCode.INVALID_FIELD, f"{field}.dtype", f"{arr.dtype!r}; expected {dtype!r}")


def _view(arr: WireArray, field: str, shape: tuple[int, ...]) -> np.ndarray:
    """The array's bytes as a numpy view of `shape` (read-only when `data` is), after checking their size."""
    nbytes = math.prod(shape) * np.dtype(arr.dtype).itemsize
    if len(arr.data) != nbytes:
        message = f"{len(arr.data)} bytes; shape {list(shape)} needs {nbytes}"
        _fail(ErrorCode.INVALID_FIELD, f"{field}.data", message)
    return np.frombuffer(arr.data, dtype=arr.dtype).reshape(shape)


def _points(arr: WireArray, n_fields: int, limits: Limits) -> np.ndarray:  # -> (N, C) float32
    _dtype(arr, "points", POINT_DTYPE)
    if len(arr.shape) != 2:
        _fail(ErrorCode.INVALID_FIELD, "points.shape", f"{arr.shape}; expected [N, C] (two integers)")
    n, c = arr.shape
    if not 4 <= c <= limits.max_fields:
        message = f"got {c}; expected an integer in [4, {limits.max_fields}]"
        _fail(ErrorCode.INVALID_FIELD, "points.shape[1]", message)
    if c != n_fields:
        _fail(ErrorCode.INVALID_FIELD, "points.shape[1]", f"{c} columns but {n_fields} names in fields")
    if n > limits.max_points:
        _fail(ErrorCode.TOO_LARGE, "points", f"{n} points; the limit is {limits.max_points}")
    return _view(arr, "points", (n, c))


# ------------------------------------------------------------------------------------------------ sectors


def _wire_array(a: np.ndarray) -> WireArray:
    """An array with explicit little-endian dtype, its C-order bytes as a view (encoded without a copy)."""
    a = np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("<"))
    return WireArray(a.dtype.str, list(a.shape), memoryview(a.reshape(-1).view(np.uint8)))


def encode_sector(msg: SectorMessage, media_type: str = MSGPACK) -> bytes:
    points = np.ascontiguousarray(msg.points, dtype=POINT_DTYPE)
    if points.ndim != 2 or points.shape[1] != len(msg.fields):
        raise ValueError(f"points: shape {points.shape}; expected (N, {len(msg.fields)}) to match fields")
    body = WireSector(
        stream_id=msg.stream_id,
        seq=msg.seq,
        sector_index=msg.sector_index,
        timestamp_ns=msg.timestamp_ns,
        points=_wire_array(points),
        fields=list(msg.fields),
        reset=msg.reset,
        min_score=UNSET if msg.min_score is None else msg.min_score,  # absent: the server's
    )
    return _format(media_type).encoder.encode(body)


def decode_sector(
    data: bytes, limits: Limits = DEFAULT_LIMITS, stream_id: str | None = None, media_type: str = MSGPACK
) -> SectorMessage:
    """Bytes (msgpack, or JSON with `media_type=JSON`) -> SectorMessage, or ServiceError naming the field.

    `stream_id` (from the URL or the zenoh key) is authoritative: the body's stream_id must be absent or
    equal. From msgpack bytes `points` is a read-only view into `data` (no copy).
    """
    fmt = _format(media_type)
    body: WireSector = _decode(fmt, fmt.sector, data, limits, _SECTOR_MAPS)
    stream_id = _stream_id(body.stream_id, stream_id, limits)
    fields = _fields(body.fields, limits)
    return SectorMessage(
        stream_id=stream_id,
        seq=body.seq,
        sector_index=body.sector_index,
        timestamp_ns=body.timestamp_ns,
        points=_points(body.points, len(fields), limits),
        fields=fields,
        reset=body.reset,
        min_score=None if body.min_score is UNSET else body.min_score,
    )


# ------------------------------------------------------------------------------------------------ replies


def _reply_keys(r: DetectionsReply) -> dict[str, Any]:  # the keys a reply has in either format
    return dict(
        stream_id=r.stream_id,
        seq=r.seq,
        class_names=list(r.class_names),
        context_sectors=r.context_sectors,
        gap=r.gap,
        timings=WireTimings(r.timings.queue_ms, r.timings.model_ms, r.timings.total_ms),
        cold_start=r.cold_start,
        worker_id=r.worker_id,
    )


def _json_detections(r: DetectionsReply) -> JsonDetections:
    return JsonDetections(
        boxes=np.asarray(r.boxes, dtype=np.float64).reshape(-1, 7).tolist(),
        scores=np.asarray(r.scores, dtype=np.float64).tolist(),
        labels=np.asarray(r.labels).astype(int).tolist(),
        **_reply_keys(r),
    )


def _wire_detections(r: DetectionsReply) -> WireDetections:
    return WireDetections(
        boxes=_wire_array(np.asarray(r.boxes, dtype=np.float32).reshape(-1, 7)),
        scores=_wire_array(np.asarray(r.scores, dtype=np.float32)),
        labels=_wire_array(np.asarray(r.labels, dtype=np.int32)),
        **_reply_keys(r),
    )


def encode_reply(r: DetectionsReply, media_type: str = MSGPACK) -> bytes:
    """A reply as msgpack (arrays as raw bytes) or, with `media_type=JSON`, as JSON (arrays as lists)."""
    fmt = _format(media_type)
    return fmt.encoder.encode(_json_detections(r) if fmt is _JSON else _wire_detections(r))


def _wire_error(e: ErrorReply) -> WireError:
    return WireError(e.code, e.message, e.field, e.stream_id, e.seq, e.retry_after_s)


def encode_error(e: ErrorReply, media_type: str = MSGPACK) -> bytes:
    return _format(media_type).encoder.encode(_wire_error(e))


def _reply_array(arr: WireArray, field: str, dtype: str, tail: tuple[int, ...]) -> np.ndarray:  # (K, *tail)
    _dtype(arr, field, dtype)
    if len(arr.shape) != 1 + len(tail) or tuple(arr.shape[1:]) != tail:
        _fail(ErrorCode.INVALID_FIELD, f"{field}.shape", f"{arr.shape}; expected [K, *{list(tail)}]")
    return _view(arr, field, tuple(arr.shape))


def decode_response(
    data: bytes, limits: Limits = DEFAULT_LIMITS, media_type: str = MSGPACK
) -> DetectionsReply | ErrorReply:
    """A server's reply bytes -> DetectionsReply or ErrorReply (the "kind" key tells which)."""
    fmt = _format(media_type)
    reply: WireDetections | JsonDetections | WireError = _decode(fmt, fmt.response, data, limits, {})
    if isinstance(reply, WireError):
        return ErrorReply(
            reply.code, reply.message, reply.field, reply.stream_id, reply.seq, reply.retry_after_s
        )
    if isinstance(reply, JsonDetections):
        boxes = np.asarray(reply.boxes, dtype=np.float32).reshape(-1, 7)  # (K, 7)
        scores, labels = np.asarray(reply.scores, np.float32), np.asarray(reply.labels, np.int32)  # (K,)
    else:
        boxes = _reply_array(reply.boxes, "boxes", "<f4", (7,))
        scores = _reply_array(reply.scores, "scores", "<f4", ())
        labels = _reply_array(reply.labels, "labels", "<i4", ())
    return DetectionsReply(
        stream_id=reply.stream_id,
        seq=reply.seq,
        boxes=boxes,
        scores=scores,
        labels=labels,
        class_names=tuple(reply.class_names),
        context_sectors=reply.context_sectors,
        gap=reply.gap,
        timings=Timings(reply.timings.queue_ms, reply.timings.model_ms, reply.timings.total_ms),
        cold_start=reply.cold_start,
        worker_id=reply.worker_id,
    )


def reply_to_json(r: DetectionsReply) -> dict[str, Any]:
    """A DetectionsReply as plain JSON-able data (what HTTP clients get with Accept: application/json)."""
    return msgspec.to_builtins(_json_detections(r))


def error_to_json(e: ErrorReply) -> dict[str, Any]:
    return msgspec.to_builtins(_wire_error(e))
