"""A step's records -> its numbers: counts, rates, client latency percentiles, the server's split."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from clients.loadtest.config import LoadTestConfig, Mode
from clients.loadtest.record import Record
from clients.loadtest.runner import StepRun

PERCENTILES = {"p50": 50.0, "p90": 90.0, "p99": 99.0, "p999": 99.9}


@dataclass(frozen=True)
class StepResult:
    """One step. sent = answered + lost; answered = ok + errors. Latencies (ms) are client side, from each
    sector's scheduled time, over every answered sector; server_* are the reply timings (p50 / p99)."""

    transport: str
    mode: str
    vehicles: int
    duration_s: float
    sent: int
    answered: int
    ok: int
    errors: int
    lost: int
    errors_by_code: dict[str, int]
    lost_by_reason: dict[str, int]
    offered_sectors_per_s: float  # scheduled (open loop) or sent (closed loop) per second of the window
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
    boxes_per_reply: float
    held: bool  # open loop: p99 <= bound, no errors, nothing lost (closed loop: always False)
    latencies_ms: list[float] = field(default_factory=list, repr=False, compare=False)


def _pct(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if values.size else float("nan")


def summarize(step: StepRun, cfg: LoadTestConfig, transport: str) -> StepResult:
    recs = step.records
    answered = [r for r in recs if r.answered]
    ok = [r for r in answered if r.ok]
    lat = np.array([r.latency_ms for r in answered], dtype=np.float64)
    last = max((r.done for r in answered if r.done is not None), default=step.send_end)
    window = max(last - step.t0, 1e-9)
    send_window = max(step.send_end - step.t0, 1e-9) if cfg.mode is Mode.CLOSED else step.duration_s
    errors = Counter(r.error_code for r in answered if r.error_code is not None)
    lost = Counter(r.lost.value for r in recs if r.lost is not None)
    p = {name: _pct(lat, q) for name, q in PERCENTILES.items()}
    server = _server_split(ok)
    lag = np.array([(r.sent - r.scheduled) * 1e3 for r in recs if r.sent is not None])
    return StepResult(
        transport=transport,
        mode=cfg.mode.value,
        vehicles=step.vehicles,
        duration_s=step.duration_s,
        sent=len(recs),
        answered=len(answered),
        ok=len(ok),
        errors=sum(errors.values()),
        lost=sum(lost.values()),
        errors_by_code=dict(sorted(errors.items())),
        lost_by_reason=dict(sorted(lost.items())),
        offered_sectors_per_s=len(recs) / send_window,
        achieved_sectors_per_s=len(answered) / window,
        predictions_per_s=len(ok) / window,
        **{f"{k}_ms": v for k, v in p.items()},
        max_ms=float(lat.max()) if lat.size else float("nan"),
        mean_ms=float(lat.mean()) if lat.size else float("nan"),
        **server,
        send_lag_p99_ms=_pct(lag, 99.0),
        boxes_per_reply=float(np.mean([r.boxes for r in ok])) if ok else 0.0,
        held=bool(
            cfg.mode is Mode.OPEN and lat.size and p["p99"] <= cfg.p99_bound_ms and not errors and not lost
        ),
        latencies_ms=lat.tolist(),
    )


def _server_split(ok: list[Record]) -> dict[str, float]:
    out: dict[str, float] = {}
    for name, attr in (("queue", "queue_ms"), ("model", "model_ms"), ("total", "server_ms")):
        values = np.array([getattr(r, attr) for r in ok], dtype=np.float64)
        out[f"server_{name}_p50_ms"] = _pct(values, 50.0)
        out[f"server_{name}_p99_ms"] = _pct(values, 99.0)
    return out
