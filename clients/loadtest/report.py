"""A load test's results as a table (markdown), JSON and CSV (columns in the spirit of perf_analyzer's)."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from clients.loadtest.config import LoadTestConfig
from clients.loadtest.stats import StepResult

TOTALS = ("sent", "answered", "ok", "errors", "lost")
CSV_COLUMNS = (
    ("Vehicles", "vehicles"),
    ("Offered Sectors/Second", "offered_sectors_per_s"),
    ("Sectors/Second", "achieved_sectors_per_s"),
    ("Predictions/Second", "predictions_per_s"),
    ("Sent", "sent"),
    ("Answered", "answered"),
    ("Errors", "errors"),
    ("Lost", "lost"),
    ("Server Queue p50 ms", "server_queue_p50_ms"),
    ("Server Compute p50 ms", "server_model_p50_ms"),
    ("Server Total p50 ms", "server_total_p50_ms"),
    ("Server Total p99 ms", "server_total_p99_ms"),
    ("Client Send Lag p99 ms", "send_lag_p99_ms"),
    ("p50 latency ms", "p50_ms"),
    ("p90 latency ms", "p90_ms"),
    ("p99 latency ms", "p99_ms"),
    ("p99.9 latency ms", "p999_ms"),
    ("Max latency ms", "max_ms"),
    ("Avg latency ms", "mean_ms"),
    ("Held", "held"),
)


@dataclass(frozen=True)
class LoadTestReport:
    transport: str
    mode: str
    source: str
    sectors_per_turn: int
    config: LoadTestConfig
    steps: list[StepResult]

    @property
    def max_vehicles_held(self) -> int | None:
        """The most vehicles of a step that held (p99 bound, no errors, nothing lost)."""
        held = [s.vehicles for s in self.steps if s.held]
        return max(held) if held else None

    @property
    def peak_step(self) -> StepResult:
        """The step with the most sectors answered per second (the closed-loop throughput ceiling)."""
        return max(self.steps, key=lambda s: s.achieved_sectors_per_s)

    @property
    def result_step(self) -> StepResult:
        """The step the headline numbers describe: closed loop, the peak; open loop, the one at
        max_vehicles_held, else the first."""
        if self.mode == "closed":
            return self.peak_step
        best = self.max_vehicles_held
        return next((s for s in self.steps if s.vehicles == best), self.steps[0])


def _clean(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


def step_dict(s: StepResult) -> dict[str, Any]:
    d = dataclasses.asdict(s)
    d.pop("latencies_ms")
    return _clean(d)


def to_json(report: LoadTestReport) -> dict[str, Any]:
    """Headline keys (sent, answered, errors, lost, achieved_sectors_per_s, p50_ms, p99_ms, ...) are those of
    `result_step`; `steps` has every step; `totals` adds the counts over all steps."""
    head = step_dict(report.result_step)
    return _clean(
        {
            **head,
            "transport": report.transport,
            "mode": report.mode,
            "source": report.source,
            "sectors_per_turn": report.sectors_per_turn,
            "sweep": report.config.sweep,
            "p99_bound_ms": report.config.p99_bound_ms,
            "max_vehicles_held": report.max_vehicles_held,
            "peak_achieved_sectors_per_s": report.peak_step.achieved_sectors_per_s,
            "peak_vehicles": report.peak_step.vehicles,
            "totals": {k: sum(getattr(s, k) for s in report.steps) for k in TOTALS},
            "steps": [step_dict(s) for s in report.steps],
            "config": dataclasses.asdict(report.config),
        }
    )


def write_json(report: LoadTestReport, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(to_json(report), indent=2, default=str) + "\n")


def write_csv(report: LoadTestReport, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["Transport", "Mode", *(name for name, _ in CSV_COLUMNS)])
        for s in report.steps:
            w.writerow([s.transport, s.mode, *(_cell(getattr(s, key)) for _, key in CSV_COLUMNS)])


def _cell(v: Any) -> str:
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return "" if not math.isfinite(v) else f"{v:.3f}"
    return str(v)


def _ms(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{v:.1f}"


def table(report: LoadTestReport) -> str:
    """A markdown table, one row per step, and a closing line on what was held."""
    head = (
        "| vehicles | offered/s | sectors/s | predictions/s | p50 | p90 | p99 | p99.9 | max | "
        "srv queue | srv model | srv total | errors | lost | held |"
    )
    rows = [head, "|" + "---|" * (head.count("|") - 1)]
    for s in report.steps:
        errors = ", ".join(f"{k} {n}" for k, n in s.errors_by_code.items()) or "0"
        lost = ", ".join(f"{k} {n}" for k, n in s.lost_by_reason.items()) or "0"
        rows.append(
            f"| {s.vehicles} | {s.offered_sectors_per_s:.1f} | {s.achieved_sectors_per_s:.1f} | "
            f"{s.predictions_per_s:.1f} | {_ms(s.p50_ms)} | {_ms(s.p90_ms)} | {_ms(s.p99_ms)} | "
            f"{_ms(s.p999_ms)} | {_ms(s.max_ms)} | {_ms(s.server_queue_p50_ms)} | "
            f"{_ms(s.server_model_p50_ms)} | "
            f"{_ms(s.server_total_p50_ms)} | {errors} | {lost} | {'yes' if s.held else 'no'} |"
        )
    rows += ["", _footer(report)]
    return "\n".join(rows)


def _footer(report: LoadTestReport) -> str:
    cfg = report.config
    if report.mode == "closed":
        peak = report.peak_step
        return (
            f"{report.transport}, closed loop (each vehicle sends its next sector when answered), "
            f"{cfg.duration_s:g} s per step; latency in ms from send. Throughput ceiling: "
            f"{peak.achieved_sectors_per_s:.1f} sectors/s with {peak.vehicles} vehicles."
        )
    held = report.max_vehicles_held
    return (
        f"{report.transport}, open loop, {cfg.turns_per_s:g} turns/s x {report.sectors_per_turn} sectors per "
        f"vehicle, {cfg.duration_s:g} s per step; latency in ms from each sector's scheduled time (server "
        f"columns: p50 of the reply timings). Most vehicles held (p99 <= {cfg.p99_bound_ms:g} ms, no errors, "
        f"nothing lost): {held if held is not None else 'none'}."
    )
