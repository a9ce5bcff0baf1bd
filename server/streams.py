"""The stream table: one entry per stream ID with its model state, sequence numbers and queued sectors.

Not thread-safe by itself: the Worker holds its lock around every call. A stream starts on its first sector
(or on a sector with the reset flag), ends on request, and is evicted after `idle_timeout_s` without sectors.
Sequence numbers: a sector must come after every sector of its stream already admitted (queued or done),
unless it carries the reset flag; a gap (seq > last + 1) is accepted and reported when the sector runs.

States: `new_state` gives a new stream its engine state (`model.engine.EngineState`: opaque here; a
fixed-shape engine's is a device slot) and `drop_state` gives it back when the stream leaves the table
(ended or evicted). A stream ended while its sector runs gives its state back when that sector has finished
(`finished`), so the step in progress never reads a slot another stream has taken meanwhile.

Tenants (`server.tenants`): each stream belongs to the tenant `tenant_of` gives its ID when it starts; a
tenant holds at most `tenant_max_streams` live streams (beyond: OVERLOADED, naming the tenant).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

import torch

from contract import DetectionsReply, ErrorCode, SectorMessage, ServiceError
from model.engine import EngineState, StatesExhausted
from server.tenants import tenant_of_id


@dataclass
class Pending:
    """One admitted sector waiting for (or in) a forward pass."""

    msg: SectorMessage
    points: torch.Tensor  # (N, C) float32, CPU, validated
    future: Future[DetectionsReply]
    transport: str
    entry: StreamEntry
    submitted: float  # time.monotonic()
    deadline: float  # time.monotonic() by which it must have started


@dataclass
class StreamEntry:
    stream_id: str
    created_unix: float
    last_seen: float  # time.monotonic() of the last sector admitted or answered
    state: EngineState  # the engine's state of this stream
    last_seq: int | None = None  # seq of the last sector that ran
    last_timestamp_ns: int | None = None  # its sensor time
    last_admitted: int | None = None  # seq of the newest sector queued or run (stale checks)
    pending: deque[Pending] = field(default_factory=deque)
    running: bool = False  # a sector of this stream is in the current forward pass
    sectors: int = 0  # sectors run
    gaps: int = 0  # sectors missed in total
    tenant: str = ""  # whose stream it is (server/tenants.py), fixed when it starts

    @property
    def idle(self) -> bool:
        return not self.pending and not self.running

    def forget_failed(self) -> None:
        """A queued or running sector failed: it no longer counts for the stale check."""
        self.last_admitted = self.pending[-1].msg.seq if self.pending else self.last_seq

    def summary(self, now: float) -> dict[str, Any]:
        return {
            "stream_id": self.stream_id,
            "sectors": self.sectors,
            "last_seq": self.last_seq,
            "last_timestamp_ns": self.last_timestamp_ns,
            "gaps": self.gaps,
            "pending": len(self.pending) + int(self.running),
            "buffered_sectors": self.state.buffered_sectors,
            "created_unix": self.created_unix,
            "idle_s": round(now - self.last_seen, 3),
        }


class StreamTable:
    def __init__(
        self,
        max_streams: int,
        idle_timeout_s: float,
        on_evict: Callable[[str], None] | None,
        new_state: Callable[[], EngineState],
        drop_state: Callable[[EngineState], None],
        tenant_of: Callable[[str], str] = tenant_of_id,
        tenant_max_streams: int | None = None,  # None: max_streams (no cap per tenant)
    ):
        self.max_streams = max_streams
        self.tenant_of = tenant_of
        self.tenant_max_streams = max_streams if tenant_max_streams is None else tenant_max_streams
        self.tenant_streams: dict[str, int] = {}  # live streams per tenant (tenants with none: absent)
        self.on_evict = on_evict
        self.idle_timeout_s = idle_timeout_s
        self.new_state = new_state
        self.drop_state = drop_state
        self.entries: dict[str, StreamEntry] = {}

    def __len__(self) -> int:
        return len(self.entries)

    def get(self, stream_id: str) -> StreamEntry | None:
        return self.entries.get(stream_id)

    def tenant(self, stream_id: str) -> str:
        """The tenant of a live stream (the one it started with), or of a new stream of this ID."""
        entry = self.entries.get(stream_id)
        return self.tenant_of(stream_id) if entry is None else entry.tenant

    def admit(self, msg: SectorMessage, now: float, tenant: str | None = None) -> StreamEntry:
        """The stream's entry (created if new, of `tenant`: by default `tenant_of` its ID) after the stale
        check; raises ServiceError."""
        entry = self.entries.get(msg.stream_id)
        if entry is None:
            entry = self._create(msg.stream_id, now, tenant or self.tenant_of(msg.stream_id))
        elif not msg.reset and entry.last_admitted is not None and msg.seq <= entry.last_admitted:
            raise ServiceError(
                ErrorCode.STALE_SEQUENCE,
                f"seq: {msg.seq} is stale or a duplicate for stream {msg.stream_id!r}; expected a seq "
                f"greater than {entry.last_admitted} (or the reset flag to start the stream over)",
                "seq",
            )
        entry.last_admitted = msg.seq
        entry.last_seen = now
        return entry

    def _create(self, stream_id: str, now: float, tenant: str) -> StreamEntry:
        if len(self.entries) >= self.max_streams:
            self.evict_idle(now)
        if len(self.entries) >= self.max_streams:
            raise self._full(stream_id)
        if self.tenant_streams.get(tenant, 0) >= self.tenant_max_streams:
            self.evict_idle(now)
        if self.tenant_streams.get(tenant, 0) >= self.tenant_max_streams:
            raise self._tenant_full(stream_id, tenant)
        try:
            state = self.new_state()
        except StatesExhausted:  # sized by max_streams; a stream ended mid-step gives its slot back after it
            raise ServiceError(
                ErrorCode.OVERLOADED,
                f"stream_id: cannot start stream {stream_id!r}: all stream-state slots (max_streams="
                f"{self.max_streams}) are in use; an ended stream's slot comes back once its running sector "
                "has finished: retry shortly",
                "stream_id",
                retry_after_s=0.1,
            ) from None
        entry = StreamEntry(stream_id, time.time(), now, state, tenant=tenant)
        self.entries[stream_id] = entry
        self.tenant_streams[tenant] = self.tenant_streams.get(tenant, 0) + 1
        return entry

    def _pop(self, stream_id: str) -> StreamEntry:
        """Take a live stream out of the table (its tenant holds one stream less)."""
        entry = self.entries.pop(stream_id)
        left = self.tenant_streams.pop(entry.tenant) - 1
        if left:
            self.tenant_streams[entry.tenant] = left
        return entry

    def _tenant_full(self, stream_id: str, tenant: str) -> ServiceError:
        return ServiceError(
            ErrorCode.OVERLOADED,
            f"stream_id: cannot start stream {stream_id!r}: its tenant {tenant!r} holds "
            f"{self.tenant_streams[tenant]} live streams, the limit per tenant (tenant_max_streams="
            f"{self.tenant_max_streams}); end one of its streams or retry once its idle streams are evicted "
            f"(after {self.idle_timeout_s:g} s without sectors)",
            "stream_id",
            retry_after_s=self.idle_timeout_s,
        )

    def _full(self, stream_id: str) -> ServiceError:
        return ServiceError(
            ErrorCode.OVERLOADED,
            f"stream_id: cannot start stream {stream_id!r}: {len(self.entries)} live streams, the limit "
            f"(max_streams={self.max_streams}); end a stream or retry once idle streams are evicted "
            f"(after {self.idle_timeout_s:g} s without sectors)",
            "stream_id",
            retry_after_s=self.idle_timeout_s,
        )

    def end(self, stream_id: str) -> StreamEntry:
        if stream_id not in self.entries:
            raise self.unknown(stream_id)
        entry = self._pop(stream_id)
        if not entry.running:  # else `finished` gives its state back
            self.drop_state(entry.state)
        return entry

    def finished(self, entry: StreamEntry) -> bool:
        """After the entry's sector ran (or failed): True if the stream is still live; if it was ended
        meanwhile, its state goes back now."""
        if self.entries.get(entry.stream_id) is entry:
            return True
        self.drop_state(entry.state)
        return False

    def unknown(self, stream_id: str) -> ServiceError:
        return ServiceError(
            ErrorCode.UNKNOWN_STREAM,
            f"stream_id: no live stream {stream_id!r} (never started, ended, or evicted after "
            f"{self.idle_timeout_s:g} s idle)",
            "stream_id",
        )

    def evict_idle(self, now: float) -> list[str]:
        """Drop streams without queued or running sectors that were idle longer than the timeout."""
        old = [sid for sid, e in self.entries.items() if e.idle and now - e.last_seen > self.idle_timeout_s]
        for sid in old:
            self.drop_state(self._pop(sid).state)
            if self.on_evict is not None:
                self.on_evict(sid)
        return old


def queued_of(entries: Iterable[StreamEntry], tenant: str) -> list[Pending]:
    """A tenant's queued sectors, newest first."""
    queued = [p for e in entries if e.tenant == tenant for p in e.pending]
    return sorted(queued, key=lambda p: p.submitted, reverse=True)
