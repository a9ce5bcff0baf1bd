"""PNG plots of a load test (matplotlib, Agg): latency histogram and tail per step; for a sweep, throughput
and p99 against the number of vehicles on a log axis, with the offered load (sectors/s) along the top and as
a line of its own."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from clients.loadtest.report import LoadTestReport


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_plots(report: LoadTestReport, folder: Path) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    out = [latency_plot(report, folder / f"latency_{report.transport}.png")]
    if len(report.steps) > 1:
        out.append(sweep_plot(report, folder / f"sweep_{report.transport}.png"))
    return out


def latency_plot(report: LoadTestReport, path: Path) -> Path:
    """Left: histogram of client latency; right: CDF with the tail stretched (1 - F on a log axis)."""
    plt = _pyplot()
    fig, (hist, cdf) = plt.subplots(1, 2, figsize=(11, 4.2))
    for s in report.steps:
        lat = np.sort(np.asarray(s.latencies_ms))
        if not lat.size:
            continue
        label = f"{s.vehicles} vehicles"
        hist.hist(lat, bins=60, histtype="step", label=label)
        tail = 1.0 - np.arange(lat.size) / lat.size  # (n,) fraction of sectors slower than each value
        cdf.plot(lat, tail, label=label)
    bound = report.config.thresholds.max_p99_ms
    for ax in (hist, cdf):
        if bound is not None:
            ax.axvline(bound, color="grey", linestyle="--", linewidth=1, label="p99 threshold")
        ax.set_xlabel("latency from scheduled send (ms)")
        ax.legend(fontsize=8)
    hist.set_ylabel("sectors")
    cdf.set_yscale("log")
    cdf.set_ylabel("fraction slower (1 - CDF)")
    fig.suptitle(f"PHiM {report.transport} {report.mode}-loop latency ({report.source})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def sweep_plot(report: LoadTestReport, path: Path) -> Path:
    """Left: offered, answered and detections per second; right: client and server p99. Both against the
    vehicles on a log axis; the top axis gives the offered load of each count (sectors/s)."""
    plt = _pyplot()
    steps = report.steps
    v = [s.vehicles for s in steps]
    fig, (thr, p99) = plt.subplots(1, 2, figsize=(11, 4.4))
    thr.plot(v, [s.offered_sectors_per_s for s in steps], "--", color="grey", label="offered")
    thr.plot(v, [s.achieved_sectors_per_s for s in steps], "o-", label="answered")
    thr.plot(v, [s.predictions_per_s for s in steps], "s-", label="predictions")
    thr.set_ylabel("sectors / s")
    p99.plot(v, [s.p99_ms for s in steps], "o-", label="client p99")
    p99.plot(v, [s.server_total_p99_ms for s in steps], "s-", label="server total p99")
    failed = [s for s in steps if not s.passed]
    p99.plot([s.vehicles for s in failed], [s.p99_ms for s in failed], "x", color="red", label="failed")
    if report.config.thresholds.max_p99_ms is not None:
        p99.axhline(report.config.thresholds.max_p99_ms, color="grey", linestyle="--", label="p99 threshold")
    p99.set_yscale("log")
    p99.set_ylabel("latency (ms)")
    for ax in (thr, p99):
        ax.set_xscale("log", base=2)
        ax.set_xticks(v, [str(n) for n in v])
        ax.xaxis.set_minor_locator(plt.NullLocator())
        ax.set_xlabel("vehicles")
        ax.legend(fontsize=8)
        if report.mode == "open":  # offered load is proportional to the vehicles
            _offered_axis(ax, report).xaxis.set_minor_locator(plt.NullLocator())
    if report.mode == "closed":
        peak = report.peak_step
        what = f"throughput ceiling {peak.achieved_sectors_per_s:.1f} sectors/s with {peak.vehicles} vehicles"
    else:
        what = f"most vehicles held: {report.max_vehicles_held or 'none'}"
    fig.suptitle(f"PHiM {report.transport} {report.mode}-loop sweep: {what}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _offered_axis(ax, report: LoadTestReport):
    """A top axis in offered sectors/s (vehicles x sensor rate), ticked at each step."""
    rate = report.config.turns_per_s * report.sectors_per_turn  # sectors/s one vehicle offers
    top = ax.secondary_xaxis("top", functions=(lambda n: n * rate, lambda r: r / rate))
    offered = [s.vehicles * rate for s in report.steps]
    top.set_xticks(offered, [f"{x:g}" for x in offered])
    top.set_xlabel("offered sectors / s", fontsize=8)
    return top
