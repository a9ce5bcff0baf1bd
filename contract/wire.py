"""The messages as they travel: msgspec Structs, the one schema that the decoders enforce and the HTTP app
publishes in its OpenAPI document; and how a message that breaks it is told. Import from `contract`.

Requests refuse unknown keys; replies may gain keys in later versions, so a client ignores the ones it does
not know (as before the schema library).

Arrays are `WireArray` maps whose `data` is raw bytes: msgpack bin, base64 in JSON.
"""

from __future__ import annotations

import enum
import re
from typing import Annotated

from msgspec import UNSET, Meta, Struct, UnsetType, ValidationError

INT64_MAX = 2**63 - 1
STREAM_ID_PATTERN = "^[A-Za-z0-9_.-]+$"
MAX_LIST_LEN = 1024  # the schema's own ceiling on `fields` (the server's max_fields is lower)
# a server's min_score unless it is set otherwise (`phim serve --min-score`; GET /v1/model says what it is):
# the shipped default model's best vehicle F1, real samples and simulated scans together (docs/model-card.md)
DEFAULT_MIN_SCORE = 0.4


class ErrorCode(enum.StrEnum):
    """An error's stable code; its HTTP status is `HTTP_STATUS[code]` (docs/protocol.md, "An error")."""

    BAD_REQUEST = "bad_request"  # undecodable body                      HTTP 400
    TOO_LARGE = "too_large"  # body / points / strings over limit         HTTP 413
    INVALID_FIELD = "invalid_field"  # a field has a wrong type/value     HTTP 422
    STALE_SEQUENCE = "stale_sequence"  # seq <= last seq of the stream    HTTP 409
    UNKNOWN_STREAM = "unknown_stream"  #                                  HTTP 404
    UNAUTHORIZED = "unauthorized"  # no or unknown bearer token            HTTP 401
    FORBIDDEN = "forbidden"  # the token's prefix does not cover the stream HTTP 403
    OVERLOADED = "overloaded"  # queue full / stream table full           HTTP 503 + Retry-After
    NOT_READY = "not_ready"  # warming up / shutting down                 HTTP 503
    DEADLINE_EXCEEDED = "deadline_exceeded"  # waited past its deadline   HTTP 504
    INTERNAL = "internal"  # model failure for this batch                 HTTP 500


Count = Annotated[int, Meta(ge=0, le=INT64_MAX)]
Label = Annotated[int, Meta(ge=0, le=2**31 - 1)]  # int32
StreamId = Annotated[str, Meta(pattern=STREAM_ID_PATTERN, description="at most max_string_len characters")]
Bytes = Annotated[memoryview, Meta(description="raw little-endian C-order bytes: msgpack bin; JSON base64")]
ContextSectors = Annotated[Count, Meta(description="sectors the prediction saw (new and buffered)")]
Gap = Annotated[Count, Meta(description="sectors missed since the stream's last processed seq")]
ColdStart = Annotated[
    bool,
    Meta(
        description="the sector ran on a fresh stream state: the stream's first on this worker (new, or "
        "after it was ended, evicted or lost in a restart), or a reset; no earlier context"
    ),
]
WorkerId = Annotated[str, Meta(description="the ID of the worker that ran the sector")]
MinScore = Annotated[
    float,
    Meta(
        ge=0.0,
        le=1.0,
        description="the reply keeps the boxes scored at least this (0: every box); absent: the server's "
        "min_score (GET /v1/model)",
    ),
]
BOXES = "x, y, z (box centre), l, w, h (metres), yaw (radians), sensor frame"


class WireTimings(Struct):
    """Where the sector's time went in the server (ms): waiting for the device loop, its forward, in all."""

    queue_ms: float
    model_ms: float
    total_ms: float


class WireError(Struct, tag_field="kind", tag="error"):
    """A request's failure."""

    code: ErrorCode
    message: Annotated[str, Meta(description="'<field>: <what was wrong>; expected <what>'")]
    field: Annotated[str | None, Meta(description="the key at fault: seq, points.shape[1], body")] = None
    stream_id: str | None = None
    seq: Annotated[int | None, Meta(description="null when the sector could not be decoded")] = None
    retry_after_s: Annotated[float | None, Meta(description="with overloaded: when to retry")] = None


class WireArray(Struct, forbid_unknown_fields=True):
    """An array: numpy dtype with explicit byte order ("<f4" float32, "<i4" int32), shape, raw bytes."""

    dtype: str
    shape: Annotated[list[Count], Meta(max_length=8)]
    data: Bytes


class WireSector(Struct, forbid_unknown_fields=True, kw_only=True):
    """One sector of a stream's points (client -> server)."""

    stream_id: StreamId | UnsetType = UNSET  # may be left out when the URL or the zenoh key names the stream
    seq: Annotated[Count, Meta(description="greater than every seq the stream sent before")]
    sector_index: Annotated[Count, Meta(description="azimuth sector in the turn: 0 .. sectors_per_turn - 1")]
    timestamp_ns: Annotated[Count, Meta(description="sensor time of the sector")]
    points: Annotated[WireArray, Meta(description='"<f4" [N, C]')]
    fields: Annotated[list[str], Meta(max_length=MAX_LIST_LEN, description="C names: x, y, z, intensity...")]
    reset: Annotated[bool, Meta(description="start the stream over (fresh state; seq may restart)")] = False
    min_score: MinScore | UnsetType = UNSET  # absent: the server's min_score (GET /v1/model)


class WireDetections(Struct, tag_field="kind", tag="detections"):
    """A sector's detections (msgpack)."""

    stream_id: str
    seq: Count
    boxes: Annotated[WireArray, Meta(description=f'"<f4" [K, 7]: {BOXES}')]
    scores: Annotated[WireArray, Meta(description='"<f4" [K]')]
    labels: Annotated[WireArray, Meta(description='"<i4" [K]: index into the model\'s classes')]
    class_names: list[str]
    context_sectors: ContextSectors
    gap: Gap
    timings: WireTimings
    cold_start: ColdStart = False
    worker_id: WorkerId = ""


class JsonDetections(Struct, tag_field="kind", tag="detections"):
    """A sector's detections in JSON: as WireDetections, with the arrays as lists."""

    stream_id: str
    seq: Count
    boxes: Annotated[list[Annotated[list[float], Meta(min_length=7, max_length=7)]], Meta(description=BOXES)]
    scores: list[float]
    labels: list[Label]
    class_names: list[str]
    context_sectors: ContextSectors
    gap: Gap
    timings: WireTimings
    cold_start: ColdStart = False
    worker_id: WorkerId = ""


# ------------------------------------------------------------------------------ a message that breaks it

_NOUNS = {  # msgspec's type names in its messages, as said in ours
    "object": "a map",
    "array": "an array",
    "str": "a string",
    "int": "an integer",
    "float": "a number",
    "bool": "true or false",
    "bytes": "binary (msgpack bin; base64 in JSON)",
    "ext": "a msgpack extension type (not allowed)",
}
_TYPE = re.compile(r"Expected `(.+)`, got `(.+)`")
_CONSTRAINT = re.compile(r"Expected `(\w+)`( .+)")  # "Expected `int` >= 0", "... of length <= 1024"
_MISSING = re.compile(r"Object missing required field `(.+)`")
_UNKNOWN = re.compile(r"Object contains unknown field `(.+)`")


def violation(e: ValidationError, maps: dict[str, tuple[str, ...]]) -> tuple[ErrorCode, str, str]:
    """msgspec's "<what> - at `$.points.shape[0]`" -> (code, the field "points.shape[0]", what was wrong);
    `maps`: the keys each map (by field) may have, named when a key is unknown."""
    text, _, where = str(e).partition(" - at `")
    in_key = where.startswith("key` in `")  # a map key that is not a string (msgpack)
    path = where.removeprefix("key` in `").removesuffix("`").removeprefix("$").removeprefix(".")
    field = path or "body"
    if in_key:
        return ErrorCode.BAD_REQUEST, field, f"map keys must be strings ({text})"
    if m := _MISSING.fullmatch(text):
        return ErrorCode.INVALID_FIELD, f"{path}.{m[1]}" if path else m[1], "missing; it is required"
    if m := _UNKNOWN.fullmatch(text):
        expected = f"; expected only {list(maps[field])}" if field in maps else ""
        return ErrorCode.INVALID_FIELD, field, f"unknown keys [{m[1]!r}]{expected}"
    if m := _TYPE.fullmatch(text):
        code = ErrorCode.BAD_REQUEST if m[2] == "ext" else ErrorCode.INVALID_FIELD
        return code, field, f"got {_NOUNS.get(m[2], m[2])}; expected {_NOUNS.get(m[1], m[1])}"
    if m := _CONSTRAINT.fullmatch(text):
        code = ErrorCode.TOO_LARGE if m[2].startswith(" of length <=") else ErrorCode.INVALID_FIELD
        return code, field, f"expected {_NOUNS.get(m[1], m[1])}{m[2]}"
    return ErrorCode.INVALID_FIELD, field, text  # e.g. "Invalid base64 encoded string"
