"""The wire protocol: round trips, and a clear error naming the field for every kind of bad message."""

from __future__ import annotations

import json
import subprocess
import sys

import msgpack
import msgspec
import numpy as np
import pytest

from contract import (
    HTTP_STATUS,
    JSON,
    MAX_LIST_LEN,
    DetectionsReply,
    ErrorCode,
    ErrorReply,
    Limits,
    SectorMessage,
    ServiceError,
    Timings,
    decode_response,
    decode_sector,
    encode_error,
    encode_reply,
    encode_sector,
    error_to_json,
    reply_to_json,
)

FIELDS = ("x", "y", "z", "intensity")


def sector(n: int = 50, c: int = 4, **kw) -> SectorMessage:
    rng = np.random.default_rng(0)
    args = dict(stream_id="car-1", seq=7, sector_index=2, timestamp_ns=1_700_000_000_000_000_000)
    args.update(kw)
    fields = (*FIELDS, "elongation") if c == 5 else FIELDS
    return SectorMessage(points=rng.normal(size=(n, c)).astype(np.float32), fields=fields, **args)


def raw(msg: SectorMessage) -> dict:
    return msgpack.unpackb(encode_sector(msg), raw=False)


def pack(obj) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


DEFAULT_LIMITS = Limits()


def expect(
    code: ErrorCode, field: str | None, data: bytes, limits: Limits = DEFAULT_LIMITS, **kw
) -> ServiceError:
    with pytest.raises(ServiceError) as info:
        decode_sector(data, limits, **kw)
    e = info.value
    assert e.code == code, e
    assert e.field == field, e
    if field is not None:
        assert field in e.message
    return e


def test_sector_round_trip_is_bit_exact():
    msg = sector(c=5, reset=True)
    out = decode_sector(encode_sector(msg))
    assert (out.stream_id, out.seq, out.sector_index, out.timestamp_ns) == ("car-1", 7, 2, msg.timestamp_ns)
    assert out.fields == (*FIELDS, "elongation") and out.reset is True
    assert out.points.dtype == np.dtype("<f4") and out.points.shape == (50, 5)
    assert out.points.tobytes() == msg.points.tobytes()
    assert raw(msg)["points"]["dtype"] == "<f4"  # raw bytes on the wire, never a list of floats
    assert isinstance(raw(msg)["points"]["data"], bytes)


def test_json_sector_round_trip_carries_the_bytes_as_base64():
    msg = sector(c=5, reset=True)
    body = encode_sector(msg, JSON)
    assert isinstance(json.loads(body)["points"]["data"], str)
    out = decode_sector(body, media_type=JSON)
    assert (out.stream_id, out.seq, out.fields, out.reset) == ("car-1", 7, msg.fields, True)
    assert out.points.dtype == np.dtype("<f4") and out.points.tobytes() == msg.points.tobytes()


def test_msgpack_points_are_a_read_only_view_of_the_body():
    data = encode_sector(sector())
    points = decode_sector(data).points
    assert np.shares_memory(points, np.frombuffer(data, np.uint8)) and not points.flags.writeable


def test_numpy_scalars_are_encoded_as_numbers():
    msg = sector(seq=np.int64(9), sector_index=np.uint8(3), reset=np.bool_(True))
    out = decode_sector(encode_sector(msg))
    assert (out.seq, out.sector_index, out.reset) == (9, 3, True)
    with pytest.raises(ValueError, match="media type"):
        encode_sector(msg, "text/csv")


def test_key_stream_id_is_authoritative():
    body = raw(sector())
    del body["stream_id"]
    assert decode_sector(pack(body), stream_id="truck.7").stream_id == "truck.7"
    e = expect(ErrorCode.INVALID_FIELD, "stream_id", encode_sector(sector()), stream_id="car-2")
    assert "'car-1' in the body but 'car-2'" in e.message


def test_empty_sector_is_valid():
    assert decode_sector(encode_sector(sector(n=0))).points.shape == (0, 4)


@pytest.mark.parametrize("data", [b"garbage", b"\xc1", b"", pack({"a": 1}) + b"x"])
def test_undecodable_bytes(data: bytes):
    expect(ErrorCode.BAD_REQUEST, "body", data)


def test_extension_types_and_non_string_keys_are_rejected():
    e = expect(ErrorCode.BAD_REQUEST, "body", pack(msgpack.ExtType(1, b"obj")))
    assert "extension type" in e.message
    expect(ErrorCode.BAD_REQUEST, "body", pack({1: 2}))
    e = expect(ErrorCode.BAD_REQUEST, "seq", pack({**raw(sector()), "seq": msgpack.ExtType(1, b"7")}))
    assert "extension type" in e.message


@pytest.mark.parametrize("data", [b"{", b'{"seq": 1} x', b"\xff"])
def test_undecodable_json(data: bytes):
    e = expect(ErrorCode.BAD_REQUEST, "body", data, media_type=JSON)
    assert "JSON" in e.message


@pytest.mark.parametrize("missing", ["seq", "sector_index", "timestamp_ns", "points", "fields", "stream_id"])
def test_missing_field(missing: str):
    body = raw(sector())
    del body[missing]
    e = expect(ErrorCode.INVALID_FIELD, missing, pack(body))
    assert "missing" in e.message


def test_not_a_map_and_unknown_keys():
    expect(ErrorCode.INVALID_FIELD, "body", pack([1, 2, 3]))
    e = expect(ErrorCode.INVALID_FIELD, "body", pack({**raw(sector()), "sequence": 3}))
    assert "sequence" in e.message


SCALAR_CASES = [
    ("seq", -1, "seq"),
    ("seq", "3", "seq"),
    ("seq", True, "seq"),
    ("seq", 2**64 - 1, "seq"),
    ("sector_index", 1.5, "sector_index"),
    ("timestamp_ns", None, "timestamp_ns"),
    ("reset", 1, "reset"),
    ("stream_id", "", "stream_id"),
    ("stream_id", "car 1", "stream_id"),
    ("stream_id", "car/1", "stream_id"),
    ("stream_id", 5, "stream_id"),
    ("fields", ["x", "y", "z"], "fields"),
    ("fields", ["y", "x", "z", "intensity"], "fields"),
    ("fields", "x,y,z,intensity", "fields"),
    ("fields", ["x", "y", "z", 3], "fields[3]"),
]


@pytest.mark.parametrize(("key", "value", "field"), SCALAR_CASES)
def test_invalid_scalar_fields(key: str, value, field: str):
    expect(ErrorCode.INVALID_FIELD, field, pack({**raw(sector()), key: value}))


@pytest.mark.parametrize(("key", "value", "field"), SCALAR_CASES)
def test_json_bodies_get_the_same_errors(key: str, value, field: str):
    expect(
        ErrorCode.INVALID_FIELD, field, msgspec.json.encode({**raw(sector()), key: value}), media_type=JSON
    )


def test_duplicate_field_names():
    msg = sector(c=5)
    body = {**raw(msg), "fields": [*FIELDS, "x"]}
    expect(ErrorCode.INVALID_FIELD, "fields", pack(body))


POINT_CASES = [
    ({"dtype": "<f8"}, "points.dtype", "'<f4'"),
    ({"dtype": ">f4"}, "points.dtype", "'<f4'"),
    ({"shape": [50]}, "points.shape", "[N, C]"),
    ({"shape": [49, 4]}, "points.data", "needs 784"),  # shape does not match the bytes
    ({"shape": [50, 5]}, "points.shape[1]", "5 columns but 4 names"),
    ({"shape": [100, 2]}, "points.shape[1]", "[4, 16]"),
    ({"data": [1.0, 2.0]}, "points.data", "expected binary"),
    ({"extra": 1}, "points", "unknown keys"),
]


@pytest.mark.parametrize(("change", "field", "needle"), POINT_CASES)
def test_invalid_points(change: dict, field: str, needle: str):
    body = raw(sector())
    body["points"] = {**body["points"], **change}
    e = expect(ErrorCode.INVALID_FIELD, field, pack(body))
    assert needle in e.message


@pytest.mark.parametrize(("change", "field", "needle"), POINT_CASES)
def test_invalid_json_points(change: dict, field: str, needle: str):
    body = raw(sector())  # msgspec.json writes its bytes as base64
    body["points"] = {**body["points"], **change}
    e = expect(ErrorCode.INVALID_FIELD, field, msgspec.json.encode(body), media_type=JSON)
    assert needle in e.message


def test_json_data_must_be_base64():
    body = json.loads(encode_sector(sector(), JSON))
    body["points"]["data"] = "not base64!"
    expect(ErrorCode.INVALID_FIELD, "points.data", json.dumps(body).encode(), media_type=JSON)


def test_limits_give_too_large_naming_the_field():
    limits = Limits(max_body_bytes=4096, max_points=100, max_string_len=16, max_fields=5)
    expect(ErrorCode.TOO_LARGE, "points", encode_sector(sector(n=101)), Limits(max_points=100))
    expect(ErrorCode.TOO_LARGE, "body", encode_sector(sector(n=1000)), limits)
    e = expect(ErrorCode.TOO_LARGE, "stream_id", encode_sector(sector(stream_id="a" * 17)), limits)
    assert "17 characters; the limit is 16" in e.message
    body = {**raw(sector()), "fields": [*FIELDS, "a", "b"]}
    expect(ErrorCode.TOO_LARGE, "fields", pack(body), limits)
    expect(ErrorCode.TOO_LARGE, "stream_id", encode_sector(sector()), limits, stream_id="k" * 17)
    body = {**raw(sector()), "fields": ["a"] * (MAX_LIST_LEN + 1)}  # the schema's own ceiling
    expect(ErrorCode.TOO_LARGE, "fields", pack(body), Limits(max_fields=10_000))


def reply(k: int = 3) -> DetectionsReply:
    rng = np.random.default_rng(1)
    return DetectionsReply(
        stream_id="car-1",
        seq=4,
        boxes=rng.normal(size=(k, 7)).astype(np.float32),
        scores=rng.random(k).astype(np.float32),
        labels=np.arange(k, dtype=np.int32) % 3,
        class_names=tuple(["VEHICLE", "PEDESTRIAN", "CYCLIST"][i % 3] for i in range(k)),
        context_sectors=4,
        gap=2,
        timings=Timings(0.5, 30.0, 31.0),
        cold_start=True,
        worker_id="gpu-7",
    )


@pytest.mark.parametrize("k", [0, 3])
def test_reply_round_trip(k: int):
    r = reply(k)
    out = decode_response(encode_reply(r))
    assert isinstance(out, DetectionsReply)
    assert out.boxes.tobytes() == r.boxes.tobytes() and out.boxes.shape == (k, 7)
    assert out.scores.tobytes() == r.scores.tobytes()
    assert out.labels.dtype == np.dtype("<i4") and out.labels.tolist() == r.labels.tolist()
    assert (out.class_names, out.context_sectors, out.gap, out.timings) == (r.class_names, 4, 2, r.timings)
    assert (out.cold_start, out.worker_id) == (True, "gpu-7")
    js = reply_to_json(r)
    assert js["kind"] == "detections" and len(js["boxes"]) == k and js["timings"]["model_ms"] == 30.0
    assert json.loads(encode_reply(r, JSON)) == js
    out = decode_response(encode_reply(r, JSON), media_type=JSON)
    assert isinstance(out, DetectionsReply) and out.boxes.shape == (k, 7) and out.labels.dtype == np.int32
    assert out.boxes.tobytes() == r.boxes.tobytes() and out.scores.tobytes() == r.scores.tobytes()
    assert (out.class_names, out.timings, out.cold_start, out.worker_id) == (
        r.class_names,
        r.timings,
        True,
        "gpu-7",
    )


def test_bad_reply_names_the_field():
    body = msgpack.unpackb(encode_reply(reply()))
    with pytest.raises(ServiceError, match=r"boxes\.shape") as info:
        decode_response(pack({**body, "boxes": {**body["boxes"], "shape": [3, 6]}}))
    assert info.value.field == "boxes.shape"
    with pytest.raises(ServiceError, match="kind") as info:
        decode_response(pack({**body, "kind": "other"}))
    assert info.value.field == "kind"


def test_error_round_trip_and_http_status():
    e = ErrorReply(ErrorCode.OVERLOADED, "queue full", None, "car-1", 9, retry_after_s=0.25)
    assert decode_response(encode_error(e)) == e
    assert error_to_json(e)["code"] == "overloaded"
    assert decode_response(encode_error(e, JSON), media_type=JSON) == e
    assert json.loads(encode_error(e, JSON)) == error_to_json(e) and error_to_json(e)["kind"] == "error"
    assert set(HTTP_STATUS) == set(ErrorCode)
    assert HTTP_STATUS[ErrorCode.STALE_SEQUENCE] == 409 and HTTP_STATUS[ErrorCode.DEADLINE_EXCEEDED] == 504


def test_protocol_needs_no_torch():
    code = "import sys, contract; assert 'torch' not in sys.modules, 'the contract imported torch'"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_a_reply_with_keys_a_later_server_adds_still_decodes():
    """Requests refuse unknown keys; replies may grow, and a client ignores what it does not know."""
    sent = reply()
    body = msgpack.unpackb(encode_reply(sent), raw=False)
    body["new_key"], body["timings"]["new_ms"] = 1, 2.0
    decoded = decode_response(pack(body))
    assert isinstance(decoded, DetectionsReply) and decoded.seq == sent.seq and len(decoded.scores) == 3
    full = ErrorReply(ErrorCode.OVERLOADED, "full")
    assert decode_response(pack({**msgpack.unpackb(encode_error(full), raw=False), "hint": "x"})) == full
