"""JSON sectors over HTTP and the published OpenAPI document: a real uvicorn server on a loopback port, the
real default model, httpx as client, jsonschema checking real bodies against the published schemas."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import httpx
import jsonschema
import msgpack
import msgspec
import numpy as np
import pytest
from server_helpers import RunningServer, comparable_detector, kitti_sectors, sector_msg, serve

from contract import HTTP_STATUS, JSON, MSGPACK, DetectionsReply, ErrorReply, decode_response, encode_sector

PATH = "/v1/streams/{stream_id}/sectors"


@pytest.fixture(scope="module")
def server() -> Iterator[RunningServer]:
    with serve(comparable_detector()) as s:
        yield s


@pytest.fixture(scope="module")
def scan() -> list[np.ndarray]:
    return kitti_sectors(0, every=4)  # 6k-8k points per sector


@pytest.fixture(scope="module")
def doc(server: RunningServer) -> dict[str, Any]:
    r = httpx.get(f"{server.url}/openapi.json", timeout=30)
    assert r.status_code == 200
    return r.json()


def validator(doc: dict[str, Any], schema: dict[str, Any]) -> jsonschema.Draft202012Validator:
    """A validator of one published schema (usually a $ref into the document's components)."""
    return jsonschema.Draft202012Validator({**schema, "components": doc["components"]})


def post(url: str, stream: str, body: bytes, ctype: str, accept: str | None = None) -> httpx.Response:
    headers = {"Content-Type": ctype, **({"Accept": accept} if accept else {})}
    return httpx.post(f"{url}/v1/streams/{stream}/sectors", content=body, headers=headers, timeout=60)


def test_openapi_publishes_the_sector_route(doc):
    op = doc["paths"][PATH]["post"]
    assert set(op["requestBody"]["content"]) == {MSGPACK, JSON}
    assert set(op["responses"]["200"]["content"]) == {MSGPACK, JSON}
    assert {int(s) for s in op["responses"]} == {200, 400, 401, 403, 404, 409, 413, 422, 500, 503, 504}
    assert {int(s) for s in op["responses"]} - {200} == set(HTTP_STATUS.values())
    for status in HTTP_STATUS.values():
        for media in (MSGPACK, JSON):
            schema = op["responses"][str(status)]["content"][media]["schema"]
            assert schema == {"$ref": "#/components/schemas/WireError"}
    assert (
        "overloaded" in op["responses"]["503"]["description"]
        and "Retry-After" in op["responses"]["503"]["headers"]
    )
    schemas = doc["components"]["schemas"]
    # per media type: bin in msgpack (the sector's points, the reply's arrays), base64 in JSON
    assert schemas["WirePoints"]["properties"]["data"]["format"] == "binary"
    assert schemas["WireArray"]["properties"]["data"]["format"] == "binary"
    assert schemas["JsonPoints"]["properties"]["data"]["contentEncoding"] == "base64"
    assert (
        op["parameters"][0]["schema"]["pattern"]
        == schemas["WireSector"]["properties"]["stream_id"]["pattern"]
        == schemas["JsonSector"]["properties"]["stream_id"]["pattern"]
    )
    names = ["WireSector", "JsonSector", "WirePoints", "JsonPoints", "WireArray", "WireDetections"]
    for name in [*names, "JsonDetections", "WireError", "WireTimings"]:
        jsonschema.Draft202012Validator.check_schema(schemas[name])
    assert "/v1/model" in doc["paths"]  # FastAPI's own routes are still there


def test_json_sector_gets_the_same_boxes_as_msgpack(server, scan, doc):
    op = doc["paths"][PATH]["post"]
    body_schema = validator(doc, op["requestBody"]["content"][JSON]["schema"])
    reply_schema = validator(doc, op["responses"]["200"]["content"][JSON]["schema"])
    for seq, points in enumerate(scan[:2]):
        body = encode_sector(sector_msg("js", seq, points), JSON)
        body_schema.validate(msgspec.json.decode(body))
        with pytest.raises(jsonschema.ValidationError):  # the schema is not vacuous
            body_schema.validate({**msgspec.json.decode(body), "seq": -1})
        packed = post(server.url, "mp", encode_sector(sector_msg("mp", seq, points)), MSGPACK)
        js = post(server.url, "js", body, JSON)  # no Accept: the reply comes in the request's format
        assert packed.headers["content-type"] == MSGPACK and js.headers["content-type"] == JSON
        reply_schema.validate(js.json())
        want, got = decode_response(packed.content), decode_response(js.content, media_type=JSON)
        assert isinstance(want, DetectionsReply) and isinstance(got, DetectionsReply)
        assert (got.stream_id, got.seq, got.context_sectors) == ("js", seq, seq + 1)
        assert got.boxes.tobytes() == want.boxes.tobytes() and got.scores.tobytes() == want.scores.tobytes()
        assert got.labels.tolist() == want.labels.tolist() and got.class_names == want.class_names
        assert len(got.scores) > 0 or seq == 0, "no boxes to compare"
    packed = post(server.url, "js", encode_sector(sector_msg("js", 2, scan[2]), JSON), JSON, accept=MSGPACK)
    assert packed.headers["content-type"] == MSGPACK and len(decode_response(packed.content).scores) > 0


def bad_bodies(scan: list[np.ndarray]) -> Iterator[tuple[str, dict[str, Any], dict[str, Any]]]:
    """(expected field, msgpack body, JSON body) of the same mistake made in each format."""
    msg = sector_msg("bad", 0, scan[0][:10])
    packed, js = msgpack.unpackb(encode_sector(msg)), msgspec.json.decode(encode_sector(msg, JSON))
    for field, key, change in [
        ("seq", "seq", None),
        ("seq", "seq", -1),
        ("body", "sequence", 3),
        ("fields", "fields", "x,y,z,intensity"),
        ("points.dtype", "points", {"dtype": "<f8"}),
        ("points.data", "points", {"shape": [9, 4]}),
        ("points.data", "points", {"data": [1.0, 2.0]}),
        ("points.shape[0]", "points", {"shape": [-1, 4]}),
        ("points.shape[1]", "points", {"shape": [20, 2]}),
        ("points", "points", {"extra": 1}),
    ]:
        bodies = []
        for body in (dict(packed), dict(js)):
            if change is None:
                del body[key]
            else:
                body[key] = {**body[key], **change} if isinstance(change, dict) else change
            bodies.append(body)
        yield field, bodies[0], bodies[1]


def test_bad_json_body_gets_the_same_error_as_msgpack(server, scan, doc):
    error_schema = validator(doc, doc["paths"][PATH]["post"]["responses"]["422"]["content"][JSON]["schema"])
    for field, packed, js in bad_bodies(scan):
        r_packed = post(server.url, "bad", msgpack.packb(packed), MSGPACK)
        r_js = post(server.url, "bad", msgspec.json.encode(js), JSON)
        assert r_packed.status_code == r_js.status_code == 422, (field, r_packed.content, r_js.content)
        assert r_js.headers["content-type"] == JSON
        error_schema.validate(r_js.json())
        e_packed, e_js = decode_response(r_packed.content), decode_response(r_js.content, media_type=JSON)
        assert isinstance(e_packed, ErrorReply) and isinstance(e_js, ErrorReply)
        assert e_packed.code == e_js.code == "invalid_field", (e_packed, e_js)
        assert e_packed.field == e_js.field == field and field in e_js.message, (e_packed, e_js)
    r = post(server.url, "bad", b'{"seq": 1', JSON)
    e = decode_response(r.content, media_type=JSON)
    assert r.status_code == 400 and isinstance(e, ErrorReply) and e.field == "body" and "JSON" in e.message
    r = post(server.url, "bad", b"{}", "text/plain", accept=JSON)
    assert r.status_code == 400 and r.json()["field"] == "Content-Type" and JSON in r.json()["message"]
