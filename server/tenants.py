"""Tenants: who shares a worker, and the shares that keep one tenant from starving the others.

A stream's tenant is a function of its stream ID, so HTTP, zenoh and the ROS 2 bridge count alike: with a
token file, the longest prefix of its stream tokens that the ID starts with (`TokenFile.tenant_of`); else
(no token file, or an ID that no stream token covers: an admin token's stream, a zenoh or ROS 2 bridge
stream outside every prefix) the ID up to and including its first '.' ("fleet-a.car-7" -> "fleet-a."), or
the whole ID when it has no '.' ("car1": a tenant of its own). A stream keeps the tenant it started with.

Each tenant may hold at most `tenant_max_streams` live streams (a hard cap: a stream is long-lived, so a
share it holds cannot be handed to another tenant later). The queue is shared work-conservingly: a tenant
alone may fill it, but each tenant is guaranteed `tenant_queue_size` sectors (and the same fraction of
`max_queued_points`): when the queue is full, a sector of a tenant within its guarantee pushes out the
newest queued sector of a tenant beyond its own (answered `overloaded`), instead of being refused. The
device loop's batches take the streams' heads round-robin between tenants (`server.scheduler.fair_order`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

from contract import ErrorCode, ServiceError

if TYPE_CHECKING:
    from server.admission import Backlog


class Queued(Protocol):
    """A queued sector as the push-out plan sees it (server.streams.Pending)."""

    points: Any  # (N, C) float32 tensor


Q = TypeVar("Q", bound=Queued)


def tenant_of_id(stream_id: str) -> str:
    """The tenant of a stream no token prefix covers: its ID up to and including the first '.', or the whole
    ID when it has none."""
    head, dot, _ = stream_id.partition(".")
    return head + dot if dot else stream_id


@dataclass
class TenantUse:
    sectors: int = 0  # queued (not running)
    points: int = 0


@dataclass
class TenantQueue:
    """Each tenant's queued sectors and points against its guaranteed share (the totals: `Backlog`)."""

    share_sectors: int  # tenant_queue_size
    share_points: int
    use: dict[str, TenantUse] = field(default_factory=dict)

    def add(self, tenant: str, n_points: int) -> None:
        u = self.use.setdefault(tenant, TenantUse())
        u.sectors += 1
        u.points += n_points

    def remove(self, tenant: str, n_points: int) -> None:
        u = self.use[tenant]
        u.sectors -= 1
        u.points -= n_points
        if u.sectors == 0:
            del self.use[tenant]  # bounded by the tenants with queued sectors

    def sectors(self, tenant: str) -> int:
        u = self.use.get(tenant)
        return 0 if u is None else u.sectors

    def within_share(self, tenant: str, n_points: int) -> bool:
        """Whether one more sector of n_points keeps the tenant within its guarantee."""
        u = self.use.get(tenant, TenantUse())
        return u.sectors + 1 <= self.share_sectors and u.points + n_points <= self.share_points


def half(n: int) -> int:
    """A default share: half of a total, at least 1."""
    return max(1, n // 2)


def plan_push_out(
    queue: TenantQueue,
    backlog: Backlog,
    tenant: str,
    n_points: int,
    queued: Callable[[str], list[Q]],
) -> list[Q] | None:
    """The queued sectors to push out so that a sector of `tenant` with n_points fits a full queue: the
    newest of the tenant furthest beyond its guarantee first, only while that tenant stays beyond it. None
    when the tenant is beyond its own guarantee, or when pushing out what is allowed would not make room.
    `queued(t)`: t's queued sectors, newest first. Plans only; the caller pushes them out."""
    if not queue.within_share(tenant, n_points):
        return None
    use = {t: TenantUse(u.sectors, u.points) for t, u in queue.use.items() if t != tenant}
    taken: dict[str, list[Q]] = {}
    sectors, points, plan = backlog.sectors, backlog.points, []
    while sectors >= backlog.max_sectors or (sectors and points + n_points > backlog.max_points):
        over = [t for t, u in use.items() if u.sectors > queue.share_sectors or u.points > queue.share_points]
        if not over:
            return None
        victim = max(over, key=lambda t: (use[t].sectors - queue.share_sectors, use[t].points))
        candidates = taken.setdefault(victim, queued(victim))
        if not candidates:  # cannot happen while the counts match the queue; refuse rather than guess
            return None
        p = candidates.pop(0)
        n = int(p.points.shape[0])
        plan.append(p)
        sectors, points = sectors - 1, points - n
        use[victim].sectors -= 1
        use[victim].points -= n
    return plan


def pushed_out_error(victim: str, queue: TenantQueue, queue_size: int, retry_s: float) -> ServiceError:
    """The answer of a sector of tenant `victim` pushed out of a full queue for another tenant's sector
    (which tenant is not said: tenants do not learn of each other)."""
    return ServiceError(
        ErrorCode.OVERLOADED,
        f"queue full: tenant {victim!r} held {queue.sectors(victim)} of the {queue_size} queued sectors, "
        f"beyond its share (tenant_queue_size={queue.share_sectors}), and a tenant within its share needed "
        f"the room; retry after {retry_s:.2f} s",
        retry_after_s=retry_s,
    )
