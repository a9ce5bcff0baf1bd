"""Which worker owns a stream: rendezvous (highest-random-weight) hashing over the live workers' IDs.

Every client computes the same owner from the same set of worker IDs, with no coordination: each (worker,
stream) pair gets a pseudo-random weight and the worker with the highest weight owns the stream. When a
worker leaves, only its own streams move (each to the worker with its next-highest weight); when one joins,
it takes the streams it now weighs highest on, about 1/N of them. The weight is a fixed hash (blake2b), not
Python's `hash`, so that every process and every version agrees.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable


def weight(worker_id: str, stream_id: str) -> int:
    """The pair's weight: 64 bits of blake2b over both IDs (a NUL between them: no ID contains one)."""
    digest = hashlib.blake2b(f"{worker_id}\0{stream_id}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big")


def stream_owner(stream_id: str, workers: Iterable[str]) -> str | None:
    """The worker that owns `stream_id` among `workers` (None when there is none). Ties, which need equal
    64-bit weights, go to the smaller worker ID, so that the answer never depends on the order given."""
    return max(workers, key=lambda w: (weight(w, stream_id), _reverse(w)), default=None)


def _reverse(worker_id: str) -> tuple[int, ...]:
    return tuple(-b for b in worker_id.encode())
