"""The worker: the model, the stream table and the scheduler, behind one thread-safe `submit`.

One device-loop thread owns the model. Transports call `submit` from any thread; it validates the sector,
admits it to its stream's queue (or fails the returned future at once) and never blocks. The loop forms a
batch of at most one sector per stream (the oldest waiting first), bounded by `max_batch` and `max_wait_ms`
(and, where the engine pads batches to buckets, preferring full ones: `server.scheduler`), runs the engine's
`step` once (`server.batch`), writes the new states back and answers every sector with its own reply or its
own error. A stream's next sector waits until its previous one has run, so each stream stays in order. The
model is reached only through the engine interface (`model.engine`). numpy <-> torch conversion happens
here (`server.admission`): transports never see a tensor.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

import torch

from contract import DetectionsReply, ErrorCode, SectorMessage, ServiceError
from model.engine import EngineState, StreamEngine
from server.admission import Backlog, sector_points
from server.batch import Answer, Observer, engine_buckets, gap_of, observe, run_batch, settle
from server.metrics import Metrics
from server.outcomes import expired_error
from server.scheduler import Wait, batch_fill, decide, fair_order
from server.streams import Pending, StreamEntry, StreamTable, queued_of
from server.tenants import TenantQueue, half, plan_push_out, pushed_out_error, tenant_of_id
from server.warmup import model_info, warm_up

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class WorkerConfig:
    worker_id: str = "phim-worker"
    max_batch: int = 8  # sectors (one per stream) per forward
    max_wait_ms: float = 0.0  # how long the oldest sector may wait for a fuller batch (0: take what's queued)
    queue_size: int = 64  # sectors waiting, all streams together; beyond: OVERLOADED
    max_queued_points: int = 4_000_000  # points waiting, all streams together; beyond: OVERLOADED
    deadline_ms: float = 2000.0  # a sector not started by then gets DEADLINE_EXCEEDED
    idle_timeout_s: float = 10.0
    max_streams: int = 256
    warmup_sectors: int = 5
    min_score: float = 0.0  # replies keep the boxes scored at least this, unless a sector says otherwise
    tenant_max_streams: int | None = None  # live streams per tenant (server/tenants.py); None: half
    tenant_queue_size: int | None = None  # queued sectors a tenant is guaranteed; None: half of queue_size

    def tenant_shares(self) -> tuple[int, int, int]:
        """(streams, queued sectors, queued points) per tenant; the points share is the sectors' fraction."""
        streams = self.tenant_max_streams or half(self.max_streams)
        sectors = min(self.queue_size, self.tenant_queue_size or half(self.queue_size))
        return streams, sectors, max(1, self.max_queued_points * sectors // self.queue_size)


class Worker:
    """One model, one device thread, many streams.

    `load` builds the engine (`model.engine`) and says where its weights come from. It runs in the device
    thread, the only thread that runs the model: with OpenMP, a second thread that has run parallel CPU ops
    (even just building the model) makes every forward about 3x slower on a 2-core machine (libgomp
    throttles its spin-waits once it manages more threads than there are CPUs)."""

    def __init__(
        self,
        load: Callable[[], tuple[StreamEngine, str]],
        cfg: WorkerConfig = WorkerConfig(),
        metrics: Metrics | None = None,
        observer: Observer | None = None,
        tenant_of: Callable[[str], str] = tenant_of_id,
    ):
        self._load = load
        self._observer = observer  # the live view (server/live_view.py); None: nothing watches
        self._det: StreamEngine | None = None
        self._source = ""  # where the weights came from (for /v1/model)
        self._buckets: tuple[int, ...] | None = None  # the engine's batch buckets (None: batches unpadded)
        self.cfg = cfg
        self.worker_id = cfg.worker_id
        self.metrics = metrics or Metrics()
        tenant_streams, tenant_sectors, tenant_points = cfg.tenant_shares()
        self.table = StreamTable(
            cfg.max_streams,
            cfg.idle_timeout_s,
            self._evicted,
            lambda: self.det.new_state(),  # streams start once the engine is loaded (ready)
            lambda state: self.det.release(state),
            tenant_of,
            tenant_streams,
        )
        self._cond = threading.Condition()
        self._backlog = Backlog(cfg.queue_size, cfg.max_queued_points)  # sectors queued (not running)
        self._tenants = TenantQueue(tenant_sectors, tenant_points)  # the same, per tenant
        self._ready = False
        self._closing = False
        self._drain_until = math.inf
        self._startup_error: str | None = None
        self._batch_s = 0.1  # moving average of one forward, for Retry-After
        self._evict_tick_s = min(1.0, max(0.01, cfg.idle_timeout_s / 4))
        self._next_evict = 0.0
        self._thread: threading.Thread | None = None
        self.metrics.bind(lambda: self._backlog.sectors, lambda: len(self.table))
        self.metrics.max_streams.set(cfg.max_streams)
        self.metrics.max_queued.set(cfg.queue_size)

    # ------------------------------------------------------------------------------------ public surface

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=f"phim-device-{self.worker_id}", daemon=True)
        self._thread.start()

    @property
    def ready(self) -> bool:
        return self._ready

    @property
    def live(self) -> bool:
        """The device loop is alive (or not started yet); False after a crash or a failed start-up."""
        return self._startup_error is None and (
            self._thread is None or self._thread.is_alive() or self._closing
        )

    @property
    def status(self) -> str:
        if self._startup_error:
            return f"start-up failed: {self._startup_error}"
        if self._closing:
            return "shutting down"
        return "ready" if self._ready else "warming up"

    @property
    def queue_depth(self) -> int:
        return self._backlog.sectors

    def wait_ready(self, timeout_s: float) -> bool:
        """Block until warmed up (True), or loading / warm-up failed or the timeout passed (False)."""
        with self._cond:
            self._cond.wait_for(lambda: self._ready or self._startup_error is not None, timeout_s)
            return self._ready

    def submit(self, msg: SectorMessage, transport: str = "direct") -> Future[DetectionsReply]:
        """Queue one sector; never blocks. The future gets the reply or a ServiceError, exactly once."""
        fut: Future[DetectionsReply] = Future()
        now = time.monotonic()
        try:
            points = sector_points(msg, self.det.cfg)
            with self._cond:
                pushed_out = self._admit(msg, points, fut, transport, now)
                self._cond.notify_all()
            settle(self.metrics, pushed_out)
        except ServiceError as e:
            settle(self.metrics, [(fut, transport, e)])
        except Exception as e:  # a bug must still give this sector its one answer
            log.exception("submit of %s seq %s failed", msg.stream_id, msg.seq)
            settle(
                self.metrics, [(fut, transport, ServiceError(ErrorCode.INTERNAL, f"{type(e).__name__}: {e}"))]
            )
        return fut

    def end_stream(self, stream_id: str) -> None:
        """Drop a stream's state; its queued sectors are answered UNKNOWN_STREAM. Raises if not live."""
        with self._cond:
            entry = self.table.end(stream_id)
            failed = self._drop_pending(entry, ErrorCode.UNKNOWN_STREAM, f"stream {stream_id!r} was ended")
        settle(self.metrics, failed)

    def streams(self) -> list[dict[str, Any]]:
        now = time.monotonic()
        with self._cond:
            return [e.summary(now) for e in self.table.entries.values()]

    def stream(self, stream_id: str) -> dict[str, Any]:
        with self._cond:
            entry = self.table.get(stream_id)
            if entry is None:
                raise self.table.unknown(stream_id)
            return entry.summary(time.monotonic())

    @property
    def det(self) -> StreamEngine:
        """The engine, once the device thread has loaded it (NOT_READY before)."""
        if self._det is None:
            raise ServiceError(ErrorCode.NOT_READY, f"worker {self.worker_id}: {self.status}; no model yet")
        return self._det

    def model_info(self) -> dict[str, Any]:
        return {**model_info(self.det, self._source, self.worker_id), "min_score": self.cfg.min_score}

    def close(self, drain_timeout_s: float = 10.0, forward_grace_s: float = 30.0) -> None:
        """Stop taking sectors and answer every queued one: run while the drain timeout lasts, NOT_READY after
        it. Then wait up to `forward_grace_s` for the forward in progress (its sectors get their results)."""
        with self._cond:
            if not self._closing:
                self._closing = True
                self._ready = False
                self.metrics.ready.set(0)
                self._drain_until = time.monotonic() + drain_timeout_s
                self._cond.notify_all()
            self._cond.wait_for(lambda: self._backlog.sectors == 0, drain_timeout_s)
            failed = self._expire(math.inf)  # what the loop did not get to (stuck, slow or never started)
        settle(self.metrics, failed)
        if self._thread is not None:
            self._thread.join(forward_grace_s)
            if self._thread.is_alive():
                log.warning(
                    "device loop still in a forward %.1f s after the drain; leaving it", forward_grace_s
                )

    # ------------------------------------------------------------------------------------------ admission

    def _admit(
        self,
        msg: SectorMessage,
        points: torch.Tensor,
        fut: Future[DetectionsReply],
        transport: str,
        now: float,
    ) -> list[Answer]:
        """Under the lock: check readiness, queue room and sequence, then queue the sector. A full queue
        takes the sector of a tenant within its share by pushing out sectors of tenants beyond theirs
        (server/tenants.py): their answers (OVERLOADED) are returned, to be settled outside the lock."""
        if self._closing or not self._ready:
            raise ServiceError(
                ErrorCode.NOT_READY, f"worker {self.worker_id}: {self.status}; not taking sectors"
            )
        n = int(points.shape[0])
        retry = max(0.01, math.ceil(self._backlog.sectors / self.cfg.max_batch) * self._batch_s)
        tenant = self.table.tenant(msg.stream_id)
        room: list[Pending] | None = []
        try:
            self._backlog.check(n, retry)
        except ServiceError:
            room = plan_push_out(
                self._tenants, self._backlog, tenant, n, lambda t: queued_of(self.table.entries.values(), t)
            )
            if room is None:
                raise
        entry = self.table.admit(msg, now, tenant)
        pushed_out = [self._push_out(p, retry) for p in room]
        deadline = now + self.cfg.deadline_ms / 1e3
        entry.pending.append(Pending(msg, points, fut, transport, entry, now, deadline))
        self._backlog.add(n)
        self._tenants.add(tenant, n)
        return pushed_out

    def _push_out(self, p: Pending, retry_s: float) -> Answer:
        """Under the lock: take a queued sector (its stream's newest) out to make room for another's."""
        error = pushed_out_error(p.entry.tenant, self._tenants, self.cfg.queue_size, retry_s)
        assert p.entry.pending[-1] is p, "only a stream's newest sector is pushed out"
        p.entry.pending.pop()
        self._unqueue([p])
        p.entry.forget_failed()
        return p.future, p.transport, error

    def _unqueue(self, pending: list[Pending]) -> None:
        """Under the lock: these sectors leave the queue (they run or are answered)."""
        self._backlog.remove(int(p.points.shape[0]) for p in pending)
        for p in pending:
            self._tenants.remove(p.entry.tenant, int(p.points.shape[0]))

    def _drop_pending(self, entry: StreamEntry, code: ErrorCode, why: str) -> list[Answer]:
        failed: list[Answer] = [
            (p.future, p.transport, ServiceError(code, f"{why} before seq {p.msg.seq} ran"))
            for p in entry.pending
        ]
        self._unqueue(list(entry.pending))
        entry.pending.clear()
        self._cond.notify_all()
        entry.forget_failed()
        return failed

    def _evicted(self, stream_id: str) -> None:
        self.metrics.evictions.inc()
        log.info("stream %s evicted after %.1f s idle", stream_id, self.cfg.idle_timeout_s)

    # -------------------------------------------------------------------------------------- device loop

    def _run(self) -> None:
        try:
            self._det, self._source = self._load()
            self._buckets = engine_buckets(self._det, self.cfg.max_streams)
            self.metrics.model_loaded(self.model_info())
            self._batch_s = warm_up(self._det, self.cfg.warmup_sectors, self.cfg.max_batch)
        except Exception as e:
            log.exception("loading or warming up the model failed; the worker will never be ready")
            with self._cond:
                self._startup_error = f"{type(e).__name__}: {e}"
                self._cond.notify_all()
            return
        with self._cond:
            self._ready = not self._closing
            self.metrics.ready.set(int(self._ready))
            self._cond.notify_all()
        log.info("worker %s ready (one forward about %.1f ms)", self.worker_id, self._batch_s * 1e3)
        while (batch := self._next_batch()) is not None:
            self._run_batch(batch)
            del batch  # while it waits for the next batch, the loop holds no stream of this one

    def _next_batch(self) -> list[Pending] | None:
        """Block until a batch is due; None when closing and nothing is left."""
        while True:
            with self._cond:
                now = time.monotonic()
                failed = self._expire(now)
                if now >= self._next_evict:
                    self.table.evict_idle(now)
                    self._next_evict = now + self._evict_tick_s
                if not failed:
                    due = self._form_batch(now)
                    if due is None or isinstance(due, list):
                        return due
                    self._cond.wait(due)
                    continue
            settle(self.metrics, failed)

    def _form_batch(self, now: float) -> list[Pending] | float | None:
        """A batch, or seconds to wait for one, or None (closing and drained)."""
        heads = [e for e in self.table.entries.values() if e.pending]
        if not heads:
            return None if self._closing else max(0.0, self._next_evict - now)
        heads.sort(key=lambda e: e.pending[0].submitted)  # oldest first; the batch: round-robin by tenant
        waited = now - heads[0].pending[0].submitted
        cfg = self.cfg
        due = decide(
            len(heads),
            len(self.table),
            waited,
            cfg.max_wait_ms / 1e3,
            cfg.max_batch,
            self._buckets,
            self._closing,
        )
        if isinstance(due, Wait):
            return due.seconds
        batch = [heads[i].pending.popleft() for i in fair_order([e.tenant for e in heads])[: due.sectors]]
        for p in batch:
            p.entry.running = True
        self._unqueue(batch)
        self._cond.notify_all()  # close() waits for the queue to empty
        return batch

    def _expire(self, now: float) -> list[Answer]:
        """Under the lock: take out sectors past their deadline (or everything after the drain timeout)."""
        failed: list[Answer] = []
        draining_over = now >= self._drain_until
        for entry in self.table.entries.values():
            before = len(failed)
            while entry.pending and (draining_over or entry.pending[0].deadline < now):
                p = entry.pending.popleft()
                self._unqueue([p])
                error = expired_error(p, now, draining_over, self.worker_id, self.cfg.deadline_ms)
                failed.append((p.future, p.transport, error))
            if len(failed) > before:
                entry.forget_failed()
        if failed:
            self._cond.notify_all()
        return failed

    def _run_batch(self, batch: list[Pending]) -> None:
        with self._cond:
            gaps = [gap_of(p) for p in batch]
            colds = [p.msg.reset or p.entry.last_seq is None for p in batch]  # on a fresh state
            # a reset: a fresh state (in the same slot, where the engine has slots; nothing written yet)
            states = [self.det.reset(p.entry.state) if p.msg.reset else p.entry.state for p in batch]
        ran = run_batch(self.det, batch, states, gaps, colds, self.cfg.min_score, self.worker_id)
        if ran.failed:
            self.metrics.batch_failures.inc()
        self._batch_s = 0.8 * self._batch_s + 0.2 * ran.model_s
        self.metrics.batch_sectors.observe(len(batch))
        self.metrics.batch_fill.observe(batch_fill(len(batch), self._buckets))
        with self._cond:
            for p, new_state, gap in zip(batch, ran.new_states, gaps, strict=True):
                self._finish(p, new_state, gap)
        settle(self.metrics, ran.answers)
        if self._observer is not None:
            observe(self._observer, batch, ran.answers)

    def _finish(self, p: Pending, new_state: EngineState | None, gap: int) -> None:
        """Under the lock: write the new state back (unless the sector failed or the stream ended: an ended
        stream's state goes back to the detector now)."""
        e = p.entry
        e.running = False
        e.last_seen = time.monotonic()
        live = self.table.finished(e)
        if new_state is None:
            e.forget_failed()
        elif live:
            e.state, e.last_seq, e.last_timestamp_ns = new_state, p.msg.seq, p.msg.timestamp_ns
            e.sectors += 1
            e.gaps += gap
