"""One load-test step: N vehicles, open loop (at sensor rate, from scheduled times) or closed loop.

Timeline of a step: a warm-up (`warmup_s`, sent the same way, not counted), then the measurement: either
`duration_s`, or windows of `window_s` judged as each ends (clients.loadtest.windows.is_stable) until the
last few agree or `max_windows` have passed; sending stops there. Then outstanding sectors get up to
`drain_timeout_s`; what is still unanswered is lost. Every sector sent is one Record.

Open loop: each vehicle's k-th sector is due at t0 + offset_v + k / rate and is sent then, whatever became of
the earlier ones (a send is a task of its own, never waiting for an answer); its latency runs from the due
time, so a server that falls behind shows it in full (no coordinated omission). One stream's sectors must
reach the server in order (it answers an overtaken one 409 stale): a sector's send starts once its previous
one is on its way (`send_async`'s `on_sent`: over HTTP its body is written, on a connection of its own;
over zenoh the get is queued on the session), which takes a fraction of a millisecond, not an answer.
Closed loop: each vehicle sends its next sector as soon as the last one is answered (in flight = vehicles).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import random
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field

from clients.base import ClientError, DetectorClient, ServerError, TransportError
from clients.loadtest.config import LoadTestConfig, Mode, WindowConfig
from clients.loadtest.record import Lost, Record
from clients.loadtest.source import SectorSource
from clients.loadtest.windows import Span, Timeline, is_stable
from contract import SectorMessage

Progress = Callable[["StepRun"], None]


@dataclass
class StepRun:
    """A step as it runs. Loop times (s): t0 <= measure_from <= counted_from <= stop."""

    vehicles: int
    t0: float  # the first sector is due (the warm-up starts)
    measure_from: float  # the warm-up ends
    stop: float  # no sector is due from here on (moved earlier once the windows are stable)
    stream_ids: list[str]
    counted_from: float = 0.0  # the step's results count sectors due from here (the stable windows)
    records: list[Record] = field(default_factory=list)
    windows: list[Span] = field(default_factory=list)
    stable: bool | None = None  # None: no windows, stability not judged
    send_end: float = 0.0  # loop time the vehicles stopped sending (closed loop: last answer in)
    drain_end: float = 0.0  # loop time the drain was over
    inflight: int = 0
    t0_unix: float = 0.0  # t0 on the wall clock (to line the step up with server logs and metrics)

    def counted(self, rec: Record) -> bool:
        """Whether a sector belongs to the step's results (due in the counted span)."""
        return self.counted_from <= rec.scheduled < self.stop


class StepRunner:
    def __init__(self, client: DetectorClient, source: SectorSource, cfg: LoadTestConfig, spt: int):
        self.client = client
        self.source = source
        self.cfg = cfg
        self.period_s = 1.0 / (cfg.turns_per_s * spt)  # between two sectors of one vehicle

    async def run(self, vehicles: int, on_tick: Progress | None = None) -> StepRun:
        loop = asyncio.get_running_loop()
        tag = self.cfg.stream_tag or uuid.uuid4().hex[:6]
        ids = [f"{self.cfg.stream_prefix}-{tag}-{v}" for v in range(vehicles)]
        t0 = loop.time() + 0.05
        start = t0 + self.cfg.warmup_s
        step = StepRun(vehicles, t0, start, start + self.cfg.measure_s, ids, counted_from=start)
        step.t0_unix = time.time() + (t0 - loop.time())
        ticker = asyncio.create_task(_tick(step, on_tick)) if on_tick else None
        judge = asyncio.create_task(_judge(step, self.cfg.windows)) if self.cfg.windows else None
        tasks: set[asyncio.Task[None]] = set()
        try:
            if self.cfg.mode is Mode.OPEN:
                await self._open_loop(step, tasks)
            else:
                await asyncio.gather(*(self._closed_vehicle(step, v) for v in range(vehicles)))
            step.send_end = loop.time()
            await self._drain(tasks)
            if judge is not None:
                await judge  # it has judged the last window by now, or is about to
        finally:
            helpers = [t for t in (ticker, judge) if t is not None]
            for helper in helpers:
                helper.cancel()
            await asyncio.gather(*helpers, return_exceptions=True)
        step.drain_end = loop.time()
        for r in step.records:
            r.settle_unanswered()
        if on_tick:
            on_tick(step)
        await self._end_streams(ids)
        return step

    async def _drain(self, tasks: set[asyncio.Task[None]]) -> None:
        if tasks:
            _, pending = await asyncio.wait(tasks, timeout=self.cfg.drain_timeout_s)
            for t in pending:
                t.cancel()
            await asyncio.gather(*pending, return_exceptions=True)

    # ------------------------------------------------------------------------------------------ open loop

    async def _open_loop(self, step: StepRun, tasks: set[asyncio.Task[None]]) -> None:
        rng = random.Random(self.cfg.seed + step.vehicles)
        offsets = [(v + rng.random()) / step.vehicles * self.period_s for v in range(step.vehicles)]
        await asyncio.gather(*(self._open_vehicle(step, v, offsets[v], tasks) for v in range(step.vehicles)))

    async def _open_vehicle(
        self, step: StepRun, v: int, offset: float, tasks: set[asyncio.Task[None]]
    ) -> None:
        loop = asyncio.get_running_loop()
        previous: asyncio.Event | None = None  # set once the vehicle's previous sector is on its way
        for k in itertools.count():
            due = step.t0 + offset + k * self.period_s
            if due >= step.stop:
                return
            delay = due - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            if due >= step.stop:  # the windows became stable while this vehicle slept
                return
            rec = Record(v, k, due)
            step.records.append(rec)
            on_way = asyncio.Event()
            task = asyncio.create_task(self._send(step, rec, previous, on_way))
            tasks.add(task)
            task.add_done_callback(tasks.discard)  # the drain waits for what is left
            previous = on_way

    # ---------------------------------------------------------------------------------------- closed loop

    async def _closed_vehicle(self, step: StepRun, v: int) -> None:
        loop = asyncio.get_running_loop()
        delay = step.t0 - loop.time()
        if delay > 0:
            await asyncio.sleep(delay)
        guard = self.cfg.connect.timeout_s + self.cfg.drain_timeout_s  # the client's own timeout comes first
        backoff = 0.0  # after a transport failure (server gone): wait before the next send, doubling to 1 s
        for k in itertools.count():
            if loop.time() >= step.stop:
                return
            rec = Record(v, k, loop.time())
            step.records.append(rec)
            with contextlib.suppress(TimeoutError):  # unanswered: counted as lost (drain)
                await asyncio.wait_for(self._send(step, rec), guard)
            backoff = min(1.0, max(0.05, 2 * backoff)) if rec.lost is Lost.TRANSPORT else 0.0
            if backoff:
                await asyncio.sleep(min(backoff, max(0.0, step.stop - loop.time())))

    # ------------------------------------------------------------------------------------------- helpers

    def _message(self, step: StepRun, rec: Record) -> SectorMessage:
        index, points = self.source.sector(rec.vehicle, rec.seq)
        return SectorMessage(
            stream_id=step.stream_ids[rec.vehicle],
            seq=rec.seq,
            sector_index=index,
            timestamp_ns=round((rec.scheduled - step.t0) * 1e9),
            points=points,
            fields=self.source.fields,
        )

    async def _send(
        self,
        step: StepRun,
        rec: Record,
        after: asyncio.Event | None = None,
        on_way: asyncio.Event | None = None,
    ) -> None:
        """Send rec's sector once `after` is set (the previous sector of its stream is on its way), set
        `on_way` when this one is (or has failed), and settle the record."""
        loop = asyncio.get_running_loop()
        try:
            if after is not None:
                await after.wait()
            msg = self._message(step, rec)
            rec.sent = loop.time()
            step.inflight += 1
            try:
                reply = await self.client.send_async(msg, None if on_way is None else on_way.set)
            except (ServerError, TransportError) as e:
                rec.settle_error(loop.time(), e)
            else:
                rec.settle_ok(loop.time(), reply)
            finally:
                step.inflight -= 1
        finally:
            if on_way is not None:
                on_way.set()

    async def _end_streams(self, ids: list[str]) -> None:
        for sid in ids:
            with contextlib.suppress(ClientError):  # already evicted or never started: nothing to end
                await asyncio.to_thread(self.client.end_stream, sid)


async def _judge(step: StepRun, cfg: WindowConfig) -> None:
    """Judge each window as it ends; once the last `count` agree, end the step there (else at the last)."""
    loop = asyncio.get_running_loop()
    for i in range(cfg.max_windows):
        start = step.measure_from + i * cfg.window_s
        end = start + cfg.window_s
        await asyncio.sleep(max(0.0, end - loop.time()))
        step.windows.append(Timeline(step.records, step.t0).span(start - step.t0, end - step.t0))
        step.stable = is_stable(step.windows, cfg.count, cfg.stability_pct)
        first = step.windows[-min(cfg.count, len(step.windows))]
        step.counted_from = step.t0 + first.start_s
        if step.stable:
            step.stop = end
            return


async def _tick(step: StepRun, on_tick: Progress, every_s: float = 0.25) -> None:
    while True:
        on_tick(step)
        await asyncio.sleep(every_s)
