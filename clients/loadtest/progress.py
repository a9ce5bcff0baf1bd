"""A live progress line per step (rich): time, sent, answered, errors, lost so far, in flight, p99."""

from __future__ import annotations

import asyncio
from types import TracebackType

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, Progress, TaskID, TextColumn, TimeElapsedColumn

from clients.loadtest.runner import StepRun


class LiveProgress:
    def __init__(self, enabled: bool = True, console: Console | None = None):
        self.enabled = enabled
        self._progress = Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            TimeElapsedColumn(),
            TextColumn("{task.fields[stats]}"),
            console=console or Console(stderr=True),
            transient=False,
            disable=not enabled,
        )
        self._task: TaskID | None = None

    def __enter__(self) -> LiveProgress:
        self._progress.start()
        return self

    def __exit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._progress.stop()

    def start_step(self, vehicles: int, duration_s: float) -> None:
        self._task = self._progress.add_task(f"{vehicles:>4} vehicles", total=duration_s, stats="")

    def tick(self, step: StepRun) -> None:
        if self._task is None:
            return
        now = asyncio.get_running_loop().time() if step.send_end == 0.0 else step.send_end
        answered = [r for r in step.records if r.answered]
        recent = np.array([r.latency_ms for r in answered[-2000:]])
        p99 = f"{np.percentile(recent, 99):.1f}" if recent.size else "-"
        errors = sum(1 for r in answered if not r.ok)
        lost = sum(1 for r in step.records if r.lost is not None)
        stats = (
            f"sent {len(step.records)}  answered {len(answered)}  errors {errors}  lost {lost}  "
            f"in flight {step.inflight}  p99 {p99} ms"
        )
        self._progress.update(self._task, completed=min(now - step.t0, step.duration_s), stats=stats)
