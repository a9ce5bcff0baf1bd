"""Property-based fuzzing (hypothesis, fixed seed): the decoder, the HTTP sector route and the zenoh
queryable take arbitrary bytes and mutated sectors. Every input gets a 4xx-class error or detections: never
an exception the contract does not name, a 500, a hang, or a change to another stream (a control stream's
detections are the same before and after). scripts/fuzz.sh runs the same properties far longer."""

from __future__ import annotations

import os
from collections.abc import Iterator
from typing import Any

import httpx
import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, seed, settings
from hypothesis import strategies as st
from server_helpers import (
    assert_same_reply,
    control_reply,
    default_detector,
    free_endpoint,
    sector_msg,
    serve,
)

from contract import (
    HTTP_STATUS,
    MSGPACK,
    DetectionsReply,
    ErrorCode,
    ErrorReply,
    KeySpace,
    Limits,
    ServiceError,
    decode_response,
    decode_sector,
    encode_sector,
)
from server.zenoh_transport import MSGPACK_ENCODING, ZenohConfig, open_session

CASES = int(os.environ.get("PHIM_FUZZ_CASES", "700"))  # per property; scripts/fuzz.sh raises it
LIMITS = Limits(max_body_bytes=2**20, max_points=20_000, max_string_len=64)
KEYS = KeySpace()
ZENOH_STREAMS = ["fuzz-3", "fuzz-4", "control-c", "*", "**", "a$*b", "x" * 80]  # keys, wildcards included
FUZZ = settings(
    max_examples=CASES,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)

scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**63), max_value=2**64 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=80),
    st.binary(max_size=64),
)
values = st.recursive(
    scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=12), inner, max_size=4),
    max_leaves=12,
)


def _valid_sector() -> dict[str, Any]:
    return msgpack.unpackb(encode_sector(sector_msg("fuzz-1", 1, np.zeros((5, 4), np.float32))))


@st.composite
def mutated_sectors(draw: st.DrawFn) -> bytes:
    """A valid sector's map with some keys dropped, replaced by anything, or added."""
    msg = _valid_sector()
    points = msg["points"]
    for _ in range(draw(st.integers(1, 4))):
        target = draw(st.sampled_from(["top", "points"]))
        d = msg if target == "top" else points
        key = draw(st.sampled_from([*d.keys(), "extra"]))
        action = draw(st.sampled_from(["drop", "replace"]))
        if action == "drop" and key in d:
            del d[key]
        else:
            d[key] = draw(values)
    return msgpack.packb(msg, use_bin_type=True)


bodies = st.one_of(st.binary(max_size=2048), mutated_sectors())


@seed(20261124)
@FUZZ
@given(body=bodies)
@example(body=b"\x81\xa7\x00\x00\x00\x00\x00\x00\x80")  # by scripts/fuzz.sh: a non-UTF-8 key (was a 500)
def test_the_decoder_names_every_fault(body: bytes) -> None:
    try:
        decode_sector(body, LIMITS, stream_id="fuzz-1")
    except ServiceError as e:
        assert 400 <= HTTP_STATUS[e.code] < 500 and e.message
    except Exception as e:  # anything else is a bug in the contract
        pytest.fail(f"{type(e).__name__}: {e}")


@pytest.fixture(scope="module")
def served() -> Iterator[tuple[Any, str]]:
    """A real server with HTTP and zenoh on loopback -> (it, its zenoh endpoint)."""
    endpoint = free_endpoint()
    overrides = dict(zenoh_enabled=True, zenoh_listen=(endpoint,), max_points=LIMITS.max_points)
    with serve(default_detector(), **overrides) as s:
        yield s, endpoint


def test_http_fuzz_never_500_and_harms_no_other_stream(served) -> None:
    url = served[0].url
    before = control_reply(url, "control-a")
    statuses: dict[int, int] = {}
    with httpx.Client(base_url=url, timeout=30) as client:

        @seed(20261124)
        @FUZZ
        @given(body=bodies, stream=st.sampled_from(["fuzz-1", "fuzz-2", "control-a"]), json=st.booleans())
        def one(body: bytes, stream: str, json: bool) -> None:
            ctype = "application/json" if json else MSGPACK
            r = client.post(f"/v1/streams/{stream}/sectors", content=body, headers={"Content-Type": ctype})
            statuses[r.status_code] = statuses.get(r.status_code, 0) + 1
            assert r.status_code < 500 or r.status_code == 503, r.content[:300]
            out = decode_response(r.content, media_type=r.headers["content-type"])
            assert isinstance(out, DetectionsReply | ErrorReply)

        one()
    after = control_reply(url, "control-b")  # a fresh stream, the same sector: the same boxes
    assert_same_reply(after, before)
    assert sum(statuses.values()) == CASES and httpx.get(f"{url}/health/live").status_code == 200


def test_zenoh_fuzz_answers_every_get_once(served) -> None:
    url, endpoint = served[0].url, served[1]
    before = control_reply(url, "control-c")
    codes: dict[str, int] = {}
    with open_session(ZenohConfig(mode="client", listen=(), connect=(endpoint,))) as session:

        @seed(20261124)
        @FUZZ
        @given(body=bodies, stream=st.sampled_from(ZENOH_STREAMS))
        def one(body: bytes, stream: str) -> None:
            replies = list(
                session.get(KEYS.sector(stream), payload=body, encoding=MSGPACK_ENCODING, timeout=30)
            )
            assert len(replies) == 1, replies  # exactly one answer per get
            reply = replies[0]
            sample = reply.ok if reply.ok is not None else reply.err
            out = decode_response(sample.payload.to_bytes())
            code = "ok" if isinstance(out, DetectionsReply) else out.code.value
            codes[code] = codes.get(code, 0) + 1
            assert code == "ok" or out.code is ErrorCode.OVERLOADED or HTTP_STATUS[out.code] < 500, out

        one()
    after = control_reply(url, "control-d")
    assert_same_reply(after, before)
    assert sum(codes.values()) == CASES
