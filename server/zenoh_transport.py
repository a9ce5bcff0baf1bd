"""The zenoh transport: sectors in over a queryable (request/reply) or a subscriber (pub/sub), answers out.

It knows the wire protocol and a `submit` callable (the worker's), nothing else: it never sees a tensor.

Threads (the skeleton: server/transport_thread.py), so that no zenoh callback ever blocks and no zenoh call
is made inside one:
  - zenoh pushes queries and samples into bounded FIFO channels (no Python callback at all);
  - two receiver threads (one per channel) `recv`, decode and `submit`; `submit` never blocks;
  - the future's done-callback (it runs on the worker's device thread) only puts the outcome in the outbox;
  - one replier thread owns every outgoing zenoh call: `reply`/`reply_err` + `drop` for queries, `put` for
    pub/sub results. Every sector gets exactly one answer, also on decode errors and on `close`. (The one
    exception: a wildcard get that reaches both the worker's own and the shared queryable is finalized
    unanswered by the own one's receiver, since the shared one answers it.)

Key expressions (prefix "phim/v1" by default): see `contract.KeySpace` and docs/protocol.md ("Zenoh").
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from functools import partial

import zenoh

from contract import (
    DEFAULT_KEY_PREFIX,
    DEFAULT_ZENOH_ENDPOINT,
    MSGPACK,
    PROBE_CHUNK,
    STREAM_ID_RE,
    DetectionsReply,
    ErrorCode,
    ErrorReply,
    KeySpace,
    Limits,
    ServiceError,
    decode_sector,
    encode_error,
    encode_reply,
)
from server.transport_thread import Submit, TransportThreads, submit_or_fail

log = logging.getLogger(__name__)

MSGPACK_ENCODING = zenoh.Encoding(MSGPACK)
CHANNEL_CAPACITY = 256  # queries / samples zenoh may hold for a receiver thread before it pushes back

Outcome = DetectionsReply | ErrorReply


@dataclass(frozen=True)
class ZenohConfig:
    mode: str = "peer"  # "peer" | "client" | "router"
    listen: tuple[str, ...] = (DEFAULT_ZENOH_ENDPOINT,)
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    config_file: str | None = None  # a zenoh JSON5 config file; the fields above override it
    key_prefix: str = DEFAULT_KEY_PREFIX
    # also answer the shared keys `{prefix}/streams/{id}/...` (one worker alone); off in a fleet, where each
    # worker answers only its own, `{prefix}/streams/{id}/workers/{worker_id}/...` (clients: --workers auto)
    shared_keys: bool = True
    # the session is reachable beyond loopback (or HTTP needs tokens) without --insecure: the config file
    # must guard it (`guards`); the server refuses to start otherwise (server/settings.py)
    guard_required: bool = False


def guards(conf: zenoh.Config) -> list[str]:
    """What in a zenoh config checks who connects: an ACL, mTLS, user/password (none: anyone may)."""

    def value(key: str) -> object:
        return json.loads(conf.get_json(key))

    found = ["ACL"] if value("access_control/enabled") is True else []
    found += ["mTLS"] if value("transport/link/tls/enable_mtls") is True else []
    usrpwd = value("transport/auth/usrpwd/dictionary_file") or value("transport/auth/usrpwd/user")
    return found + (["user/password"] if usrpwd else [])


def require_guard(conf: zenoh.Config, config_file: str | None) -> None:
    """ValueError unless the config guards the session (`guards`)."""
    if not guards(conf):
        raise ValueError(
            f"zenoh config file {config_file}: no ACL (access_control.enabled), mTLS (transport.link.tls"
            ".enable_mtls) or user/password (transport.auth.usrpwd), so anyone who reaches the session may "
            "send into every stream: add one (deploy/zenoh/ has samples), or give --insecure"
        )


def build_config(cfg: ZenohConfig) -> zenoh.Config:
    """A zenoh.Config: the config file (if any), then mode, endpoints and multicast scouting from `cfg`;
    ValueError when `cfg.guard_required` and the file guards nothing."""
    if cfg.mode not in ("peer", "client", "router"):
        raise ValueError(f"zenoh mode: {cfg.mode!r}; expected 'peer', 'client' or 'router'")
    conf = zenoh.Config.from_file(cfg.config_file) if cfg.config_file else zenoh.Config()
    if cfg.guard_required:
        require_guard(conf, cfg.config_file)
    conf.insert_json5("mode", json.dumps(cfg.mode))
    conf.insert_json5("listen/endpoints", json.dumps(list(cfg.listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    return conf


def open_session(cfg: ZenohConfig) -> zenoh.Session:
    """Open a zenoh session built from `cfg` (servers, clients and tests share this) and log how."""
    conf = build_config(cfg)
    session = zenoh.open(conf)
    log.info(
        "zenoh session %s: mode=%s listen=%s connect=%s multicast_scouting=%s config_file=%s",
        session.zid(),
        json.loads(conf.get_json("mode")),
        json.loads(conf.get_json("listen/endpoints")),
        json.loads(conf.get_json("connect/endpoints")),
        json.loads(conf.get_json("scouting/multicast/enabled")),
        cfg.config_file,
    )
    return session


@dataclass(eq=False)
class _Job:
    """One sector waiting for its one answer: a query to reply to, or (query None) a pub/sub sector."""

    key_id: str  # the stream-ID chunk of the key the sector came on
    query: zenoh.Query | None
    stream_id: str | None = None  # validated (from the decoded sector, or the key if it is a valid ID)
    seq: int | None = None

    def error(self, e: ServiceError) -> ErrorReply:
        return ErrorReply.from_error(e, self.stream_id, self.seq)


class ZenohTransport:
    """Queryable `{prefix}/streams/*/sector`, subscriber `{prefix}/streams/*/sectors` (the shared keys, when
    served) and the same under `{prefix}/streams/*/workers/{worker_id}/`; liveliness token
    `{prefix}/workers/{worker_id}/{zid}`; results on `.../{id}/detections`, errors on `.../{id}/errors`."""

    def __init__(
        self,
        submit: Submit,
        cfg: ZenohConfig,
        worker_id: str,
        limits: Limits,
        on_reject: Callable[[ErrorCode], None] | None = None,
    ):
        """`on_reject` hears of every sector answered with an error before it reached `submit` (metrics)."""
        self.submit = submit
        self.on_reject = on_reject
        self.cfg = cfg
        self.worker_id = worker_id
        self.limits = limits
        self.keys = KeySpace(cfg.key_prefix)
        self._session: zenoh.Session | None = None
        self._queryables: list[zenoh.Queryable] = []
        self._subscribers: list[zenoh.Subscriber] = []
        self._token: zenoh.LivelinessToken | None = None
        self._threads: TransportThreads[_Job, Outcome] = TransportThreads(
            "zenoh", worker_id, self._deliver, lambda job: f"stream {job.key_id} seq {job.seq}"
        )

    # ------------------------------------------------------------------------------------ public surface

    def start(self, announce: bool = True) -> None:
        """Open the session, declare queryables and subscribers, then (`announce`) the liveliness token."""
        if self._session is not None or self._threads.closing:
            raise RuntimeError("a ZenohTransport starts once")
        session = open_session(self.cfg)
        self._session = session
        try:
            self._threads.start_sender("replier")
            for (queryable_key, subscriber_key), skip in zip(self.intake_keys, self._skips(), strict=True):
                queryable = session.declare_queryable(
                    queryable_key, zenoh.handlers.FifoChannel(CHANNEL_CAPACITY)
                )
                subscriber = session.declare_subscriber(
                    subscriber_key, zenoh.handlers.FifoChannel(CHANNEL_CAPACITY)
                )
                self._queryables.append(queryable)
                self._subscribers.append(subscriber)
                self._threads.receive(queryable.handler, partial(self._query, skip=skip[0]), "queries")
                self._threads.receive(subscriber.handler, partial(self._sample, skip=skip[1]), "samples")
            if announce:
                self.announce()
        except BaseException:
            self.close(drain_timeout_s=0.0)
            raise
        log.info(
            "zenoh transport for worker %s: queryable, subscriber %s, liveliness %s",
            self.worker_id,
            self.intake_keys,
            self.token_key,
        )

    @property
    def intake_keys(self) -> list[tuple[str, str]]:
        """(queryable, subscriber) key expressions: the worker's own, then the shared ones if served."""
        own = (
            self.keys.worker_sector_queryable(self.worker_id),
            self.keys.worker_sector_subscriber(self.worker_id),
        )
        shared = (self.keys.sector_queryable, self.keys.sector_subscriber)
        return [own, shared] if self.cfg.shared_keys else [own]

    def announce(self) -> None:
        """Declare the liveliness token: clients send this worker sectors from now on (a worker announces
        itself once warmed up, so that no client routes a stream to it while it could only answer NOT_READY).
        Idempotent; nothing once closing."""
        with self._threads.cond:
            if self._session is None or self._threads.closing or self._token is not None:
                return
            self._token = self._session.liveliness().declare_token(self.token_key)
        log.info("zenoh: worker %s announced (%s)", self.worker_id, self.token_key)

    @property
    def session(self) -> zenoh.Session | None:
        """The open session (None before `start` and after `close`): the ROS 2 bridge shares it, since a
        second session could not listen on the same endpoints."""
        return self._session

    @property
    def token_key(self) -> str:
        """The worker's liveliness token: `{prefix}/workers/{worker_id}/{zenoh session ID}`."""
        assert self._session is not None
        return self.keys.worker(self.worker_id, str(self._session.zid()))

    def close(self, drain_timeout_s: float = 10.0) -> None:
        """Withdraw the token, stop taking sectors, send every answer still due (sectors not settled within
        `drain_timeout_s` get NOT_READY), then close the session. Idempotent."""
        session = self._session
        if session is None or not self._threads.begin_close():
            return
        for entity in (self._token, *self._queryables, *self._subscribers):
            if entity is not None:
                entity.undeclare()  # closes the channels: the receivers drain them and stop
        self._threads.join_receivers()
        late = self._threads.drain(drain_timeout_s)
        if late:
            log.warning("zenoh closing: %d sectors unanswered after %.1f s", len(late), drain_timeout_s)
        for job in late:
            why = ServiceError(ErrorCode.NOT_READY, f"worker {self.worker_id}: zenoh transport closed")
            self._threads.send(job, job.error(why))
        self._threads.stop_sender()
        session.close()
        self._session = None
        log.info("zenoh transport for worker %s closed", self.worker_id)

    # ------------------------------------------------------------------------------------------- intake

    def _skips(self) -> list[tuple[zenoh.KeyExpr | None, zenoh.KeyExpr | None]]:
        """Per intake pair, the keys whose sectors it leaves to another pair: a wildcard get or put (e.g.
        `{prefix}/streams/**`) reaches both the worker's own queryable and the shared one; the shared one
        alone takes it (an error: it names no stream), so that it gets one answer, not two."""
        if not self.cfg.shared_keys:
            return [(None, None)]
        shared = (zenoh.KeyExpr(self.keys.sector_queryable), zenoh.KeyExpr(self.keys.sector_subscriber))
        return [shared, (None, None)]

    def _query(self, query: zenoh.Query, skip: zenoh.KeyExpr | None) -> None:
        if skip is not None and query.key_expr.intersects(skip):
            query.drop()  # finalized unanswered: the shared queryable answers it
            return
        self._accept(str(query.key_expr), query.payload, query)

    def _sample(self, sample: zenoh.Sample, skip: zenoh.KeyExpr | None) -> None:
        if sample.kind == zenoh.SampleKind.PUT and not (
            skip is not None and sample.key_expr.intersects(skip)
        ):
            self._accept(str(sample.key_expr), sample.payload, None)

    def _accept(self, key: str, payload: zenoh.ZBytes | None, query: zenoh.Query | None) -> None:
        """Decode and submit one sector; whatever happens, its answer ends up in the outbox once."""
        job = _Job(self.keys.stream_id_of(key), query)
        if job.key_id == PROBE_CHUNK and query is not None:  # a client checking this worker's token: an
            why = ServiceError(ErrorCode.BAD_REQUEST, f"worker {self.worker_id}: a probe, not a sector")
            self._threads.send(job, job.error(why))  # answer from this session, counted nowhere
            return
        if STREAM_ID_RE.fullmatch(job.key_id) and len(job.key_id) <= self.limits.max_string_len:
            job.stream_id = job.key_id
        try:
            data = payload.to_bytes() if payload is not None else b""
            msg = decode_sector(data, self.limits, stream_id=job.key_id)
        except ServiceError as e:
            log.debug("zenoh: rejected a sector on %s: %s", key, e.message)
            self._reject(job, e)
            return
        except Exception as e:  # a bug, not the sender's fault; the sector is answered all the same
            log.exception("zenoh: decoding a sector on %s failed", key)
            self._reject(job, ServiceError(ErrorCode.INTERNAL, f"{type(e).__name__}: {e}"))
            return
        job.stream_id, job.seq = msg.stream_id, msg.seq
        self._threads.admit(job)
        future = submit_or_fail(self.submit, msg)
        future.add_done_callback(partial(self._settled, job))

    def _reject(self, job: _Job, e: ServiceError) -> None:
        if self.on_reject is not None:
            self.on_reject(e.code)
        self._threads.send(job, job.error(e))

    def _settled(self, job: _Job, future: Future[DetectionsReply]) -> None:
        """Done-callback (worker thread): hand the outcome to the replier; never touches zenoh."""
        if self._threads.settle(job):  # else close() already answered it
            self._threads.send(job, _outcome(job, future))

    # ------------------------------------------------------------------------------------------- output

    def _deliver(self, job: _Job, outcome: Outcome) -> None:
        ok = isinstance(outcome, DetectionsReply)
        payload = encode_reply(outcome) if ok else encode_error(outcome)
        if job.query is not None:
            try:  # the reply's QoS (congestion control, priority) follows the query's
                if ok:
                    job.query.reply(job.query.key_expr, payload, encoding=MSGPACK_ENCODING)
                else:
                    job.query.reply_err(payload, encoding=MSGPACK_ENCODING)
            finally:
                job.query.drop()  # finalize: the querier's get completes now
            return
        if job.stream_id is None:
            # a put on a key that names no stream (a wildcard, a bad ID): an error published on its key would
            # reach every subscriber the key matches, every vehicle's for `*`. Dropped (counted as rejected)
            log.debug("zenoh: no answer published for a put on %r: not a stream ID", job.key_id[:64])
            return
        assert self._session is not None  # the session outlives the replier thread
        key = self.keys.detections(job.key_id) if ok else self.keys.errors(job.key_id)
        self._session.put(
            key, payload, encoding=MSGPACK_ENCODING, congestion_control=zenoh.CongestionControl.BLOCK
        )


def _outcome(job: _Job, future: Future[DetectionsReply]) -> Outcome:
    try:
        return future.result(timeout=0)
    except ServiceError as e:
        return job.error(e)
    except Exception as e:
        log.error("zenoh: sector %s seq %s failed: %r", job.key_id, job.seq, e)
        return job.error(ServiceError(ErrorCode.INTERNAL, f"{type(e).__name__}: {e}"))
