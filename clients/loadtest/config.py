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
class LoadTestConfig:
    connect: ConnectConfig = field(default_factory=ConnectConfig)
    source: SourceConfig = field(default_factory=SourceConfig)
    mode: Mode = Mode.OPEN
    vehicles: tuple[int, ...] = (1,)  # one step per entry; several entries make a sweep
    duration_s: float = 10.0  # per step: how long sectors are sent
    turns_per_s: float = 10.0  # sensor rate of every vehicle
    sectors_per_turn: int | None = None  # None: ask the server (GET /v1/model), else 4
    drain_timeout_s: float = 10.0  # after the last send, wait this long for outstanding replies
    p99_bound_ms: float = 25.0  # a sweep step "holds" when p99 <= this, with no errors and nothing lost
    stop_after_failure: bool = True  # a sweep stops at the first step that does not hold
    settle_s: float = 0.5  # pause between sweep steps
    stream_prefix: str = "loadtest"
    seed: int = 0  # vehicle start offsets and scan choice

    @property
    def sweep(self) -> bool:
        return len(self.vehicles) > 1


@dataclass(frozen=True)
class OutputConfig:
    json_path: Path | None = None
    csv_path: Path | None = None
    plots_dir: Path | None = None
    progress: bool = True
