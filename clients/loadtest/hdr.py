"""Latency percentiles from an HdrHistogram (the `hdrhistogram` package, `hdrh`), as wrk2, k6 and
perf_analyzer's peers report them: values recorded in microseconds with 3 significant digits, so every
percentile is within 0.1 % of a recorded value (plus 1 us), whatever the spread. The max is exact (to the
recorded microsecond): the histogram would give the top of its bucket, up to 0.1 % above it."""

from __future__ import annotations

import math
from collections.abc import Iterable

from hdrh.histogram import HdrHistogram

LOWEST_US = 1
HIGHEST_US = 3_600_000_000  # one hour: anything slower is clamped there (and is a lost sector anyway)
DIGITS = 3
PERCENTILES = {"p50": 50.0, "p90": 90.0, "p99": 99.0, "p999": 99.9}


def to_us(value_ms: float) -> int:
    """A latency in ms as the whole microseconds the histogram records (negative counts as 0, clamped)."""
    return min(HIGHEST_US, max(0, round(value_ms * 1e3)))


def histogram(values_ms: Iterable[float]) -> HdrHistogram:
    """An HdrHistogram of latencies given in milliseconds."""
    h = HdrHistogram(LOWEST_US, HIGHEST_US, DIGITS)
    for v in values_ms:
        h.record_value(to_us(v))
    return h


def percentile_ms(h: HdrHistogram, q: float) -> float:
    """The q-th percentile (0..100) in ms; NaN for an empty histogram."""
    if h.get_total_count() == 0:
        return math.nan
    return h.get_value_at_percentile(q) / 1e3


def summary_ms(values_ms: Iterable[float]) -> dict[str, float]:
    """p50, p90, p99, p999, max and mean (ms) of the values; NaN when there are none."""
    values = list(values_ms)
    h = histogram(values)
    out = {name: percentile_ms(h, q) for name, q in PERCENTILES.items()}
    empty = not values
    out["max"] = math.nan if empty else max(map(to_us, values)) / 1e3
    out["mean"] = math.nan if empty else h.get_mean_value() / 1e3
    return out
