"""The sector route in the OpenAPI document: it is a plain Starlette route (server/app.py: FastAPI's
parameter handling cost about 0.15 ms per sector), which FastAPI leaves out of GET /openapi.json.

The schemas are the contract's msgspec Structs (`msgspec.json.schema_components`), made exact per media
type: an array's `data` is binary in msgpack (`WirePoints`, `WireArray`) and a base64 string in JSON
(`JsonPoints`), so the request body has one schema per media type (`WireSector`, `JsonSector`). What the
Structs cannot say and the decoder checks (`contract.decode_sector` with the server's `Limits`) is written in:
the `fields` rule, the points' dtype and shape, a body `stream_id` equal to the path's, and which azimuths a
sector index covers."""

from __future__ import annotations

import copy
from typing import Any

import msgspec
from fastapi import FastAPI

from contract import (
    HTTP_STATUS,
    JSON,
    MSGPACK,
    POINT_DTYPE,
    REQUIRED_FIELDS,
    ErrorCode,
    JsonDetections,
    Limits,
    WireDetections,
    WireError,
    WireSector,
)

REF_TEMPLATE = "#/components/schemas/{name}"
Schema = dict[str, Any]  # a JSON Schema or a piece of the OpenAPI document
DEFAULT_LIMITS = Limits()
WIRE_ERROR: Schema = {"$ref": REF_TEMPLATE.format(name="WireError")}

STREAM_ID_RULE = (
    "The stream: 1..{n} characters of [A-Za-z0-9_.-]. In a body it may be left out; where present it must "
    "equal the path's stream_id (else 422 invalid_field, field stream_id)."
)
SECTOR_INDEX_RULE = (
    "Azimuth sector in the turn: 0 .. S - 1, S = sectors_per_turn of GET /v1/model. Sector i holds the "
    "points whose azimuth atan2(y, x) (sensor frame: x forward, y left) lies in [-180 + 360 i / S, "
    "-180 + 360 (i + 1) / S) degrees: with S = 4, sector 0 is [-180, -90), 1 is [-90, 0), 2 is [0, 90), "
    "3 is [90, 180)."
)
FIELDS_RULE = (
    "The names of the C point columns: unique, non-empty, starting with x, y, z, intensity (then e.g. "
    "elongation); 4..{n} names, as many as points.shape[1]."
)
BINARY = "raw little-endian C-order bytes, as msgpack bin (not a string)"
BASE64 = "raw little-endian C-order bytes, base64 (RFC 4648, with padding)"


def publish_sector_route(app: FastAPI, path: str, limits: Limits = DEFAULT_LIMITS) -> None:
    """Puts the sector route (a plain Starlette route, which FastAPI leaves out) in GET /openapi.json, with
    schemas generated from the contract's msgspec Structs: once, when the document is first asked for."""
    fastapi_openapi = app.openapi

    def openapi() -> dict[str, Any]:
        doc = app.openapi_schema
        if doc is None:
            doc = fastapi_openapi()  # FastAPI's document, kept in app.openapi_schema (and so is what we add)
            _, schemas = msgspec.json.schema_components(
                [WireSector, WireDetections, JsonDetections, WireError], ref_template=REF_TEMPLATE
            )
            schemas = exact_schemas(schemas, limits)
            doc.setdefault("components", {}).setdefault("schemas", {}).update(schemas)
            stream_id = {**schemas["WireSector"]["properties"]["stream_id"]}
            stream_id["description"] = f"the stream: 1..{limits.max_string_len} characters of [A-Za-z0-9_.-]"
            doc["paths"][path] = {"post": _sector_operation(stream_id)}
            for operation in (op for ops in doc["paths"].values() for op in ops.values()):
                for param in operation.get("parameters", []):
                    if param["name"] == "stream_id":  # FastAPI's says "a string"; the contract's, which
                        param["schema"] = stream_id  # the routes check
        return doc

    app.openapi = openapi  # type: ignore[method-assign]


def _ref(name: str) -> Schema:
    return {"$ref": REF_TEMPLATE.format(name=name)}


def exact_schemas(schemas: dict[str, Schema], limits: Limits) -> dict[str, Schema]:
    """The Structs' schemas made exact per media type: binary `data` in msgpack (WireArray, WirePoints,
    WireSector), base64 in JSON (JsonPoints, JsonSector), with the rules the decoder checks written in."""
    out = copy.deepcopy(schemas)
    array = out["WireArray"]
    array["properties"]["data"] = {"type": "string", "format": "binary", "description": BINARY}
    sector = out["WireSector"]
    props = sector["properties"]
    props["stream_id"]["description"] = STREAM_ID_RULE.format(n=limits.max_string_len)
    props["stream_id"].update(minLength=1, maxLength=limits.max_string_len)
    props["sector_index"]["description"] = SECTOR_INDEX_RULE
    props["fields"] = {
        "description": FIELDS_RULE.format(n=limits.max_fields),
        "type": "array",
        "prefixItems": [{"const": name} for name in REQUIRED_FIELDS],
        "items": {"type": "string", "minLength": 1, "maxLength": limits.max_string_len},
        "minItems": len(REQUIRED_FIELDS),
        "maxItems": limits.max_fields,
        "uniqueItems": True,
    }
    sector["description"] = (
        f"{sector.get('description', '')} The msgpack body: points.data is bin. {STREAM_ID_RULE}"
    ).format(n=limits.max_string_len)
    out["WirePoints"] = _points(array, limits, "WirePoints")
    out["JsonPoints"] = _points(array, limits, "JsonPoints")
    out["JsonPoints"]["properties"]["data"] = {
        "type": "string",
        "contentEncoding": "base64",
        "description": BASE64,
    }
    props["points"] = {"description": props["points"].get("description", ""), **_ref("WirePoints")}
    json_sector = copy.deepcopy(sector)
    json_sector["title"] = "JsonSector"
    json_sector["description"] = sector["description"].replace(
        "msgpack body: points.data is bin", "JSON body: points.data is base64"
    )
    json_sector["properties"]["points"] = {**props["points"], **_ref("JsonPoints")}
    out["JsonSector"] = json_sector
    return out


def _points(array: Schema, limits: Limits, title: str) -> Schema:
    """A sector's points: a WireArray of dtype "<f4", shape [N, C], N <= max_points, 4 <= C <= max_fields."""
    points = copy.deepcopy(array)
    points["title"] = title
    points["description"] = (
        f'The sector\'s points: dtype "{POINT_DTYPE}", shape [N, C], N * C * 4 bytes of data.'
    )
    points["properties"]["dtype"] = {"const": POINT_DTYPE, "description": "float32, little-endian"}
    points["properties"]["shape"] = {
        "description": "[N, C]: N points (at most the server's max_points), C columns (as many as fields)",
        "type": "array",
        "prefixItems": [
            {"type": "integer", "minimum": 0, "maximum": limits.max_points},
            {"type": "integer", "minimum": len(REQUIRED_FIELDS), "maximum": limits.max_fields},
        ],
        "items": {"type": "integer", "minimum": 0},
        "minItems": 2,
        "maxItems": 2,
    }
    return points


def error_responses(codes: list[ErrorCode], error: Schema = WIRE_ERROR) -> dict[str, Schema]:
    """The OpenAPI responses of the errors a route may answer: a WireError (JSON or msgpack) per status."""
    by_status: dict[int, list[str]] = {}
    for code in codes:
        by_status.setdefault(HTTP_STATUS[code], []).append(code.value)
    out = {
        str(status): {
            "description": f"WireError, code {' or '.join(names)}",
            "content": {MSGPACK: {"schema": error}, JSON: {"schema": error}},
        }
        for status, names in sorted(by_status.items())
    }
    if "503" in out:
        out["503"]["headers"] = {
            "Retry-After": {"description": "seconds (overloaded)", "schema": {"type": "integer"}}
        }
    return out


def _sector_operation(stream_id: Schema) -> Schema:
    """The OpenAPI operation of the sector route's POST: a body and a reply schema per media type."""
    return {
        "summary": "Run one sector of a stream",
        "description": (
            "The body is a sector in msgpack (WireSector: points.data is bin) or JSON (JsonSector: "
            "points.data is a base64 string), by Content-Type. The reply is msgpack (WireDetections: its "
            "arrays' data is bin) or JSON (JsonDetections: the arrays as lists) by Accept; when Accept names "
            "neither, in the body's format. A body stream_id must equal the path's (else 422)."
        ),
        "operationId": "post_sector",
        "parameters": [{"name": "stream_id", "in": "path", "required": True, "schema": stream_id}],
        "requestBody": {
            "required": True,
            "content": {MSGPACK: {"schema": _ref("WireSector")}, JSON: {"schema": _ref("JsonSector")}},
        },
        "responses": {
            "200": {
                "description": "the detections",
                "content": {
                    MSGPACK: {"schema": _ref("WireDetections")},
                    JSON: {"schema": _ref("JsonDetections")},
                },
            },
            **error_responses(list(ErrorCode)),
        },
    }
