"""zenoh client: a `get` on `{prefix}/streams/{stream_id}/sector` with a msgpack sector as payload.

The session is a zenoh client (or peer) connecting to the given endpoints (a worker or a router). Gets use
`CongestionControl.BLOCK` (a reply's QoS follows its query's), and a timeout after which zenoh itself ends the
get with a `Timeout` error reply (encoding zenoh/bytes, unlike the server's msgpack error replies).

The async path never blocks the event loop: the get runs with a callback handler (zenoh calls it on its own
thread), which decodes the reply and resolves an asyncio future through `loop.call_soon_threadsafe`; any
number of gets may be in flight. zenoh has no model-info or end-stream keys: give `http_url` to reach those
over HTTP; without it `end_stream` makes the stream's next sector a reset and `model_info` raises.

With `auto_workers` (a fleet: `--workers auto`) each sector goes to its stream's owner among the live workers
under that worker's own keys (clients/zenoh_workers.py). A sector that gets no answer from its owner (no
reply, zenoh's timeout, or NOT_READY) because that owner has left is sent once more, to the new owner, as a
reset; a second failure is raised. So a vehicle's sequence goes on across a worker's death, cold. While no
worker is known, a sector waits for one up to `timeout_s` (the async path in a thread, every sector
sharing the one wait: the event loop never blocks), then fails with a TransportError.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import zenoh

from clients.base import (
    ClientError,
    DetectorClient,
    OnSent,
    RequestTimeout,
    ServerError,
    TransportError,
    answer,
)
from clients.http_client import HttpClient
from clients.zenoh_session import MSGPACK_ENCODING, open_session
from clients.zenoh_workers import LiveWorkers, StreamOwners
from contract import (
    DEFAULT_KEY_PREFIX,
    DEFAULT_ZENOH_ENDPOINT,
    DetectionsReply,
    ErrorCode,
    ErrorReply,
    KeySpace,
    SectorMessage,
    ServiceError,
    decode_response,
    encode_sector,
)

log = logging.getLogger(__name__)
BLOCK = zenoh.CongestionControl.BLOCK
Outcome = DetectionsReply | ErrorReply | ClientError
Held = tuple[zenoh.Reply, Outcome]  # an answer not taken yet, and what it says


class NotSupported(ClientError):
    """The transport has no way to do this (e.g. model info over zenoh without an HTTP address)."""


@dataclass(frozen=True)
class ZenohClientConfig:
    connect: tuple[str, ...] = (DEFAULT_ZENOH_ENDPOINT,)
    mode: str = "client"  # "client" (needs a reachable worker or router at open) or "peer"
    key_prefix: str = DEFAULT_KEY_PREFIX
    timeout_s: float = 10.0  # per get
    config_file: str | None = None  # a zenoh JSON5 file (TLS, ...); the fields above override it
    worker: str | None = None  # take answers from this worker ID only (default: any live worker)
    auto_workers: bool = False  # send each stream to its owner among the live workers, under its own keys
    http_url: str | None = None  # the same server's HTTP address, for model_info / end_stream
    token: str | None = None  # the bearer token for http_url
    ca_cert: str | None = None  # the CA (PEM) an https http_url is checked against


class ZenohClient(DetectorClient):
    """The detector over zenoh request/reply. Send one stream's sectors from one client (ordering).

    An answer counts only when it comes from a session that holds a worker's liveliness token (that worker's,
    when `worker` is set): others are ignored and counted in `ignored_replies` (clients/zenoh_workers.py)."""

    transport = "zenoh"

    def __init__(self, config: ZenohClientConfig | None = None, **overrides: Any):
        cfg = config or ZenohClientConfig(**overrides)
        self.config = cfg
        self.keys = KeySpace(cfg.key_prefix)
        self._reset_next: set[str] = set()
        self._lock = threading.Lock()
        try:
            self._session: zenoh.Session | None = open_session(
                cfg.connect, cfg.mode, config_file=cfg.config_file
            )
        except zenoh.ZError as e:
            raise TransportError(
                f"zenoh: cannot open a {cfg.mode} session to {list(cfg.connect)}: {e}"
            ) from e
        self._live = LiveWorkers(self._session, self.keys, min(2.0, cfg.timeout_s))
        self.owners = StreamOwners(self._live, cfg.timeout_s) if cfg.auto_workers else None
        self.ignored_replies = 0
        self.retries = 0  # sectors sent again to a new owner after theirs left (auto_workers)
        self._http = HttpClient(cfg.http_url, token=cfg.token, ca_cert=cfg.ca_cert) if cfg.http_url else None

    # ------------------------------------------------------------------------------------------ sectors

    def send(self, msg: SectorMessage) -> DetectionsReply:
        if self.owners is None:
            return self._send_to(msg, None)
        worker, msg = self._route(msg)
        try:
            return self._send_to(msg, worker)
        except ClientError as e:
            retry = self._retry(msg, worker, e)
            if retry is None:
                raise
            return self._send_to(retry[1], retry[0])

    async def send_async(self, msg: SectorMessage, on_sent: OnSent | None = None) -> DetectionsReply:
        if self.owners is None:
            return await self._send_to_async(msg, None, on_sent)
        if on_sent is not None and not self._live.routable():
            # no worker known: this sector waits (one bounded wait, shared) and so may the stream's next;
            # the waits end in the order they began, so the gets still leave in the stream's order
            on_sent()
            on_sent = None
        owner, moved = await self.owners.route_async(msg.stream_id)
        worker, msg = owner, dataclasses.replace(msg, reset=True) if moved else msg
        try:
            return await self._send_to_async(msg, worker, on_sent)
        except ClientError as e:
            loop = asyncio.get_running_loop()
            retry = await loop.run_in_executor(None, self._retry, msg, worker, e)
            if retry is None:
                raise
            return await self._send_to_async(retry[1], retry[0], None)

    def _send_to(self, msg: SectorMessage, worker: str | None) -> DetectionsReply:
        key = self.keys.sector(msg.stream_id, worker)
        replies = self._session_or_fail().get(key, payload=self._body(msg), **self._get_options())
        expected = worker or self.config.worker
        outcome: Outcome | None = None
        held: list[Held] = []
        for reply in replies:  # ends when every queryable finalized the query, or at the timeout
            judged, trusted = self._judge(reply, expected)
            if trusted is None:
                held.append((reply, judged))
            elif outcome is None and trusted:
                outcome = judged
        if outcome is None and held:
            outcome = self._recheck(held, expected)
        return _result(outcome, key)

    async def _send_to_async(
        self, msg: SectorMessage, worker: str | None, on_sent: OnSent | None
    ) -> DetectionsReply:
        loop = asyncio.get_running_loop()
        key = self.keys.sector(msg.stream_id, worker)
        expected = worker or self.config.worker
        future: asyncio.Future[Outcome | list[Held] | None] = loop.create_future()
        pending = _Pending(loop, future, partial(self._judge, expected=expected))
        handler = zenoh.handlers.Callback(pending.on_reply, pending.on_done)
        self._session_or_fail().get(key, handler, payload=self._body(msg), **self._get_options())
        if on_sent is not None:  # the query is queued on the session: later gets follow it on the link
            on_sent()
        outcome = await future
        if isinstance(outcome, list):  # no worker's answer, only answers held back
            outcome = await loop.run_in_executor(None, self._recheck, outcome, expected)
        return _result(outcome, key)

    def _route(self, msg: SectorMessage) -> tuple[str, SectorMessage]:
        """The stream's owner, and the sector to send it (a reset when the stream moves there)."""
        assert self.owners is not None
        worker, moved = self.owners.route(msg.stream_id)
        return worker, dataclasses.replace(msg, reset=True) if moved else msg

    def _retry(self, msg: SectorMessage, worker: str, e: ClientError) -> tuple[str, SectorMessage] | None:
        """Where to send a sector once more: its stream's new owner, when `worker` failed it for lack of a
        worker (no answer, zenoh's timeout, NOT_READY) and has left. None: raise `e`."""
        assert self.owners is not None
        lost = not isinstance(e, ServerError) or e.code is ErrorCode.NOT_READY
        if not lost or not self.owners.gone(worker):
            return None
        new, _ = self.owners.route(msg.stream_id)
        if new == worker:
            return None
        # always a reset: a stream's sectors in flight to a dead worker fail together and come back here in
        # any order; as resets none is refused as stale on the new owner (each restarts the stream there)
        msg = dataclasses.replace(msg, reset=True)
        with self._lock:
            self.retries += 1
        log.info(
            "zenoh: worker %s left; stream %s seq %d sent again to %s", worker, msg.stream_id, msg.seq, new
        )
        return new, msg

    def _judge(self, reply: zenoh.Reply, expected: str | None) -> tuple[Outcome, bool | None]:
        """A reply's outcome, and whether to take it: True for a worker's answer; False for another worker
        than the `expected` one (the pinned or addressed worker); None (held back until the get ends) for an
        answer from a session that holds no worker token (yet), and for zenoh's own errors (its b"Timeout"
        comes when the get ends anyway)."""
        outcome = reply_outcome(reply)
        rid = reply.replier_id
        zid = str(rid.zid) if rid is not None else ""
        if isinstance(outcome, ClientError) or not self._live.holds(zid):
            return outcome, None
        if expected is not None and not self._live.holds(zid, expected):
            self._ignore(reply, f"a worker, not {expected!r}")
            return outcome, False
        return outcome, True

    def _recheck(self, held: list[Held], expected: str | None) -> Outcome | None:
        """When the get ended without a worker's answer: the first held answer whose session proves to be a
        worker once the tokens are asked for again; else zenoh's own error (the timeout); else None."""
        if not all(isinstance(outcome, ClientError) for _, outcome in held):
            self._live.refresh(min(2.0, self.config.timeout_s))
        errors: list[Outcome] = []
        for reply, outcome in held:
            if isinstance(outcome, ClientError):
                errors.append(outcome)
                continue
            trusted = self._judge(reply, expected)[1]
            if trusted:
                return outcome
            if trusted is None:
                self._ignore(reply, "a session that holds no worker token")
        return errors[0] if errors else None

    def _ignore(self, reply: zenoh.Reply, why: str) -> None:
        with self._lock:
            self.ignored_replies += 1
        rid = reply.replier_id
        log.warning("zenoh: ignored an answer from %s: %s", rid.zid if rid is not None else "?", why)

    def _body(self, msg: SectorMessage) -> bytes:
        with self._lock:
            if msg.stream_id in self._reset_next:
                self._reset_next.discard(msg.stream_id)
                msg = dataclasses.replace(msg, reset=True)
        return encode_sector(msg)

    def _get_options(self) -> dict[str, Any]:
        # every reply reaches the client as it comes (zenoh's default consolidation would keep one per key,
        # the latest: a rogue's late answer would replace the worker's before the client could judge it)
        return {
            "encoding": MSGPACK_ENCODING,
            "congestion_control": BLOCK,
            "consolidation": zenoh.ConsolidationMode.NONE,
            "timeout": self.config.timeout_s,
        }

    # ------------------------------------------------------------------------------------------ control

    def end_stream(self, stream_id: str) -> None:
        """Over HTTP when `http_url` is given; else the stream's next sector is sent with reset=True (the
        server drops the old state then, or evicts it when idle)."""
        if self._http is not None:
            self._http.end_stream(stream_id)
            return
        with self._lock:
            self._reset_next.add(stream_id)

    def model_info(self) -> dict[str, Any]:
        if self._http is None:
            raise NotSupported("zenoh has no model-info key; give ZenohClientConfig.http_url")
        return self._http.model_info()

    def workers(self, timeout_s: float = 2.0) -> list[str]:
        """The IDs of the live workers under this prefix (their liveliness tokens), asked for now."""
        self._session_or_fail()
        self._live.refresh(timeout_s)
        return self._live.ids()

    def _session_or_fail(self) -> zenoh.Session:
        if self._session is None:
            raise TransportError("the client is closed")
        return self._session

    def close(self) -> None:
        if self._http is not None:
            self._http.close()
        if self._session is not None:
            session, self._session = self._session, None
            self._live.close()
            session.close()


def reply_outcome(reply: zenoh.Reply) -> Outcome:
    """One zenoh reply -> the server's answer (detections or error), or the client-side failure."""
    if reply.ok is not None:
        data, is_msgpack = reply.ok.payload.to_bytes(), True
    else:
        err = reply.err
        assert err is not None
        data, is_msgpack = err.payload.to_bytes(), str(err.encoding).startswith(str(MSGPACK_ENCODING))
    if not is_msgpack:  # zenoh's own error reply: b"Timeout" when the get's timeout passed
        if data.strip().lower() == b"timeout":
            return RequestTimeout("zenoh: no reply before the get's timeout")
        return TransportError(f"zenoh error reply: {data[:200]!r}")
    try:
        return decode_response(data)
    except ServiceError as e:
        return TransportError(f"zenoh: the reply is not a PHiM message ({e.message})")


def _result(outcome: Outcome | None, key: str) -> DetectionsReply:
    if outcome is None:
        raise TransportError(f"zenoh: no worker answered on {key}")
    if isinstance(outcome, ClientError):
        raise outcome
    return answer(outcome)


class _Pending:
    """The callback side of one async get: runs on zenoh's thread, touches only the future's loop. The
    future gets the first worker's answer; else, when the get ends, what was held back (a list), or None."""

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        future: asyncio.Future[Outcome | list[Held] | None],
        judge: Callable[[zenoh.Reply], tuple[Outcome, bool | None]],
    ):
        self.loop = loop
        self.future = future
        self.judge = judge
        self.answered = False
        self.held: list[Held] = []
        self._lock = threading.Lock()  # zenoh may call on_reply and on_done from different threads

    def on_reply(self, reply: zenoh.Reply) -> None:
        outcome, trusted = self.judge(reply)
        with self._lock:
            if self.answered or trusted is False:
                return
            if trusted is None:
                self.held.append((reply, outcome))
                return
            self.answered = True
            self._resolve(outcome)

    def on_done(self) -> None:  # the get ended (finalized or timed out): resolves a get nobody answered
        with self._lock:
            if not self.answered:
                self.answered = True
                self._resolve(self.held or None)

    def _resolve(self, outcome: Outcome | list[Held] | None) -> None:
        with contextlib.suppress(RuntimeError):  # a closed loop: nobody waits for this answer any more
            self.loop.call_soon_threadsafe(_set, self.future, outcome)


def _set(future: asyncio.Future[Outcome | list[Held] | None], outcome: Outcome | list[Held] | None) -> None:
    if not future.done():
        future.set_result(outcome)
