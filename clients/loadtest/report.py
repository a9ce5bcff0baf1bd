"""A load test's results as a table (markdown), JSON and CSV (columns in the spirit of perf_analyzer's), and
its verdict: the run passes when a step passed its thresholds (a sweep: it found a load that holds)."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from clients.loadtest.config import LoadTestConfig
from clients.loadtest.record import Lost
from clients.loadtest.stats import StepResult

TOTALS = ("sent", "answered", "ok", "errors", "lost", "uncounted", "cold_starts")
PER_STEP_ONLY = ("windows", "series", "samples")  # in `steps`, not repeated in the headline
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
    ("Error Rate", "error_rate"),
    ("Client Send Lag p99 ms", "send_lag_p99_ms"),
    ("p50 latency ms", "p50_ms"),
    ("p90 latency ms", "p90_ms"),
    ("p99 latency ms", "p99_ms"),
    ("p99.9 latency ms", "p999_ms"),
    ("Max latency ms", "max_ms"),
    ("Avg latency ms", "mean_ms"),
    ("Stable", "stable"),
    ("Passed", "passed"),
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
    retried: int = 0  # sectors the client sent once more, to a new owner, after their worker left (zenoh)

    @property
    def max_vehicles_held(self) -> int | None:
        """The most vehicles of an open-loop step that held (passed its thresholds)."""
        held = [s.vehicles for s in self.steps if s.held]
        return max(held) if held else None

    @property
    def passed(self) -> bool:
        """A step passed: one step, that one; a sweep found a load that passes."""
        return any(s.passed for s in self.steps)

    @property
    def unreachable(self) -> int:
        """Sectors lost to transport failures (connection refused or reset, an unreadable reply): the server
        went away or never answered."""
        return sum(s.lost_by_reason.get(Lost.TRANSPORT.value, 0) for s in self.steps)

    @property
    def refused(self) -> int:
        """Sectors the server refused for their token (unauthorized, forbidden): nothing measured for them."""
        return sum(s.errors_by_code.get(c, 0) for s in self.steps for c in ("unauthorized", "forbidden"))

    @property
    def exit_code(self) -> int:
        """1 when thresholds are enforced and the run did not pass, or when sectors were lost to transport
        failures or refused for their token (with or without thresholds: there was nothing to measure),
        else 0."""
        unmeasured = self.unreachable > 0 or self.refused > 0
        return int((self.config.thresholds.enforced and not self.passed) or unmeasured)

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
    """Headline keys (sent, answered, errors, lost, achieved_sectors_per_s, p50_ms, p99_ms, checks, ...) are
    those of `result_step`; `steps` has every step with its windows, time series and samples; `totals` adds
    the counts over all steps; `thresholds`, `passed` and `exit_code` give the verdict."""
    head = {k: v for k, v in step_dict(report.result_step).items() if k not in PER_STEP_ONLY}
    return _clean(
        {
            **head,
            "transport": report.transport,
            "mode": report.mode,
            "source": report.source,
            "sectors_per_turn": report.sectors_per_turn,
            "sweep": report.config.sweep,
            "thresholds": dataclasses.asdict(report.config.thresholds),
            "passed": report.passed,
            "exit_code": report.exit_code,
            "lost_to_transport": report.unreachable,
            "refused_by_auth": report.refused,
            "max_vehicles_held": report.max_vehicles_held,
            "peak_achieved_sectors_per_s": report.peak_step.achieved_sectors_per_s,
            "peak_vehicles": report.peak_step.vehicles,
            "retried": report.retried,
            "totals": {
                **{k: sum(getattr(s, k) for s in report.steps) for k in TOTALS},
                "by_worker": dict(
                    sorted(sum((Counter(s.by_worker) for s in report.steps), Counter()).items())
                ),
            },
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
    if v is None:
        return ""
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return "" if not math.isfinite(v) else f"{v:.3f}"
    return str(v)


def _ms(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{v:.1f}"


def table(report: LoadTestReport) -> str:
    """A markdown table, one row per step, and closing lines on the thresholds and the verdict."""
    head = (
        "| vehicles | offered/s | sectors/s | predictions/s | p50 | p90 | p99 | p99.9 | max | "
        "srv queue | srv model | srv total | errors | lost | verdict |"
    )
    rows = [head, "|" + "---|" * (head.count("|") - 1)]
    for s in report.steps:
        errors = ", ".join(f"{k} {n}" for k, n in s.errors_by_code.items()) or "0"
        lost = ", ".join(f"{k} {n}" for k, n in s.lost_by_reason.items()) or "0"
        rows.append(
            f"| {s.vehicles} | {s.offered_sectors_per_s:.1f} | {s.achieved_sectors_per_s:.1f} | "
            f"{s.predictions_per_s:.1f} | {_ms(s.p50_ms)} | {_ms(s.p90_ms)} | {_ms(s.p99_ms)} | "
            f"{_ms(s.p999_ms)} | {_ms(s.max_ms)} | {_ms(s.server_queue_p50_ms)} | "
            f"{_ms(s.server_model_p50_ms)} | {_ms(s.server_total_p50_ms)} | {errors} | {lost} | "
            f"{_verdict(s)} |"
        )
    rows += ["", _footer(report), _thresholds_line(report)]
    return "\n".join(rows)


def _verdict(s: StepResult) -> str:
    """ "passed", or what failed: "p99 31.2 > 25", "error rate 0.12 > 0", "not stable"."""
    failed = []
    for name, c in s.checks.items():
        if c["passed"]:
            continue
        if name == "stable":
            failed.append("not stable")
        else:
            value = "-" if not math.isfinite(c["value"]) else f"{c['value']:.4g}"
            failed.append(f"{name.removesuffix('_ms').replace('_', ' ')} {value} > {c['limit']:g}")
    return "; ".join(failed) or "passed"


def _footer(report: LoadTestReport) -> str:
    cfg = report.config
    warmup = f" after a {cfg.warmup_s:g} s warm-up" if cfg.warmup_s else ""
    length = (
        f"{cfg.duration_s:g} s per step"
        if cfg.windows is None
        else f"windows of {cfg.windows.window_s:g} s until {cfg.windows.count} agree within "
        f"{cfg.windows.stability_pct:g} % (at most {cfg.windows.max_windows})"
    )
    if report.mode == "closed":
        peak = report.peak_step
        return (
            f"{report.transport}, closed loop (each vehicle sends its next sector when answered), "
            f"{length}{warmup}; latency in ms from send. Throughput ceiling: "
            f"{peak.achieved_sectors_per_s:.1f} sectors/s with {peak.vehicles} vehicles."
        )
    held = report.max_vehicles_held
    return (
        f"{report.transport}, open loop, {cfg.turns_per_s:g} turns/s x {report.sectors_per_turn} sectors per "
        f"vehicle, {length}{warmup}; latency in ms from each sector's scheduled time (server columns: p50 "
        f"of the reply timings). Most vehicles held: {held if held is not None else 'none'}."
    )


def _thresholds_line(report: LoadTestReport) -> str:
    t = report.config.thresholds
    limits = [f"p99 <= {t.max_p99_ms:g} ms"] if t.max_p99_ms is not None else []
    limits += [f"error rate <= {t.max_error_rate:g}"] if t.max_error_rate is not None else []
    limits += ["stable windows"] if report.config.windows is not None else []
    verdict = "passed" if report.passed else "failed"
    how = f"exit code {report.exit_code}" if t.enforced else "not enforced (no threshold given)"
    line = f"Thresholds: {', '.join(limits) or 'none'}; {verdict}, {how}."
    if report.unreachable:
        line += f"\n{report.unreachable} sectors lost to transport failures (server gone?): exit code 1."
    if report.refused:
        line += f"\n{report.refused} sectors refused for their token (--token? --stream-prefix?): exit 1."
    return line
