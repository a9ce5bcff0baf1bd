"""The sector route in the OpenAPI document: it is a plain Starlette route (server/app.py: FastAPI's
parameter handling cost about 0.15 ms per sector), which FastAPI leaves out of GET /openapi.json."""

from __future__ import annotations

from typing import Any

import msgspec
from fastapi import FastAPI

from contract import (
    HTTP_STATUS,
    JSON,
    MSGPACK,
    ErrorCode,
    JsonDetections,
    WireDetections,
    WireError,
    WireSector,
)

REF_TEMPLATE = "#/components/schemas/{name}"


def publish_sector_route(app: FastAPI, path: str) -> None:
    """Puts the sector route (a plain Starlette route, which FastAPI leaves out) in GET /openapi.json, with
    schemas generated from the contract's msgspec Structs: once, when the document is first asked for."""
    fastapi_openapi = app.openapi

    def openapi() -> dict[str, Any]:
        doc = app.openapi_schema
        if doc is None:
            doc = fastapi_openapi()  # FastAPI's document, kept in app.openapi_schema (and so is what we add)
            refs, schemas = msgspec.json.schema_components(
                [WireSector, WireDetections, JsonDetections, WireError], ref_template=REF_TEMPLATE
            )
            doc.setdefault("components", {}).setdefault("schemas", {}).update(schemas)
            stream_id = schemas["WireSector"]["properties"]["stream_id"]
            doc["paths"][path] = {"post": _sector_operation(stream_id, *refs)}
            for operation in (op for ops in doc["paths"].values() for op in ops.values()):
                for param in operation.get("parameters", []):
                    if param["name"] == "stream_id":  # FastAPI's says "a string"; the contract's, which
                        param["schema"] = stream_id  # the routes check
        return doc

    app.openapi = openapi  # type: ignore[method-assign]


Schema = dict[str, Any]  # a JSON Schema or a piece of the OpenAPI document
WIRE_ERROR: Schema = {"$ref": REF_TEMPLATE.format(name="WireError")}


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


def _sector_operation(
    stream_id: Schema, sector: Schema, detections: Schema, json_detections: Schema, error: Schema
) -> Schema:
    """The OpenAPI operation of the sector route's POST, from the JSON Schemas of its messages."""

    def content(msgpack_schema: Schema, json_schema: Schema) -> Schema:
        return {MSGPACK: {"schema": msgpack_schema}, JSON: {"schema": json_schema}}

    errors = error_responses(list(ErrorCode), error)
    return {
        "summary": "Run one sector of a stream",
        "description": (
            "The body is a sector in msgpack or JSON (Content-Type). The reply is msgpack or JSON by Accept; "
            "when Accept names neither, in the body's format. Array `data`: msgpack bin; base64 in JSON. "
            "The JSON reply gives the arrays as lists (JsonDetections)."
        ),
        "operationId": "post_sector",
        "parameters": [{"name": "stream_id", "in": "path", "required": True, "schema": stream_id}],
        "requestBody": {"required": True, "content": content(sector, sector)},
        "responses": {
            "200": {"description": "the detections", "content": content(detections, json_detections)},
            **errors,
        },
    }
