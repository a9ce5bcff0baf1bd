"""schemathesis against the server's own OpenAPI document (GET /openapi.json), on a real uvicorn server:
every operation, with bodies and parameters generated from the schema and broken on purpose (positive and
negative cases, msgpack and JSON). schemathesis checks every answer: no 5xx other than the documented 503,
status codes, content types and bodies as the document says. A control stream's detections are the same
before and after (tests/test_fuzz.py fuzzes bytes; this fuzzes by the schema)."""

from __future__ import annotations

import base64
import binascii
import contextlib
import os
from collections.abc import Iterator
from typing import Any

import httpx
import msgpack
import pytest
import schemathesis
from hypothesis import HealthCheck, given, seed, settings
from schemathesis.generation.modes import GenerationMode
from schemathesis.specs.openapi.checks import negative_data_rejection, positive_data_acceptance
from server_helpers import RunningServer, assert_same_reply, control_reply, default_detector, serve

from contract import MSGPACK

CASES = int(os.environ.get("PHIM_SCHEMA_FUZZ_CASES", "200"))  # per operation and phase (fuzz.sh: 5,000)
SECTOR_ROUTE = "POST /v1/streams/{stream_id}/sectors"


@schemathesis.serializer(MSGPACK)
def _msgpack(ctx: schemathesis.SerializationContext, value: Any) -> bytes:
    """The schema's msgpack body as msgpack: `data` (base64 in the JSON Schema) travels as bin when it is
    valid base64, so generated sectors reach the decoder's deeper checks; integers msgpack cannot hold go
    as floats."""
    return msgpack.packb(_binary_data(value), use_bin_type=True)


def _binary_data(value: Any) -> Any:
    if isinstance(value, dict):
        out = {k: _binary_data(v) for k, v in value.items()}
        if isinstance(out.get("data"), str):
            with contextlib.suppress(binascii.Error, ValueError):
                out["data"] = base64.b64decode(out["data"], validate=True)
        return out
    if isinstance(value, list):
        return [_binary_data(v) for v in value]
    if isinstance(value, int) and not -(2**63) <= value < 2**64:
        return float(value)  # msgpack has no wider integers (a client could not send one)
    return value


@pytest.fixture(scope="module")
def served() -> Iterator[RunningServer]:
    with serve(default_detector(), max_points=20_000) as s:
        yield s


@pytest.fixture(scope="module")
def api(served: RunningServer) -> Any:
    return schemathesis.openapi.from_url(f"{served.url}/openapi.json")


@pytest.fixture(scope="module")
def control(served: RunningServer) -> Iterator[None]:
    """The control stream's detections before any case and after all of them: the same boxes."""
    before = control_reply(served.url, "control-a")
    yield
    assert_same_reply(control_reply(served.url, "control-b"), before)
    assert httpx.get(f"{served.url}/health/live").status_code == 200


@pytest.mark.parametrize("mode", list(GenerationMode))
def test_every_operation_answers_as_its_schema_says(api: Any, control: None, mode: GenerationMode) -> None:
    seen: dict[str, int] = {}  # operation -> cases answered and checked
    ran: list[str] = []
    for result in api.get_all_operations():
        operation = result.ok()
        if mode is GenerationMode.NEGATIVE and "{" not in operation.path and not len(operation.body):
            continue  # nothing to break: no path parameter, no body
        ran.append(operation.label)

        @seed(20261124)
        @settings(
            max_examples=CASES,
            deadline=None,
            derandomize=True,
            database=None,
            suppress_health_check=list(HealthCheck),
        )
        @given(case=operation.as_strategy(generation_mode=mode))
        def one(case: Any) -> None:
            # a sector can fit the schema and still be refused (422): the schema cannot say that `shape`
            # must match `fields` and the length of `data`, or that points are "<f4"
            skip = [positive_data_acceptance] if case.operation.label == SECTOR_ROUTE else []
            # schemathesis' rejection check knows no 413, which is how the limits refuse: ours instead
            skip.append(negative_data_rejection)
            response = case.call(timeout=30)
            case.validate_response(response, excluded_checks=skip)
            if mode is GenerationMode.NEGATIVE:
                assert 400 <= response.status_code < 500, (response.status_code, response.content[:300])
            seen[case.operation.label] = seen.get(case.operation.label, 0) + 1

        one()
    assert SECTOR_ROUTE in ran and sorted(seen) == sorted(ran), (ran, seen)  # every operation got cases
