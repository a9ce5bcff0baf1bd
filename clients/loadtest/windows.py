"""A step over time: what happened in a span of it (sectors due, sends started, replies and losses that came
in, the latency of those replies), the per-second time series, and perf_analyzer's stability rule.

A span counts a reply where it came back (as perf_analyzer's measurement windows count completed requests),
so a window can be judged the moment it ends; a step's results proper count each sector by its due time.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from clients.loadtest.hdr import histogram, percentile_ms
from clients.loadtest.record import Record


@dataclass(frozen=True)
class Span:
    start_s: float  # seconds from the step's start (its first due time, warm-up included)
    end_s: float
    offered: int  # sectors due in the span
    sent: int  # sends that started in it
    answered: int  # replies (detections or the server's errors) that came back in it
    errors: int  # of them, the server's errors
    lost: int  # sectors given up in it (timeout, transport; a drain loss at the drain's end)
    p50_ms: float  # latency of the replies that came back in it, from each one's due time (NaN: none)
    p99_ms: float

    @property
    def answered_per_s(self) -> float:
        return self.answered / max(self.end_s - self.start_s, 1e-9)

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "answered_per_s": self.answered_per_s}


class Timeline:
    """A step's records as arrays (each (n,), seconds from `t0`), to cut into spans."""

    def __init__(self, records: Sequence[Record], t0: float, lost_at: float | None = None):
        """`lost_at`: the loop time to count a drain loss (a record without `done`) at; None: not yet."""
        fallback = math.nan if lost_at is None else lost_at
        self.due = np.array([r.scheduled for r in records], dtype=np.float64) - t0  # (n,)
        self.sent = np.array([math.nan if r.sent is None else r.sent for r in records]) - t0  # (n,)
        self.done = np.array([fallback if r.done is None else r.done for r in records]) - t0  # (n,)
        self.answered = np.array([r.answered for r in records], dtype=bool)  # (n,)
        self.error = np.array([r.error_code is not None for r in records], dtype=bool)  # (n,)
        self.lost = np.array([r.lost is not None for r in records], dtype=bool)  # (n,)
        self.latency_ms = (self.done - self.due) * 1e3  # (n,), meaningful where answered

    def span(self, start_s: float, end_s: float) -> Span:
        came = (self.done >= start_s) & (self.done < end_s)  # (n,) NaN compares False
        h = histogram(self.latency_ms[came & self.answered])
        return Span(
            start_s=start_s,
            end_s=end_s,
            offered=int(np.count_nonzero((self.due >= start_s) & (self.due < end_s))),
            sent=int(np.count_nonzero((self.sent >= start_s) & (self.sent < end_s))),
            answered=int(np.count_nonzero(came & self.answered)),
            errors=int(np.count_nonzero(came & self.error)),
            lost=int(np.count_nonzero(came & self.lost)),
            p50_ms=percentile_ms(h, 50.0),
            p99_ms=percentile_ms(h, 99.0),
        )

    def series(self, end_s: float, width_s: float = 1.0) -> list[Span]:
        """Consecutive spans of `width_s` from 0 until `end_s` (the last one may be shorter)."""
        edges = [*np.arange(0.0, end_s, width_s).tolist(), end_s]
        return [self.span(a, b) for a, b in itertools.pairwise(edges) if b > a]


def is_stable(windows: Sequence[Span], count: int, tolerance_pct: float) -> bool:
    """perf_analyzer's rule: the last `count` windows agree, each within +-tolerance_pct % of their mean, in
    replies per second and in p99. Fewer windows, or one without replies (no p99), is not stable."""
    if count < 1 or len(windows) < count:
        return False
    last = windows[-count:]
    for values in ([w.answered_per_s for w in last], [w.p99_ms for w in last]):
        v = np.asarray(values, dtype=np.float64)  # (count,)
        if not np.isfinite(v).all() or np.any(np.abs(v - v.mean()) > tolerance_pct / 100 * v.mean()):
            return False
    return True
