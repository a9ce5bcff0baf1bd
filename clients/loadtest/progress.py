"""A live progress line per step (rich): time, sent, answered, errors, lost so far, in flight, recent p99
(and the windows judged so far)."""

from __future__ import annotations

import asyncio
from types import TracebackType

from rich.console import Console
from rich.progress import BarColumn, Progress, TaskID, TextColumn, TimeElapsedColumn

from clients.loadtest.hdr import histogram, percentile_ms
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
        self._total_s = 0.0

    def __enter__(self) -> LiveProgress:
        self._progress.start()
        return self

    def __exit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._progress.stop()

    def start_step(self, vehicles: int, total_s: float) -> None:
        self._total_s = total_s
        self._task = self._progress.add_task(f"{vehicles:>4} vehicles", total=total_s, stats="")

    def tick(self, step: StepRun) -> None:
        if self._task is None or not self.enabled:
            return
        answered = [r for r in step.records if r.answered]
        p99 = percentile_ms(histogram(r.latency_ms for r in answered[-2000:]), 99.0)
        errors = sum(1 for r in answered if not r.ok)
        lost = sum(1 for r in step.records if r.lost is not None)
        stable = "" if step.stable is None else f"  windows {len(step.windows)} stable {step.stable}"
        stats = (
            f"sent {len(step.records)}  answered {len(answered)}  errors {errors}  lost {lost}  "
            f"in flight {step.inflight}  p99 {p99:.1f} ms{stable}"
        )
        elapsed = asyncio.get_running_loop().time() - step.t0
        done = self._total_s if step.send_end else min(elapsed, self._total_s)
        self._progress.update(self._task, completed=done, stats=stats)
