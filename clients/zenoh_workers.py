"""Which zenoh sessions are workers, and which worker owns a stream.

A client keeps the workers' liveliness tokens (`{prefix}/workers/{worker_id}/{zid}`), each a claim: "the
session `zid` is worker `worker_id`". zenoh does not say which session declared a token, so without the ACL
of deploy/zenoh/ anyone may declare any claim; the client therefore holds claims, never a table keyed by
session ID alone, and checks each one:

- A claim is kept as a (worker ID, session ID) pair: a second worker ID claiming a session's ID adds a
  second pair and displaces nothing, and its withdrawal removes only its own pair.
- Each new claim is probed once: a get on the claimed worker's own sector key (`KeySpace.probe`) must be
  answered by the claimed session (zenoh names every reply's session). A worker answers it; a made-up
  worker ID (no queryable), a made-up session ID or another session's ID (another replier) is refuted.
  Only confirmed claims are routed to (`ids`); an answer counts when its session holds an unrefuted claim
  (that worker's, when the client is pinned to a worker or addresses one).
- The table holds MAX_CLAIMS pairs (4,096), refuted ones too, so that none is probed twice: beyond it the
  oldest refuted pair makes room, else (a flood of unchecked claims) the new claim is dropped and
  counted (`dropped`, logged at most every few seconds). A fleet has tens of workers.

What the ACL alone gives: a rogue session can still declare a queryable on a worker ID of its own and a
token naming itself, pass the probe and be routed streams (docs/security.md).

In a fleet (`--workers auto`), `StreamOwners` gives each stream its rendezvous owner among the confirmed
workers (`contract.stream_owner`) and remembers where each stream's last sector went, so that the first
sector after a move is sent as a reset: the new owner starts the stream cold, and a worker the stream comes
back to drops the state it kept from before."""

from __future__ import annotations

import asyncio
import enum
import logging
import queue
import threading
import time

import zenoh

from clients.base import TransportError
from contract import MSGPACK, KeySpace, stream_owner

log = logging.getLogger(__name__)
MSGPACK_ENCODING = zenoh.Encoding(MSGPACK)

MAX_CLAIMS = (
    4096  # worker tokens a client keeps, refuted ones too (so none is probed twice); a fleet has tens
)
WARN_EVERY_S = 5.0
Claim = tuple[str, str]  # (worker ID, zenoh session ID)


class State(enum.Enum):
    PENDING = "pending"  # probe not answered yet
    CONFIRMED = "confirmed"  # the claimed session answered on the claimed worker's keys
    REFUTED = "refuted"  # nobody, or another session, answered


class LiveWorkers:
    """The workers' claims under a prefix, kept by a liveliness subscriber and checked by probes."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: KeySpace,
        probe_timeout_s: float = 2.0,
        max_claims: int = MAX_CLAIMS,
    ):
        self.session = session
        self.keys = keys
        self.probe_timeout_s = probe_timeout_s
        self.max_claims = max_claims
        self.dropped = 0  # claims not kept: the table was full of unrefuted claims
        self._claims: dict[Claim, State] = {}  # in the order first seen
        self._pending = 0  # claims whose probe has not ended
        self._changed = threading.Condition()
        self._closed = False
        self._last_warning = -WARN_EVERY_S
        self._to_probe: queue.SimpleQueue[Claim | None] = queue.SimpleQueue()
        self._prober = threading.Thread(target=self._probe_loop, name="zenoh-worker-probes", daemon=True)
        self._prober.start()
        self._subscriber = session.liveliness().declare_subscriber(
            keys.worker("*", "*"), self._on_token, history=True
        )

    # ------------------------------------------------------------------------------------------- claims

    def _on_token(self, sample: zenoh.Sample) -> None:  # zenoh's thread: only the table, no zenoh call
        found = self.keys.worker_of(str(sample.key_expr))
        if found is None:
            return
        with self._changed:
            if sample.kind == zenoh.SampleKind.PUT:
                self._add(found)
            else:
                if self._claims.pop(found, None) is State.PENDING:
                    self._pending -= 1
            self._changed.notify_all()

    def _add(self, claim: Claim) -> None:
        """Keep a new claim and queue its probe; the lock is held."""
        if claim in self._claims or self._closed:
            return
        if len(self._claims) >= self.max_claims:
            refuted = next((c for c, s in self._claims.items() if s is State.REFUTED), None)
            if refuted is None:
                self.dropped += 1
                now = time.monotonic()
                if now - self._last_warning >= WARN_EVERY_S:
                    self._last_warning = now
                    log.warning(
                        "zenoh: %d worker tokens held, the most kept (MAX_CLAIMS); %d dropped so far, "
                        "the last %s (a flood of tokens? the ACL of deploy/zenoh/ keeps them out)",
                        len(self._claims),
                        self.dropped,
                        self.keys.worker(*claim),
                    )
                return
            del self._claims[refuted]
        self._claims[claim] = State.PENDING
        self._pending += 1
        self._to_probe.put(claim)

    def refresh(self, timeout_s: float) -> None:
        """Ask for the tokens now (a worker may answer before its token's sample reached the subscriber).
        It only adds: a liveliness get may come back short (seen under the ACL), so only the subscriber's
        DELETE, which zenoh sends when a token is withdrawn or its session is lost, removes a claim."""
        found: list[Claim] = []
        done = threading.Event()

        def on_reply(reply: zenoh.Reply) -> None:  # zenoh's thread: never waits (a full channel would)
            claim = self.keys.worker_of(str(reply.ok.key_expr)) if reply.ok is not None else None
            if claim is not None and len(found) < 2 * self.max_claims:
                found.append(claim)

        handler = zenoh.handlers.Callback(on_reply, done.set)
        self.session.liveliness().get(self.keys.worker("*", "*"), handler, timeout=timeout_s)
        done.wait(timeout_s + 1.0)
        with self._changed:
            for claim in list(found):
                self._add(claim)

    # ------------------------------------------------------------------------------------------- probes

    def _probe_loop(self) -> None:
        """One probe at a time, each a get with a timeout: a made-up worker's ends at once (no queryable),
        a worker answers in a few ms; no zenoh callback runs Python here."""
        while (claim := self._to_probe.get()) is not None:
            with self._changed:
                if self._closed:
                    return
                if self._claims.get(claim) is not State.PENDING:
                    continue
            try:
                replies = self.session.get(
                    self.keys.probe(claim[0]),
                    consolidation=zenoh.ConsolidationMode.NONE,
                    timeout=self.probe_timeout_s,
                )
                confirmed = any(_answered_by(reply, claim[1]) for reply in replies)
            except zenoh.ZError as e:  # the session is closing
                log.debug("zenoh: could not probe %s: %s", claim, e)
                confirmed = False
            self._settle(claim, confirmed)

    def _settle(self, claim: Claim, confirmed: bool) -> None:
        with self._changed:
            if self._claims.get(claim) is State.PENDING:
                self._claims[claim] = State.CONFIRMED if confirmed else State.REFUTED
                self._pending -= 1
                self._changed.notify_all()
        if not confirmed:
            log.debug("zenoh: worker token %s refuted by its probe", claim)

    # ------------------------------------------------------------------------------------------ queries

    def holds(self, zid: str, worker_id: str | None = None) -> bool:
        """Whether the session `zid` holds an unrefuted claim (to be `worker_id`, when given)."""
        with self._changed:
            return any(
                z == zid and (worker_id is None or w == worker_id) and s is not State.REFUTED
                for (w, z), s in self._claims.items()
            )

    def ids(self) -> list[str]:
        """The confirmed workers' IDs: where streams may be routed."""
        with self._changed:
            return self._confirmed()

    def _confirmed(self) -> list[str]:
        return sorted({w for (w, _), s in self._claims.items() if s is State.CONFIRMED})

    def claims(self) -> dict[Claim, State]:
        with self._changed:
            return dict(self._claims)

    def routable(self) -> list[str] | None:
        """The confirmed workers, once no claim awaits its probe and one is confirmed (None: not yet), so
        that every client routes a stream to the same owner from its first sector."""
        with self._changed:
            return self._routable()

    def _routable(self) -> list[str] | None:
        return None if self._pending else (self._confirmed() or None)

    def wait_routable(self, timeout_s: float) -> list[str]:
        """`routable`, waiting up to `timeout_s` for the probes to end and asking for the tokens again while
        none is known (a session just opened learns the tokens from its router over a few ms, and a get
        asked before that answers with none); at the deadline, whatever is confirmed then."""
        deadline = time.monotonic() + timeout_s
        while self.routable() is None and (left := deadline - time.monotonic()) > 0:
            with self._changed:
                probing = self._pending > 0
            if not probing:  # while probes run, their answers are what is waited for
                self.refresh(min(left, 0.5))
            with self._changed:
                self._changed.wait_for(
                    lambda: self._routable() is not None, max(0.0, min(0.2, deadline - time.monotonic()))
                )
        return self.ids()

    def wait_gone(self, worker_id: str, timeout_s: float) -> bool:
        """Whether `worker_id` holds no unrefuted claim any more, waiting up to `timeout_s` for its DELETE (a
        get that failed because its worker died may end before the token's DELETE reaches this session)."""

        def gone() -> bool:
            return not any(w == worker_id and s is not State.REFUTED for (w, _), s in self._claims.items())

        with self._changed:
            return self._changed.wait_for(gone, timeout_s)

    def close(self) -> None:
        with self._changed:
            self._closed = True
        self._to_probe.put(None)
        self._subscriber.undeclare()
        self._prober.join(5.0)


def _answered_by(reply: zenoh.Reply, zid: str) -> bool:
    """Whether the worker's session `zid` answered (its msgpack error; zenoh's own timeout names a session
    too, but is not the worker's answer)."""
    rid = reply.replier_id
    said = reply.ok is not None or (reply.err is not None and reply.err.encoding == MSGPACK_ENCODING)
    return said and rid is not None and str(rid.zid) == zid


class StreamOwners:
    """Each stream's worker under `--workers auto`: its rendezvous owner among the confirmed workers."""

    def __init__(self, live: LiveWorkers, refresh_timeout_s: float):
        self.live = live
        self.refresh_timeout_s = refresh_timeout_s
        self._last: dict[str, str] = {}  # stream ID -> the worker its last sector was sent to
        self._lock = threading.Lock()
        self._waiting: asyncio.Task[list[str]] | None = None  # the async paths' one wait for a worker
        self.moves = 0  # sectors sent to another worker than the stream's previous one (sent as resets)

    def route(self, stream_id: str) -> tuple[str, bool]:
        """(the stream's owner now, whether the stream moves to it with this sector); blocks up to
        `refresh_timeout_s` while no worker is known."""
        return self._place(stream_id, self.live.routable() or self.live.wait_routable(self.refresh_timeout_s))

    async def route_async(self, stream_id: str) -> tuple[str, bool]:
        """`route` without blocking the event loop: while no worker is known, every sector waits for the
        same one bounded wait (in a thread), then is routed or gets its TransportError."""
        workers = self.live.routable()
        if not workers:
            loop = asyncio.get_running_loop()
            with self._lock:
                task = self._waiting
                if task is None or task.done() or task.get_loop() is not loop:
                    wait = asyncio.to_thread(self.live.wait_routable, self.refresh_timeout_s)
                    task = self._waiting = loop.create_task(wait)
            workers = await asyncio.shield(task)  # a cancelled sector leaves the others' wait alone
        return self._place(stream_id, workers)

    def _place(self, stream_id: str, workers: list[str]) -> tuple[str, bool]:
        worker = stream_owner(stream_id, workers)
        if worker is None:
            raise TransportError(f"zenoh: no live worker under {self.live.keys.prefix}")
        with self._lock:
            previous, self._last[stream_id] = self._last.get(stream_id), worker
            moved = previous is not None and previous != worker
            self.moves += moved
        return worker, moved

    def gone(self, worker: str) -> bool:
        """Whether `worker` has left (its token is gone), waiting `refresh_timeout_s` at most to hear so."""
        return self.live.wait_gone(worker, self.refresh_timeout_s)
