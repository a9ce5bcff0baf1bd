"""What a load test runs: one dataclass, filled by the CLI or by tests."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from pathlib import Path

from clients.connect import ConnectConfig


class Mode(enum.StrEnum):
    OPEN = "open"  # each sector at its scheduled time, latency from that time (no coordinated omission)
    CLOSED = "closed"  # each vehicle sends its next sector when the last is answered: maximum throughput


@dataclass(frozen=True)
class SourceConfig:
    folder: Path | None = None  # KITTI velodyne .bin scans or native .npz scans; None: synthetic turns
    max_scans: int = 20  # scans read from the folder (they are cycled)
    every: int = 1  # keep every n-th point (lighter sectors)
    synthetic_turns: int = 4  # distinct synthetic turns when no folder is given


@dataclass(frozen=True)
class Thresholds:
    """What a step must meet to pass (None: not checked): p99 latency, and its error rate, the fraction of
    its sectors answered with an error or lost. A step also fails when it did not stabilize (windows).
    `enforced`: the exit code follows the verdict (the CLI sets it when a threshold is given); without it
    the defaults only judge which steps held."""

    max_p99_ms: float | None = 25.0  # one sector period at 10 turns/s x 4 sectors
    max_error_rate: float | None = 0.0
    enforced: bool = False


@dataclass(frozen=True)
class WindowConfig:
    """perf_analyzer's stability: measure in windows of `window_s` until the last `count` windows agree
    within `stability_pct` % (replies/s and p99), or `max_windows` have passed (the step did not stabilize:
    reported, and it fails)."""

    window_s: float
    stability_pct: float = 10.0
    max_windows: int = 10
    count: int = 3


@dataclass(frozen=True)
class LoadTestConfig:
    connect: ConnectConfig = field(default_factory=ConnectConfig)
    source: SourceConfig = field(default_factory=SourceConfig)
    mode: Mode = Mode.OPEN
    vehicles: tuple[int, ...] = (1,)  # one step per entry; several entries make a sweep
    duration_s: float = 10.0  # per step: how long sectors are sent and counted (without windows)
    warmup_s: float = 0.0  # per step, before the measurement: sent at the same rate, not counted
    windows: WindowConfig | None = None  # measure in windows until stable (instead of duration_s)
    thresholds: Thresholds = field(default_factory=Thresholds)
    turns_per_s: float = 10.0  # sensor rate of every vehicle
    sectors_per_turn: int | None = None  # None: ask the server (GET /v1/model), else 4
    drain_timeout_s: float = 10.0  # after the last send, wait this long for outstanding replies
    stop_after_failure: bool = True  # an open-loop sweep stops at the first step that does not hold
    settle_s: float = 0.5  # pause between sweep steps
    stream_prefix: str = "loadtest"
    stream_tag: str | None = None  # the IDs' middle part (None: random per step, so reruns never collide)
    seed: int = 0  # vehicle start offsets and scan choice

    @property
    def sweep(self) -> bool:
        return len(self.vehicles) > 1

    @property
    def measure_s(self) -> float:
        """The longest a step measures: duration_s, or every window."""
        return self.duration_s if self.windows is None else self.windows.max_windows * self.windows.window_s


@dataclass(frozen=True)
class OutputConfig:
    json_path: Path | None = None
    csv_path: Path | None = None
    plots_dir: Path | None = None
    progress: bool = True
