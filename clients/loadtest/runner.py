"""One load-test step: N vehicles, open loop (at sensor rate, from scheduled times) or closed loop.

Open loop: each vehicle's k-th sector is due at t0 + offset_v + k / rate and is sent then, whatever became of
the earlier ones (a send is a task of its own, never waiting for an answer); its latency runs from the due
time, so a server that falls behind shows it in full (no coordinated omission). One stream's sectors must
reach the server in order (it answers an overtaken one 409 stale): a sector's send starts once its previous
one is on its way (`send_async`'s `on_sent`: over HTTP its body is written, on a connection of its own;
over zenoh the get is queued on the session), which takes a fraction of a millisecond, not an answer.
Closed loop: each vehicle sends its next sector as soon as the last one is answered (in flight = vehicles).
After the sending window, outstanding sectors get up to `drain_timeout_s`; what is still unanswered then is
lost. Every scheduled sector is one Record.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import uuid
from collections.abc import Callable
from dataclasses import dataclass

from clients.base import ClientError, DetectorClient, ServerError, TransportError
from clients.loadtest.config import LoadTestConfig, Mode
from clients.loadtest.record import Record
from clients.loadtest.source import SectorSource
from contract import SectorMessage

Progress = Callable[["StepRun"], None]


@dataclass
class StepRun:
    vehicles: int
    t0: float  # loop time the first sector is due
    duration_s: float
    records: list[Record]
    stream_ids: list[str]
    send_end: float = 0.0  # loop time the sending window closed
    inflight: int = 0


class StepRunner:
    def __init__(self, client: DetectorClient, source: SectorSource, cfg: LoadTestConfig, spt: int):
        self.client = client
        self.source = source
        self.cfg = cfg
        self.period_s = 1.0 / (cfg.turns_per_s * spt)  # between two sectors of one vehicle

    async def run(self, vehicles: int, on_tick: Progress | None = None) -> StepRun:
        loop = asyncio.get_running_loop()
        tag = uuid.uuid4().hex[:6]
        ids = [f"{self.cfg.stream_prefix}-{tag}-{v}" for v in range(vehicles)]
        step = StepRun(vehicles, loop.time() + 0.05, self.cfg.duration_s, [], ids)
        ticker = asyncio.create_task(_tick(step, on_tick)) if on_tick else None
        try:
            if self.cfg.mode is Mode.OPEN:
                await self._open_loop(step)
            else:
                await asyncio.gather(*(self._closed_vehicle(step, v) for v in range(vehicles)))
            step.send_end = max(loop.time(), step.t0 + step.duration_s)
        finally:
            if ticker is not None:
                ticker.cancel()
                await asyncio.gather(ticker, return_exceptions=True)
        for r in step.records:
            r.settle_unanswered()
        if on_tick:
            on_tick(step)
        await self._end_streams(ids)
        return step

    # ------------------------------------------------------------------------------------------ open loop

    async def _open_loop(self, step: StepRun) -> None:
        rng = random.Random(self.cfg.seed + step.vehicles)
        offsets = [(v + rng.random()) / step.vehicles * self.period_s for v in range(step.vehicles)]
        tasks: set[asyncio.Task[None]] = set()
        await asyncio.gather(*(self._open_vehicle(step, v, offsets[v], tasks) for v in range(step.vehicles)))
        if tasks:
            _, pending = await asyncio.wait(tasks, timeout=self.cfg.drain_timeout_s)
            for t in pending:
                t.cancel()
            await asyncio.gather(*pending, return_exceptions=True)

    async def _open_vehicle(
        self, step: StepRun, v: int, offset: float, tasks: set[asyncio.Task[None]]
    ) -> None:
        loop = asyncio.get_running_loop()
        n = int(step.duration_s / self.period_s)
        previous: asyncio.Event | None = None  # set once the vehicle's previous sector is on its way
        for k in range(n):
            due = step.t0 + offset + k * self.period_s
            delay = due - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            rec = Record(v, k, due)
            step.records.append(rec)
            on_way = asyncio.Event()
            task = asyncio.create_task(self._send(step, rec, previous, on_way))
            tasks.add(task)
            task.add_done_callback(tasks.discard)
            previous = on_way

    # ---------------------------------------------------------------------------------------- closed loop

    async def _closed_vehicle(self, step: StepRun, v: int) -> None:
        loop = asyncio.get_running_loop()
        end, k = step.t0 + step.duration_s, 0
        delay = step.t0 - loop.time()
        if delay > 0:
            await asyncio.sleep(delay)
        while loop.time() < end:
            rec = Record(v, k, loop.time())
            step.records.append(rec)
            guard = (
                self.cfg.connect.timeout_s + self.cfg.drain_timeout_s
            )  # the client's own timeout comes first
            with contextlib.suppress(TimeoutError):  # unanswered: counted as lost (drain)
                await asyncio.wait_for(self._send(step, rec), guard)
            k += 1

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
            if on_way is not None:
                on_way.set()

    async def _end_streams(self, ids: list[str]) -> None:
        for sid in ids:
            with contextlib.suppress(ClientError):  # already evicted or never started: nothing to end
                await asyncio.to_thread(self.client.end_stream, sid)


async def _tick(step: StepRun, on_tick: Progress, every_s: float = 0.25) -> None:
    while True:
        on_tick(step)
        await asyncio.sleep(every_s)
