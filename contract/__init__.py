"""The wire contract between the server and its clients, owned by neither: sectors in, detections or errors
out (msgpack, or JSON over HTTP), the limits, the error codes, the zenoh key space, the point fields and the
media types.

The messages are msgspec Structs (contract/wire.py), decoded by typed decoders that refuse unknown keys; the
server's `Limits` are checked after decoding. Arrays travel as maps {"dtype": "<f4", "shape": [N, C],
"data": <raw little-endian bytes>}: msgpack bin (base64 in JSON), never pickle, never lists of floats in
msgpack, never msgpack extension types. Every failure is a `ServiceError` whose message names the field
and says what was expected. numpy + msgspec only (no torch): a client needs nothing else. See
docs/protocol.md.

The package's modules: `messages` (the decoded messages, limits, errors, point fields, media types),
`codec` (them to bytes and back), `wire` (the Structs and error codes), `keys` (the zenoh key space),
`placement` (which worker owns a stream), `ros2` (the ROS 2 wire facts: rmw_zenoh's key expressions and
message formats). Everything a caller needs is importable from `contract` itself.
"""

from contract.codec import (
    DEFAULT_LIMITS,
    check_stream_id,
    decode_response,
    decode_sector,
    encode_error,
    encode_reply,
    encode_sector,
    error_to_json,
    reply_to_json,
)
from contract.keys import (
    DEFAULT_HTTP_PORT,
    DEFAULT_KEY_PREFIX,
    DEFAULT_URL,
    DEFAULT_ZENOH_ENDPOINT,
    PROBE_CHUNK,
    KeySpace,
)
from contract.messages import (
    HTTP_STATUS,
    JSON,
    MAX_COORDINATE_M,
    MSGPACK,
    MSGPACK_TYPES,
    POINT_DTYPE,
    POINT_FIELDS,
    REQUIRED_FIELDS,
    STREAM_ID_RE,
    DetectionsReply,
    ErrorReply,
    Limits,
    SectorMessage,
    ServiceError,
    Timings,
)
from contract.placement import stream_owner
from contract.wire import (
    DEFAULT_MIN_SCORE,
    INT64_MAX,
    MAX_LIST_LEN,
    STREAM_ID_PATTERN,
    ErrorCode,
    JsonDetections,
    WireArray,
    WireDetections,
    WireError,
    WireSector,
    WireTimings,
)

__all__ = [
    "DEFAULT_HTTP_PORT",
    "DEFAULT_KEY_PREFIX",
    "DEFAULT_LIMITS",
    "DEFAULT_MIN_SCORE",
    "DEFAULT_URL",
    "DEFAULT_ZENOH_ENDPOINT",
    "HTTP_STATUS",
    "INT64_MAX",
    "JSON",
    "MAX_COORDINATE_M",
    "MAX_LIST_LEN",
    "MSGPACK",
    "MSGPACK_TYPES",
    "POINT_DTYPE",
    "POINT_FIELDS",
    "PROBE_CHUNK",
    "REQUIRED_FIELDS",
    "STREAM_ID_PATTERN",
    "STREAM_ID_RE",
    "DetectionsReply",
    "ErrorCode",
    "ErrorReply",
    "JsonDetections",
    "KeySpace",
    "Limits",
    "SectorMessage",
    "ServiceError",
    "Timings",
    "WireArray",
    "WireDetections",
    "WireError",
    "WireSector",
    "WireTimings",
    "check_stream_id",
    "decode_response",
    "decode_sector",
    "encode_error",
    "encode_reply",
    "encode_sector",
    "error_to_json",
    "reply_to_json",
    "stream_owner",
]
