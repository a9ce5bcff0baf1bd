"""The load tester as a CI gate and a measurement: thresholds that set the exit code, the warm-up kept out of
the results, perf_analyzer-style stability windows, HdrHistogram percentiles, the JSON's samples and time
series, and the open-loop promise at overload (every sector sent on time, in order, answered once), against
real servers on loopback (uvicorn + zenoh) and, for the rules themselves, synthetic numbers."""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner
from client_helpers import EVERY, Served, loadtest_config, serve_both
from server_helpers import default_detector

from clients.connect import Transport
from clients.loadtest.config import LoadTestConfig, OutputConfig, Thresholds, WindowConfig
from clients.loadtest.hdr import PERCENTILES, summary_ms
from clients.loadtest.report import table
from clients.loadtest.run import run_loadtest
from clients.loadtest.stats import StepResult, threshold_checks
from clients.loadtest.windows import Span, is_stable
from phim.cli import main as app

FORWARD_S = 0.1  # the overloaded server's extra time per forward (one sector per forward)
DEADLINE_MS = 500.0  # the overloaded server's deadline; the client's timeout (30 s) is far above it
SECTOR_PERIOD_MS = 100.0  # one vehicle's sector period at 10 sectors/s
MAX_SEND_LAG_MS = SECTOR_PERIOD_MS / 2  # the typical send's lag
STALL_MS = 2000.0  # the longest a stalled (shared, 2-core) machine may delay one send


@pytest.fixture(scope="module")
def served() -> Iterator[Served]:
    with serve_both(default_detector(), deadline_ms=60_000, queue_size=256) as s:
        yield s


@contextlib.contextmanager
def slow_server(**settings: Any) -> Iterator[Served]:
    """A server whose forwards take FORWARD_S longer, one sector each: about 7 sectors/s."""
    det = default_detector()
    real = det.step

    def slow_step(points: Any, states: Any) -> Any:
        time.sleep(FORWARD_S)
        return real(points, states)

    det.step = slow_step  # type: ignore[method-assign]
    with serve_both(det, max_batch=1, warmup_sectors=1, **settings) as s:
        yield s


@pytest.fixture(scope="module")
def overloaded() -> Iterator[Served]:
    """Slow, with a short queue and deadline: 503 and 504 when pushed."""
    with slow_server(queue_size=4, deadline_ms=DEADLINE_MS) as s:
        yield s


@pytest.fixture(scope="module")
def backlogged() -> Iterator[Served]:
    """Slow, refusing nothing: pushed, its queue (and the latency) grows without end."""
    with slow_server(queue_size=256, deadline_ms=60_000) as s:
        yield s


def config(served: Served, transport: Transport = Transport.HTTP, **kw: Any) -> LoadTestConfig:
    return loadtest_config(served, transport, **kw)


def cli(served: Served, *extra: str) -> tuple[int, dict[str, Any], str]:
    args = ["loadtest", "--url", served.url, "--duration", "1", "--turns-per-s", "1", "--every", str(EVERY)]
    args += ["--synthetic", "--no-progress", "--json", *extra]
    result = CliRunner().invoke(app, args)
    return result.exit_code, json.loads(result.stdout), result.output


# ------------------------------------------------------------------------------------------- thresholds


def test_a_generous_threshold_passes_with_exit_0_an_impossible_one_fails_with_1(served: Served) -> None:
    code, doc, out = cli(served, "--max-p99-ms", "60000", "--max-error-rate", "0")
    assert code == 0, out
    assert doc["passed"] is True and doc["exit_code"] == 0 and doc["thresholds"]["enforced"] is True
    assert doc["checks"]["p99_ms"] == {"limit": 60000.0, "value": doc["p99_ms"], "passed": True}
    assert doc["checks"]["error_rate"] == {"limit": 0.0, "value": 0.0, "passed": True}
    code, doc, out = cli(served, "--max-p99-ms", "0.001", "--max-error-rate", "1")
    assert code == 1, out
    assert doc["passed"] is False and doc["exit_code"] == 1 and doc["steps"][0]["passed"] is False
    assert doc["checks"]["p99_ms"]["passed"] is False and doc["checks"]["error_rate"]["passed"] is True


def test_without_thresholds_the_defaults_judge_but_do_not_set_the_exit_code(served: Served) -> None:
    code, doc, out = cli(served)
    assert code == 0, out
    assert doc["thresholds"] == {"max_p99_ms": 25.0, "max_error_rate": 0.0, "enforced": False}
    assert set(doc["checks"]) == {"p99_ms", "error_rate"} and doc["exit_code"] == 0
    assert doc["passed"] is (doc["p99_ms"] <= 25.0 and doc["errors"] == doc["lost"] == 0)


def test_threshold_checks_name_what_failed() -> None:
    t = Thresholds(max_p99_ms=100.0, max_error_rate=0.01)
    passing = threshold_checks(t, 99.0, 0.0, None)
    assert all(c["passed"] for c in passing.values()) and set(passing) == {"p99_ms", "error_rate"}
    failing = threshold_checks(t, 101.0, 0.02, False)
    assert {k: c["passed"] for k, c in failing.items()} == {
        "p99_ms": False,
        "error_rate": False,
        "stable": False,
    }
    assert not threshold_checks(t, math.nan, math.nan, None)["p99_ms"]["passed"]  # no replies: no p99
    assert threshold_checks(Thresholds(None, None), 1e9, 1.0, None) == {}


# ------------------------------------------------------------------------------------ warm-up and JSON


def test_the_warm_up_is_sent_but_kept_out_of_the_results(served: Served, tmp_path: Path) -> None:
    out = OutputConfig(json_path=tmp_path / "w.json", progress=False)
    report = run_loadtest(config(served, warmup_s=1.0), out)
    step = report.steps[0]
    assert step.sent == 4 and step.uncounted == 4 and step.ok == 4  # 1 s x 4 sectors/s, and 4 before
    assert len(step.latencies_ms) == 4
    doc = json.loads((tmp_path / "w.json").read_text())
    samples = doc["steps"][0]["samples"]
    assert samples["seq"] == list(range(8)) and samples["outcome"] == ["ok"] * 8  # all sent, all answered
    assert samples["counted"] == [False] * 4 + [True] * 4
    assert all(due >= 1.0 for due, c in zip(samples["due_s"], samples["counted"], strict=True) if c)
    counted = [lat for lat, c in zip(samples["latency_ms"], samples["counted"], strict=True) if c]
    assert sorted(counted) == pytest.approx(sorted(step.latencies_ms), abs=1e-3)


def test_the_json_has_every_sample_and_a_time_series_that_adds_up(served: Served, tmp_path: Path) -> None:
    out = OutputConfig(json_path=tmp_path / "t.json", progress=False)
    run_loadtest(config(served, vehicles=(2,), duration_s=2.0, warmup_s=0.5, turns_per_s=2.0), out)
    step = json.loads((tmp_path / "t.json").read_text())["steps"][0]
    samples, series = step["samples"], step["series"]
    n = len(samples["seq"])
    assert n == step["sent"] + step["uncounted"] == 2 * 2.5 * 8  # 2 vehicles x 2.5 s x 8 sectors/s
    assert set(samples) == {
        *("vehicle", "seq", "due_s", "sent_lag_ms", "latency_ms", "outcome", "counted"),
        *("worker", "cold_start", "context_sectors"),
    }
    assert set(samples["worker"]) == {"test-worker"} and samples["cold_start"].count(True) == 2  # one each
    assert all(len(col) == n for col in samples.values())
    assert [s["start_s"] for s in series] == list(range(len(series))) and len(series) >= 3
    assert sum(s["offered"] for s in series) == sum(s["sent"] for s in series) == n
    assert sum(s["answered"] for s in series) == n - sum(s["lost"] for s in series) == n
    for s in series:
        assert s["answered"] == 0 or 0 < s["p50_ms"] <= s["p99_ms"]
    latencies = np.array([x for x in samples["latency_ms"] if x is not None])
    assert max(s["p99_ms"] for s in series if s["answered"]) <= latencies.max() * 1.001 + 1e-3


def test_hdr_percentiles_agree_with_numpy_within_the_histograms_precision() -> None:
    values = np.random.default_rng(0).lognormal(np.log(40.0), 0.8, 20_000)  # (20000,) latencies, ms
    ordered = np.sort(values)
    got = summary_ms(values.tolist())
    for name, q in PERCENTILES.items():
        rank = q / 100 * (len(values) - 1)  # numpy's (linear) rank; HdrHistogram rounds its own
        near = ordered[max(0, math.floor(rank) - 2) : math.ceil(rank) + 3]  # the order statistics around it
        assert near.min() * (1 - 1e-3) - 1e-3 <= got[name] <= near.max() * (1 + 1e-3) + 1e-3, name
        assert got[name] == pytest.approx(np.percentile(values, q), rel=2e-3), name
    assert got["max"] == pytest.approx(values.max(), abs=5e-4)  # exact to the recorded microsecond
    assert got["mean"] == pytest.approx(values.mean(), rel=1e-3)
    assert math.isnan(summary_ms([])["p99"]) and math.isnan(summary_ms([])["max"])
    assert summary_ms([24.4974])["max"] == 24.497  # not the top of its 16 us bucket (24.511)


# ------------------------------------------------------------------------------------ stability windows


def span(answered: int, p99_ms: float, width_s: float = 1.0) -> Span:
    return Span(0.0, width_s, answered, answered, answered, 0, 0, p99_ms / 2, p99_ms)


def test_windows_are_stable_when_the_last_ones_agree_in_throughput_and_p99() -> None:
    steady = [span(100, 500.0), span(40, 80.0), span(41, 82.0), span(39, 79.0)]
    assert is_stable(steady, count=3, tolerance_pct=10)  # the first (a ramp) is not among the last 3
    assert not is_stable(steady, count=4, tolerance_pct=10)
    assert not is_stable(steady[:2], count=3, tolerance_pct=10)  # too few windows
    growing = [span(40, 80.0), span(40, 120.0), span(40, 160.0)]  # a queue that grows: p99 does
    assert not is_stable(growing, count=3, tolerance_pct=10) and is_stable(growing, 3, tolerance_pct=40)
    slowing = [span(40, 80.0), span(30, 80.0), span(20, 80.0)]
    assert not is_stable(slowing, count=3, tolerance_pct=10)
    silent = [span(40, 80.0), span(40, 80.0), span(0, math.nan)]  # a window without replies
    assert not is_stable(silent, count=3, tolerance_pct=100)


def test_a_step_ends_once_its_windows_are_stable_and_counts_only_those(served: Served) -> None:
    """Any 3 windows with replies agree (a 1000 % tolerance), so the step ends at the first window whose
    last 3 all had replies: the third on an idle machine, later where a busy one left a window silent."""
    windows = WindowConfig(window_s=0.5, stability_pct=1000.0, max_windows=6)
    step = run_loadtest(config(served, turns_per_s=2.0, windows=windows)).steps[0]
    assert step.stable is True and step.passed is step.checks["p99_ms"]["passed"]
    spans = [Span(**{k: v for k, v in w.items() if k != "answered_per_s"}) for w in step.windows]
    n = len(spans)
    assert 3 <= n <= 6 and step.checks["stable"]["passed"] is True
    assert is_stable(spans, 3, 1000.0) and not is_stable(spans[:-1], 3, 1000.0)  # ended once stable
    assert step.duration_s == pytest.approx(1.5) and step.sent == 12  # the last 3 x 0.5 s x 8 sectors/s
    assert step.uncounted >= 4 * (n - 3)  # the windows before them


def test_a_step_that_never_stabilizes_says_so_and_fails(backlogged: Served) -> None:
    """A queue that grows all along (offered 10/s, served ~7/s, nothing refused): p99 grows every window."""
    windows = WindowConfig(window_s=0.5, stability_pct=10.0, max_windows=4)
    cfg = config(backlogged, turns_per_s=2.5, windows=windows, thresholds=Thresholds(None, None))
    report = run_loadtest(cfg)
    step = report.steps[0]
    assert step.stable is False and len(step.windows) == 4 and not step.passed
    assert step.checks == {"stable": {"limit": True, "value": False, "passed": False}}
    assert "not stable" in table(report) and not report.passed


# ------------------------------------------------------------------------------------------- overload


def sent_before_previous_answer(samples: dict[str, list[Any]]) -> int:
    """Sectors sent while their stream's previous sector was still unanswered (the client did not wait)."""
    by_vehicle: dict[int, list[tuple[int, float, float]]] = {}
    for v, seq, due, lag, lat in zip(
        samples["vehicle"],
        samples["seq"],
        samples["due_s"],
        samples["sent_lag_ms"],
        samples["latency_ms"],
        strict=True,
    ):
        by_vehicle.setdefault(v, []).append((seq, due + lag / 1e3, due + lat / 1e3))
    return sum(
        nxt[1] < prev[2] for rows in by_vehicle.values() for prev, nxt in itertools.pairwise(sorted(rows))
    )


@pytest.mark.parametrize("transport", [Transport.HTTP, Transport.ZENOH])
def test_open_loop_at_overload_sends_every_sector_on_time_and_each_gets_one_answer(
    overloaded: Served, transport: Transport
) -> None:
    """20 sectors/s offered to a server that does about 7: every sector leaves on time (the median within
    MAX_SEND_LAG_MS, all but two before the stream's next sector is due, in its stream's order, never waiting
    for an answer) and gets detections, 503 or 504: no 409 stale, none lost, none unsent."""
    cfg = config(overloaded, transport, vehicles=(2,), turns_per_s=2.5, duration_s=2.0)
    step: StepResult = run_loadtest(cfg).steps[0]
    samples = step.samples
    assert step.sent == len(samples["seq"]) == 40 and step.uncounted == 0
    assert step.lost == 0 and step.answered == 40, step.lost_by_reason
    outcomes = set(samples["outcome"])
    assert outcomes <= {"ok", "overloaded", "deadline_exceeded"}, step.errors_by_code
    assert "ok" in outcomes and outcomes & {"overloaded", "deadline_exceeded"}  # it was overloaded
    lags = samples["sent_lag_ms"]
    assert all(lag is not None for lag in lags), lags
    # on time: the median within MAX_SEND_LAG_MS, all but two before the stream's next sector is due, none
    # stalled past STALL_MS (the shared CI machine once stalled this process for 0.6 s, delaying one sector;
    # beside a training run three sends left 73-101 ms late); not waiting for answers is checked by
    # sent_before_previous_answer
    assert float(np.median(lags)) < MAX_SEND_LAG_MS, sorted(lags)
    assert sorted(lags)[-3] < SECTOR_PERIOD_MS and max(lags) < STALL_MS, sorted(lags)[-3:]
    assert step.send_lag_max_ms == pytest.approx(max(lags), abs=0.01)  # samples are rounded to 1 us
    assert sent_before_previous_answer(samples) > 10
