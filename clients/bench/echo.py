"""`python -m clients.bench.echo`: the bare responder behind `phim bench server`'s transport floor.

No protocol, no validation, no stream table: the same transports (uvicorn + a Starlette route, a zenoh
queryable read by a receiver thread) around a stand-in for the forward. A request is

    header (HEADER: hold_ms float64, reply_bytes uint32) + the payload (the sector's bytes, unread)

and its answer is `reply_bytes` bytes starting with the time the stand-in really held (float64 seconds).
The stand-in keeps the CPU busy with numpy matmuls for hold_ms on one thread of its own, the way the
device thread's forward does, so the machine is in the same state when the answer goes out. What a round
trip costs beyond the hold is the floor any server on these transports pays on this machine.
"""

from __future__ import annotations

import asyncio
import struct
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor

import click
import numpy as np
import zenoh
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import Response
from starlette.routing import Route

from clients.zenoh_session import open_session
from phim.process import tune_malloc

HEADER = struct.Struct("<dI")  # hold_ms, reply_bytes
HELD = struct.Struct("<d")  # seconds held, at the start of the answer
ECHO_KEY = "phim/bench/echo"
ECHO_PATH = "/echo"


def request_header(hold_ms: float, reply_bytes: int) -> bytes:
    return HEADER.pack(hold_ms, max(HELD.size, reply_bytes))


class Holder:
    """Busy for hold_ms on its own thread, as the worker's device thread is during a forward."""

    def __init__(self) -> None:
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="echo-hold")
        self._a = np.random.default_rng(0).random((192, 192), dtype=np.float32)  # (192, 192)

    def hold(self, hold_ms: float) -> float:
        t0 = time.perf_counter()
        while (time.perf_counter() - t0) * 1e3 < hold_ms:
            self._a = np.clip(self._a @ self._a, 0.0, 1.0)
        return time.perf_counter() - t0

    def answer(self, body: bytes | memoryview) -> bytes:
        hold_ms, reply_bytes = HEADER.unpack_from(body)
        return HELD.pack(self.hold(hold_ms)) + bytes(reply_bytes - HELD.size)

    def submit(self, body: bytes) -> Future[bytes]:
        return self._pool.submit(self.answer, body)


def http_app(holder: Holder) -> Starlette:
    async def echo(request: Request) -> Response:
        body = await request.body()
        answer = await asyncio.wrap_future(holder.submit(body))
        return Response(answer, media_type="application/octet-stream")

    async def ready(request: Request) -> Response:
        return Response(b"ready")

    return Starlette(routes=[Route(ECHO_PATH, echo, methods=["POST"]), Route("/ready", ready)])


def serve_zenoh(holder: Holder, listen: str) -> tuple[zenoh.Session, zenoh.Queryable]:
    """A queryable on ECHO_KEY; a receiver thread hands each query to the holder, then replies."""
    session = open_session((), mode="peer", listen=(listen,))
    queryable = session.declare_queryable(ECHO_KEY, zenoh.handlers.FifoChannel(16))

    def receive() -> None:
        while True:
            try:
                query = queryable.handler.recv()
            except zenoh.ZError:
                return
            try:
                body = query.payload.to_bytes() if query.payload is not None else b""
                query.reply(query.key_expr, holder.submit(body).result())
            finally:
                query.drop()

    threading.Thread(target=receive, name="echo-zenoh", daemon=True).start()
    return session, queryable


@click.command()
@click.option("--port", type=int, default=18090, show_default=True, help="HTTP port.")
@click.option("--zenoh-listen", default="tcp/127.0.0.1:17490", show_default=True, help="Zenoh endpoint.")
def main(port: int, zenoh_listen: str) -> None:
    """Serve the bare responder until killed."""
    import uvicorn

    tune_malloc()
    holder = Holder()
    session_and_queryable = serve_zenoh(holder, zenoh_listen)  # live as long as the process
    uvicorn.run(http_app(holder), host="127.0.0.1", port=port, log_level="warning", ws="none")
    del session_and_queryable


if __name__ == "__main__":
    main()
