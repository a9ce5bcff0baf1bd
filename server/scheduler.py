"""When the device loop runs a batch, and how many sectors it takes: a pure function of the queue.

A batch takes at most one sector per stream (the streams' oldest, oldest first) and at most `max_batch`.
The oldest sector may wait up to `max_wait` for a fuller batch; it runs at once when every live stream (up
to `max_batch`) has a sector queued, or when the worker is closing.

A fixed-shape engine pads a batch to its bucket (1, 2, 4, ... streams: the batch buckets its description
gives, `model.engine.EngineInfo`), and a padding stream costs about as much as a real one. So, while
`max_wait` allows, it also runs at once a batch that fills a bucket exactly when the streams not queued yet
could not fill the next bucket up (e.g. 4 queued of 5 live streams: 4 now, not 5 padded to 8 later); a
batch that just misses a bucket (3 of 5) waits.

Which streams' sectors a batch takes is fair between tenants (server/tenants.py): `fair_order` lists the
queued streams round-robin by tenant (each tenant's oldest first, the tenant with the oldest sector first),
so a tenant with many queued streams gets no more of a batch than one with few, while they have sectors.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class Dispatch:
    sectors: int  # take this many streams' oldest sectors now


@dataclass(frozen=True)
class Wait:
    seconds: float  # decide again after this long (or when a sector arrives)


def decide(
    heads: int,
    live: int,
    waited_s: float,
    max_wait_s: float,
    max_batch: int,
    buckets: Sequence[int] | None = None,
    closing: bool = False,
) -> Dispatch | Wait:
    """heads: streams with a sector queued (>= 1); live: streams in the table; waited_s: how long the oldest
    queued sector has waited; buckets: the engine's batch buckets (None: a batch runs unpadded)."""
    if heads < 1:
        raise ValueError(f"heads: {heads}; expected at least one stream with a queued sector")
    take = min(heads, max_batch)
    target = min(max_batch, live)  # the fullest batch the live streams can make
    if heads >= target or closing or waited_s >= max_wait_s:
        return Dispatch(take)
    if buckets is not None and heads in buckets and _next_bucket(heads, buckets) > target:
        return Dispatch(heads)  # a full bucket now; waiting could only pad a bigger one
    return Wait(max_wait_s - waited_s)


def fair_order(tenants: Sequence[str]) -> list[int]:
    """The queued streams' order for a batch: `tenants[i]` is the tenant of the i-th oldest head; the result
    takes each tenant's heads in turn (round-robin, tenants by their oldest head), so the first k of it give
    every tenant with heads an equal part of k (max-min fair), the oldest of each tenant first."""
    by_tenant: dict[str, list[int]] = {}
    for i, tenant in enumerate(tenants):
        by_tenant.setdefault(tenant, []).append(i)
    rounds = max((len(heads) for heads in by_tenant.values()), default=0)
    return [heads[r] for r in range(rounds) for heads in by_tenant.values() if r < len(heads)]


def _next_bucket(n: int, buckets: Sequence[int]) -> int:
    """The smallest bucket above n (past the largest: infinitely large)."""
    return min((b for b in buckets if b > n), default=2**62)


def bucket_of(sectors: int, buckets: Sequence[int] | None) -> int:
    """The batch size a batch of `sectors` runs at: its bucket, or itself when unpadded."""
    if buckets is None:
        return sectors
    fits = [b for b in buckets if b >= sectors]
    if not fits:
        raise ValueError(f"sectors: {sectors} in one batch; the largest bucket is {max(buckets)}")
    return min(fits)


def batch_fill(sectors: int, buckets: Sequence[int] | None) -> float:
    """Sectors / the batch size they run at (1.0: no padding stream)."""
    return sectors / bucket_of(sectors, buckets)
