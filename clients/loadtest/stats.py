"""A step's records -> its numbers: counts, rates, client latency percentiles (HdrHistogram), the server's
split, the threshold checks, the time series and every sample."""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from clients.loadtest.config import LoadTestConfig, Mode, Thresholds
from clients.loadtest.hdr import summary_ms
from clients.loadtest.record import Record
from clients.loadtest.runner import StepRun
from clients.loadtest.windows import Timeline


@dataclass(frozen=True)
class StepResult:
    """One step. Counted: the sectors due in the measured span (after the warm-up; with windows, the last
    stable ones). sent = answered + lost; answered = ok + errors. Latencies (ms) are client side, from each
    sector's scheduled time, over every answered sector; server_* are the reply timings (p50 / p99)."""

    transport: str
    mode: str
    vehicles: int
    duration_s: float  # the measured span
    started_unix: float  # when the step's first sector was due (Unix time): samples' due_s count from here
    uncounted: int  # sectors sent outside the measured span (warm-up, windows before the stable ones)
    sent: int
    answered: int
    ok: int
    errors: int
    lost: int
    error_rate: float  # (errors + lost) / sent
    errors_by_code: dict[str, int]
    lost_by_reason: dict[str, int]
    by_worker: dict[str, int]  # detections replies by the worker that ran them
    cold_starts: int  # detections replies that ran on a fresh stream state (a stream's first, or moved)
    offered_sectors_per_s: float  # scheduled (open loop) or sent (closed loop) per second of the span
    achieved_sectors_per_s: float  # answered sectors per second, until the last answer
    predictions_per_s: float  # detections replies per second, until the last answer
    p50_ms: float
    p90_ms: float
    p99_ms: float
    p999_ms: float
    max_ms: float
    mean_ms: float
    server_queue_p50_ms: float
    server_queue_p99_ms: float
    server_model_p50_ms: float
    server_model_p99_ms: float
    server_total_p50_ms: float
    server_total_p99_ms: float
    send_lag_p99_ms: float  # how late the client itself sent (a busy client shows here, not hidden)
    send_lag_max_ms: float
    boxes_per_reply: float
    stable: bool | None  # the windows agreed (None: no windows)
    checks: dict[str, dict[str, Any]]  # per threshold: {"limit", "value", "passed"}
    passed: bool  # every check passed
    held: bool  # open loop and passed: the server kept up with this many vehicles
    windows: list[dict[str, Any]] = field(default_factory=list, repr=False)  # each judged window
    series: list[dict[str, Any]] = field(default_factory=list, repr=False)  # per second of the whole step
    samples: dict[str, list[Any]] = field(default_factory=dict, repr=False)  # every sector sent, by column
    latencies_ms: list[float] = field(default_factory=list, repr=False, compare=False)


def summarize(step: StepRun, cfg: LoadTestConfig, transport: str) -> StepResult:
    recs = [r for r in step.records if step.counted(r)]
    answered = [r for r in recs if r.answered]
    ok = [r for r in answered if r.ok]
    lat = [r.latency_ms for r in answered]
    start = step.counted_from
    span = max(step.stop - start, 1e-9)
    last = max((r.done for r in answered if r.done is not None), default=step.stop)
    window = max(last - start, 1e-9)
    errors = Counter(r.error_code for r in answered if r.error_code is not None)
    lost = Counter(r.lost.value for r in recs if r.lost is not None)
    p = summary_ms(lat)
    lag = summary_ms((r.sent - r.scheduled) * 1e3 for r in recs if r.sent is not None)
    error_rate = (sum(errors.values()) + sum(lost.values())) / len(recs) if recs else math.nan
    checks = threshold_checks(cfg.thresholds, p["p99"], error_rate, step.stable)
    passed = all(c["passed"] for c in checks.values())
    return StepResult(
        transport=transport,
        mode=cfg.mode.value,
        vehicles=step.vehicles,
        duration_s=span,
        started_unix=round(step.t0_unix, 6),
        uncounted=len(step.records) - len(recs),
        sent=len(recs),
        answered=len(answered),
        ok=len(ok),
        errors=sum(errors.values()),
        lost=sum(lost.values()),
        error_rate=error_rate,
        errors_by_code=dict(sorted(errors.items())),
        lost_by_reason=dict(sorted(lost.items())),
        by_worker=dict(sorted(Counter(r.worker_id for r in ok).items())),
        cold_starts=sum(r.cold_start for r in ok),
        offered_sectors_per_s=len(recs) / span,
        achieved_sectors_per_s=len(answered) / window,
        predictions_per_s=len(ok) / window,
        **{f"{k}_ms": v for k, v in p.items()},
        **_server_split(ok),
        send_lag_p99_ms=lag["p99"],
        send_lag_max_ms=lag["max"],
        boxes_per_reply=float(np.mean([r.boxes for r in ok])) if ok else 0.0,
        stable=step.stable,
        checks=checks,
        passed=passed,
        held=passed and cfg.mode is Mode.OPEN,
        windows=[w.to_dict() for w in step.windows],
        series=[s.to_dict() for s in Timeline(step.records, step.t0, step.drain_end).series(_span_end(step))],
        samples=samples(step),
        latencies_ms=lat,
    )


def threshold_checks(
    t: Thresholds, p99_ms: float, error_rate: float, stable: bool | None
) -> dict[str, dict[str, Any]]:
    """Each threshold set, and stability when judged: {"limit", "value", "passed"}. A step without replies
    (no p99) or without sectors (no error rate) fails the threshold on it."""
    checks: dict[str, dict[str, Any]] = {}
    if t.max_p99_ms is not None:
        checks["p99_ms"] = {"limit": t.max_p99_ms, "value": p99_ms, "passed": bool(p99_ms <= t.max_p99_ms)}
    if t.max_error_rate is not None:
        ok = bool(error_rate <= t.max_error_rate)
        checks["error_rate"] = {"limit": t.max_error_rate, "value": error_rate, "passed": ok}
    if stable is not None:
        checks["stable"] = {"limit": True, "value": stable, "passed": stable}
    return checks


def samples(step: StepRun) -> dict[str, list[Any]]:
    """Every sector the step sent, by column (times in s from the step's start, latencies in ms; None where
    there is none): vehicle, seq, due_s, sent_lag_ms, latency_ms, outcome ("ok", the server's error code, or
    "lost:<reason>"), counted (whether it is in the step's results); for detections: worker, cold_start,
    context_sectors."""
    recs = step.records
    return {
        "vehicle": [r.vehicle for r in recs],
        "seq": [r.seq for r in recs],
        "due_s": [round(r.scheduled - step.t0, 6) for r in recs],
        "sent_lag_ms": [None if r.sent is None else round((r.sent - r.scheduled) * 1e3, 3) for r in recs],
        "latency_ms": [round(r.latency_ms, 3) if r.answered else None for r in recs],
        "outcome": [_outcome(r) for r in recs],
        "counted": [step.counted(r) for r in recs],
        "worker": [r.worker_id if r.ok else None for r in recs],
        "cold_start": [r.cold_start if r.ok else None for r in recs],
        "context_sectors": [r.context_sectors if r.ok else None for r in recs],
    }


def _outcome(r: Record) -> str:
    if r.ok:
        return "ok"
    if r.error_code is not None:
        return r.error_code
    return f"lost:{r.lost.value if r.lost is not None else 'unsettled'}"


def _span_end(step: StepRun) -> float:
    """Where the step's time series ends: the drain is over, every sector settled (s from the start)."""
    return step.drain_end - step.t0 + 1e-6


def _server_split(ok: list[Record]) -> dict[str, float]:
    out: dict[str, float] = {}
    for name, attr in (("queue", "queue_ms"), ("model", "model_ms"), ("total", "server_ms")):
        p = summary_ms(getattr(r, attr) for r in ok)
        out[f"server_{name}_p50_ms"] = p["p50"]
        out[f"server_{name}_p99_ms"] = p["p99"]
    return out
