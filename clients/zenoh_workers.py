"""Which zenoh sessions are workers: a client keeps the live workers' liveliness tokens
(`{prefix}/workers/{worker_id}/{zid}`) and takes a sector's answer only from a session that holds one (and,
when the client is pinned to a worker, holds that worker's). Any session on the network could declare a
queryable and answer first with forged boxes; under the ACL of deploy/zenoh/ only workers may declare tokens
and queryables, and this check is the client's half of that (docs/security.md)."""

from __future__ import annotations

import threading

import zenoh

from contract import KeySpace


class LiveWorkers:
    """The live workers under a prefix, kept by a liveliness subscriber: zenoh session ID -> worker ID."""

    def __init__(self, session: zenoh.Session, keys: KeySpace):
        self.session = session
        self.keys = keys
        self._by_zid: dict[str, str] = {}
        self._lock = threading.Lock()
        self._subscriber = session.liveliness().declare_subscriber(
            keys.worker("*", "*"), self._on_token, history=True
        )

    def _on_token(self, sample: zenoh.Sample) -> None:  # zenoh's thread: only the dict, no zenoh call
        found = self.keys.worker_of(str(sample.key_expr))
        if found is None:
            return
        worker_id, zid = found
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._by_zid[zid] = worker_id
            else:
                self._by_zid.pop(zid, None)

    def refresh(self, timeout_s: float) -> None:
        """Ask for the tokens now (a worker may answer before its token's sample reached the subscriber)."""
        found: dict[str, str] = {}
        for reply in self.session.liveliness().get(self.keys.worker("*", "*"), timeout=timeout_s):
            token = self.keys.worker_of(str(reply.ok.key_expr)) if reply.ok is not None else None
            if token is not None:
                found[token[1]] = token[0]
        with self._lock:
            self._by_zid.update(found)

    def worker_at(self, zid: str) -> str | None:
        """The worker ID of the session `zid`, or None if that session holds no worker token."""
        with self._lock:
            return self._by_zid.get(zid)

    def ids(self) -> list[str]:
        with self._lock:
            return sorted(set(self._by_zid.values()))

    def close(self) -> None:
        self._subscriber.undeclare()
