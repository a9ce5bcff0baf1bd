"""Which zenoh sessions are workers, and which worker owns a stream.

A client keeps the live workers' liveliness tokens (`{prefix}/workers/{worker_id}/{zid}`) and takes a
sector's answer only from a session that holds one (and, when the client is pinned to a worker or addresses
one, holds that worker's). Any session on the network could declare a queryable and answer first with forged
boxes; under the ACL of deploy/zenoh/ only workers may declare tokens and queryables, and this check is the
client's half of that (docs/security.md).

In a fleet (`--workers auto`), `StreamOwners` gives each stream its rendezvous owner among the live workers
(`contract.stream_owner`) and remembers where each stream's last sector went, so that the first sector after
a move is sent as a reset: the new owner starts the stream cold, and a worker the stream comes back to
drops the state it kept from before."""

from __future__ import annotations

import threading
import time

import zenoh

from clients.base import TransportError
from contract import KeySpace, stream_owner


class LiveWorkers:
    """The live workers under a prefix, kept by a liveliness subscriber: zenoh session ID -> worker ID."""

    def __init__(self, session: zenoh.Session, keys: KeySpace):
        self.session = session
        self.keys = keys
        self._by_zid: dict[str, str] = {}
        self._changed = threading.Condition()
        self._subscriber = session.liveliness().declare_subscriber(
            keys.worker("*", "*"), self._on_token, history=True
        )

    def _on_token(self, sample: zenoh.Sample) -> None:  # zenoh's thread: only the dict, no zenoh call
        found = self.keys.worker_of(str(sample.key_expr))
        if found is None:
            return
        worker_id, zid = found
        with self._changed:
            if sample.kind == zenoh.SampleKind.PUT:
                self._by_zid[zid] = worker_id
            else:
                self._by_zid.pop(zid, None)
            self._changed.notify_all()

    def refresh(self, timeout_s: float) -> None:
        """Ask for the tokens now (a worker may answer before its token's sample reached the subscriber).
        It only adds: a liveliness get may come back short (seen under the ACL), so only the subscriber's
        DELETE, which zenoh sends when a token is withdrawn or its session is lost, removes a worker."""
        found: dict[str, str] = {}
        for reply in self.session.liveliness().get(self.keys.worker("*", "*"), timeout=timeout_s):
            token = self.keys.worker_of(str(reply.ok.key_expr)) if reply.ok is not None else None
            if token is not None:
                found[token[1]] = token[0]
        with self._changed:
            self._by_zid.update(found)

    def wait_gone(self, worker_id: str, timeout_s: float) -> bool:
        """Whether `worker_id` holds no token any more, waiting up to `timeout_s` for its DELETE (a get that
        failed because its worker died may end before the token's DELETE reaches this session)."""
        with self._changed:
            return self._changed.wait_for(lambda: worker_id not in self._by_zid.values(), timeout_s)

    def worker_at(self, zid: str) -> str | None:
        """The worker ID of the session `zid`, or None if that session holds no worker token."""
        with self._changed:
            return self._by_zid.get(zid)

    def ids(self) -> list[str]:
        with self._changed:
            return sorted(set(self._by_zid.values()))

    def close(self) -> None:
        self._subscriber.undeclare()


class StreamOwners:
    """Each stream's worker under `--workers auto`: its rendezvous owner among the live workers."""

    def __init__(self, live: LiveWorkers, refresh_timeout_s: float):
        self.live = live
        self.refresh_timeout_s = refresh_timeout_s
        self._last: dict[str, str] = {}  # stream ID -> the worker its last sector was sent to
        self._lock = threading.Lock()
        self.moves = 0  # sectors sent to another worker than the stream's previous one (sent as resets)

    def route(self, stream_id: str) -> tuple[str, bool]:
        """(the stream's owner now, whether the stream moves to it with this sector)."""
        workers = self.live.ids() or self._wait_for_workers()
        worker = stream_owner(stream_id, workers)
        if worker is None:
            raise TransportError(f"zenoh: no live worker under {self.live.keys.prefix}")
        with self._lock:
            previous, self._last[stream_id] = self._last.get(stream_id), worker
            moved = previous is not None and previous != worker
            self.moves += moved
        return worker, moved

    def _wait_for_workers(self) -> list[str]:
        """None seen yet: a session just opened learns the tokens from its router over a few ms, and a get
        asked before that answers with none. Ask again until one shows, for `refresh_timeout_s` at most."""
        deadline = time.monotonic() + self.refresh_timeout_s
        while not (workers := self.live.ids()) and time.monotonic() < deadline:
            self.live.refresh(self.refresh_timeout_s)
            time.sleep(0.05)
        return workers

    def gone(self, worker: str) -> bool:
        """Whether `worker` has left (its token is gone), waiting `refresh_timeout_s` at most to hear so."""
        return self.live.wait_gone(worker, self.refresh_timeout_s)
