"""The HTTP app (FastAPI): a thin transport over the Worker. Its lifespan owns the model, the worker and the
zenoh transport; routes decode, submit, await (never blocking the event loop on the model) and encode.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from fastapi import FastAPI, Request, Response
from fastapi.responses import JSONResponse, PlainTextResponse
from starlette.requests import ClientDisconnect

from contract import (
    HTTP_STATUS,
    JSON,
    MSGPACK,
    MSGPACK_TYPES,
    ErrorCode,
    ErrorReply,
    Limits,
    ServiceError,
    check_stream_id,
    decode_sector,
    encode_error,
    encode_reply,
)
from model.config import Engine, Precision
from model.engine import EngineSettings, StreamEngine, build_engine
from server.auth import Grant, TokenFile
from server.metrics import Metrics
from server.openapi import error_responses, publish_sector_route
from server.settings import Settings
from server.tenants import tenant_of_id
from server.transports import start_live_view, start_ros2, start_zenoh
from server.warmup import package_version
from server.worker import Worker

if TYPE_CHECKING:
    from server.zenoh_transport import ZenohTransport

log = logging.getLogger(__name__)


class Closeable(Protocol):
    def close(self, drain_timeout_s: float) -> None: ...


@dataclass
class Services:
    settings: Settings
    worker: Worker
    metrics: Metrics
    limits: Limits
    tokens: TokenFile | None  # None: no authentication (docs/security.md)


def engine_settings(settings: Settings) -> EngineSettings:
    """The engine the server's settings name (`model.engine`): one stream-state slot per live stream."""
    return EngineSettings(
        checkpoint=settings.checkpoint,
        config=settings.config,
        device=settings.device,
        engine=Engine(settings.engine),
        precision=Precision(settings.precision),
        refiner=settings.refiner,
        ego_footprint=settings.ego_footprint,
        slots=settings.max_streams,
        sector_voxels=settings.sector_voxels,  # the graph engine derives padding and crops (docs/model.md)
    )


def build_detector(settings: Settings) -> tuple[StreamEngine, str]:
    """The engine the settings ask for, its weights loaded -> (engine, where its weights come from)."""
    return build_engine(engine_settings(settings))


def create_app(
    settings: Settings, detector: StreamEngine | None = None, model_source: str = "given detector"
) -> FastAPI:
    """The app; `detector` (already built) skips loading the model the settings name (tests share one)."""
    tokens = TokenFile(settings.auth_tokens) if settings.auth_tokens is not None else None

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        def load() -> tuple[StreamEngine, str]:  # runs in the worker's device thread
            return (detector, model_source) if detector is not None else build_detector(settings)

        metrics = Metrics()
        view = await asyncio.to_thread(start_live_view, settings, metrics)  # before any sector is answered
        observer = None if view is None else view.observe
        tenant_of = tenant_of_id if tokens is None else tokens.tenant_of  # server/tenants.py
        worker = Worker(load, settings.worker_config(), metrics, observer, tenant_of)
        worker.start()
        zenoh: ZenohTransport | None = None
        ros2: Closeable | None = None
        try:
            if settings.zenoh_enabled:
                zenoh = await asyncio.to_thread(start_zenoh, settings, worker)
            ros2 = await asyncio.to_thread(start_ros2, settings, worker, zenoh)
            app.state.services = Services(settings, worker, metrics, settings.limits(), tokens)
            yield
        finally:
            log.info("shutting down: draining (up to %.1f s)", settings.drain_timeout_s)
            if ros2 is not None:  # before zenoh, whose session it shares: publishes its answers in flight
                await asyncio.to_thread(ros2.close, settings.drain_timeout_s)
            if zenoh is not None:  # first: withdraw the liveliness token, answer zenoh's sectors in flight
                await asyncio.to_thread(zenoh.close, settings.drain_timeout_s)
            await asyncio.to_thread(worker.close, settings.drain_timeout_s)
            log.info("worker %s stopped", worker.worker_id)
            if view is not None:  # last: it shows the sectors the drain answered
                await asyncio.to_thread(view.stop)

    # with tokens, the API's description needs one too (docs/security.md)
    no_docs = {} if tokens is None else {"openapi_url": None, "docs_url": None, "redoc_url": None}
    app = FastAPI(title="PHiM detection server", version=package_version(), lifespan=lifespan, **no_docs)
    if tokens is not None:
        _add_guarded_docs(app)
    app.add_exception_handler(ServiceError, _service_error_handler)  # type: ignore[arg-type]
    _add_routes(app)
    publish_sector_route(app, SECTOR_PATH, settings.limits())
    return app


# ------------------------------------------------------------------------------------------------ helpers


def _services(request: Request) -> Services:
    return request.app.state.services


def wants_json(request: Request, default: bool) -> bool:
    accept = request.headers.get("accept", "")
    if any(t in accept for t in MSGPACK_TYPES):
        return False
    return JSON in accept or default


def error_response(
    e: ServiceError, as_json: bool, stream_id: str | None = None, seq: int | None = None
) -> Response:
    reply = ErrorReply.from_error(e, stream_id, seq)
    headers = {}
    if e.code is ErrorCode.UNAUTHORIZED:
        headers["WWW-Authenticate"] = 'Bearer realm="phim"'
    if e.retry_after_s is not None:
        headers["Retry-After"] = str(max(1, math.ceil(e.retry_after_s)))
    media_type = JSON if as_json else MSGPACK
    body = encode_error(reply, media_type)
    return Response(body, status_code=HTTP_STATUS[e.code], headers=headers, media_type=media_type)


async def _service_error_handler(request: Request, e: ServiceError) -> Response:
    stream_id = None if e.code in AUTH_ERRORS else request.path_params.get("stream_id")
    return error_response(e, wants_json(request, default=True), stream_id)


AUTH_ERRORS = (ErrorCode.UNAUTHORIZED, ErrorCode.FORBIDDEN)  # their replies name no stream


def authorize(request: Request, stream_id: str | None = None) -> Grant | None:
    """The request's grant (None when authentication is off); checked before anything else a route does.
    ServiceError UNAUTHORIZED without a known bearer token, FORBIDDEN for a stream outside its prefix."""
    tokens = _services(request).tokens
    if tokens is None:
        return None
    sent = request.headers.getlist("authorization")
    if len(sent) > 1:  # which one counts would depend on the proxy or framework that reads it: neither
        raise ServiceError(
            ErrorCode.UNAUTHORIZED,
            f"Authorization: {len(sent)} headers; expected exactly one 'Bearer <token>'",
            "Authorization",
        )
    scheme, _, token = (sent[0] if sent else "").partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        raise ServiceError(
            ErrorCode.UNAUTHORIZED, "Authorization: missing; expected 'Bearer <token>'", "Authorization"
        )
    grant = tokens.grant(token.strip())
    if grant is None:
        raise ServiceError(ErrorCode.UNAUTHORIZED, "Authorization: unknown token", "Authorization")
    if stream_id is not None and not grant.allows(stream_id):
        raise ServiceError(
            ErrorCode.FORBIDDEN,
            f"stream_id: this token may use the streams whose ID starts with {grant.prefix!r}",
            "stream_id",
        )
    return grant


def _content_type(request: Request) -> str:
    return request.headers.get("content-type", "").split(";")[0].strip().lower()


def _check_content_type(ctype: str) -> None:
    if ctype != JSON and ctype not in MSGPACK_TYPES:
        raise ServiceError(
            ErrorCode.BAD_REQUEST,
            f"Content-Type: {ctype or 'missing'!r}; expected {MSGPACK!r} or {JSON!r}",
            "Content-Type",
        )


async def read_body(request: Request, limit: int) -> bytes:
    """The body, refusing (413) by Content-Length before reading, and while reading past `limit` bytes."""
    declared = request.headers.get("content-length")
    if declared is not None:
        if not declared.isdigit():
            raise ServiceError(ErrorCode.BAD_REQUEST, f"Content-Length: {declared!r}; expected an integer")
        if int(declared) > limit:
            raise ServiceError(
                ErrorCode.TOO_LARGE, f"body: Content-Length {declared} bytes; the limit is {limit}", "body"
            )
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise ServiceError(
                ErrorCode.TOO_LARGE, f"body: more than {limit} bytes; the limit is {limit}", "body"
            )
        chunks.append(chunk)
    return b"".join(chunks)


# ------------------------------------------------------------------------------------------------- routes


async def post_sector(request: Request) -> Response:
    """A sector in msgpack or JSON (by Content-Type); the reply in msgpack or JSON by Accept, and when Accept
    names neither, in the request's format."""
    stream_id: str = request.path_params["stream_id"]
    svc = _services(request)
    ctype = _content_type(request)
    reply_type = JSON if wants_json(request, default=ctype == JSON) else MSGPACK
    try:
        authorize(request, stream_id)
    except ServiceError as e:
        svc.metrics.count("http", e.code.value)
        return error_response(e, reply_type == JSON)
    try:
        _check_content_type(ctype)
        body = await read_body(request, svc.limits.max_body_bytes)
        msg = decode_sector(body, svc.limits, stream_id, media_type=ctype)
    except ServiceError as e:
        svc.metrics.count("http", e.code.value)
        return error_response(e, reply_type == JSON, stream_id)
    except ClientDisconnect:  # gone before its body arrived: nothing was submitted, nobody to answer
        log.debug("http: a client left while sending a sector for %r", stream_id[:64])
        return Response(status_code=400)
    try:
        reply = await asyncio.wrap_future(svc.worker.submit(msg, transport="http"))
    except ServiceError as e:
        return error_response(e, reply_type == JSON, stream_id, msg.seq)
    return Response(encode_reply(reply, reply_type), media_type=reply_type)


async def delete_stream(stream_id: str, request: Request) -> dict[str, Any]:
    authorize(request, stream_id)
    _services(request).worker.end_stream(check_stream_id(stream_id))
    return {"stream_id": stream_id, "ended": True}


async def list_streams(request: Request) -> dict[str, Any]:
    grant = authorize(request)
    svc = _services(request)
    streams = svc.worker.streams()
    if grant is not None and not grant.admin:  # a stream token sees its own namespace only
        streams = [s for s in streams if grant.allows(s["stream_id"])]
    return {"streams": streams, "live": len(streams), "max_streams": svc.settings.max_streams}


async def get_stream(stream_id: str, request: Request) -> dict[str, Any]:
    authorize(request, stream_id)
    return _services(request).worker.stream(check_stream_id(stream_id))


async def get_model(request: Request) -> dict[str, Any]:
    authorize(request)
    return _services(request).worker.model_info()


async def live(request: Request) -> Response:
    worker = _services(request).worker
    if not worker.live:
        return error_response(ServiceError(ErrorCode.INTERNAL, f"device loop: {worker.status}"), as_json=True)
    return JSONResponse({"status": "live", "worker_id": worker.worker_id})


async def ready(request: Request) -> Response:
    worker = _services(request).worker
    if not worker.ready:
        return error_response(ServiceError(ErrorCode.NOT_READY, f"worker: {worker.status}"), as_json=True)
    return JSONResponse({"status": "ready", "worker_id": worker.worker_id})


async def metrics(request: Request) -> Response:
    if not _services(request).settings.public_metrics:
        authorize(request)
    m = _services(request).metrics
    return Response(m.exposition(), media_type=m.content_type)


E = ErrorCode
AUTH = (E.UNAUTHORIZED,)  # with --auth-tokens
STREAM = (E.UNAUTHORIZED, E.FORBIDDEN, E.INVALID_FIELD, E.UNKNOWN_STREAM)
# method, path, route, the errors it may answer (the OpenAPI document lists them)
ROUTES: list[tuple[str, str, Callable[..., Any], tuple[ErrorCode, ...]]] = [
    ("DELETE", "/v1/streams/{stream_id}", delete_stream, STREAM),
    ("GET", "/v1/streams", list_streams, AUTH),
    ("GET", "/v1/streams/{stream_id}", get_stream, STREAM),
    ("GET", "/v1/model", get_model, AUTH),
    ("GET", "/health/live", live, (E.INTERNAL,)),
    ("GET", "/health/ready", ready, (E.NOT_READY,)),
    ("GET", "/metrics", metrics, AUTH),
]


SECTOR_PATH = "/v1/streams/{stream_id}/sectors"


def _add_guarded_docs(app: FastAPI) -> None:
    """With tokens: GET /openapi.json needs one, like every route but /health (FastAPI's own route is open);
    /docs and /redoc are not served (a browser sends no bearer token to fetch the document with)."""

    async def openapi(request: Request) -> Response:
        authorize(request)
        return JSONResponse(app.openapi())

    app.add_route("/openapi.json", openapi, methods=["GET"], include_in_schema=False)


def _add_routes(app: FastAPI) -> None:
    # the hot route as a plain Starlette route: FastAPI's parameter handling cost about 0.15 ms per sector
    # (docs/benchmarks.md); `server.openapi.publish_sector_route` adds it to the OpenAPI document
    app.router.add_route(SECTOR_PATH, post_sector, methods=["POST"])
    for method, path, endpoint, errors in ROUTES:
        # /metrics is Prometheus' text format; the other routes answer JSON
        kind = PlainTextResponse if endpoint is metrics else JSONResponse
        responses = error_responses(list(errors))
        app.add_api_route(path, endpoint, methods=[method], responses=responses, response_class=kind)
