"""One batch through the engine, outside the worker's lock: its step, each sector's own answer, and the
streams' new states. Anything failing in the step fails this batch only (every sector gets INTERNAL, every
stream keeps its state): the device loop goes on."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, InvalidStateError
from dataclasses import dataclass

from contract import DetectionsReply, ErrorCode, SectorMessage, ServiceError
from model.engine import EngineState, SectorRejected, StreamEngine
from server.metrics import OK, Metrics
from server.outcomes import sector_answer
from server.streams import Pending

log = logging.getLogger(__name__)

Answer = tuple[Future[DetectionsReply], str, DetectionsReply | ServiceError]  # future, transport, outcome
# sees each answered sector with its reply, in the device thread after the answer: must be cheap, never block
Observer = Callable[[SectorMessage, DetectionsReply], None]


@dataclass(frozen=True)
class BatchRun:
    answers: list[Answer]  # each sector's, in batch order
    new_states: list[EngineState | None]  # None: the stream keeps the state it had (its sector did not run)
    model_s: float  # seconds of the step
    failed: bool  # the step raised: every sector got INTERNAL


def run_batch(
    engine: StreamEngine,
    batch: Sequence[Pending],
    states: list[EngineState],
    gaps: list[int],
    colds: list[bool],
    min_score: float,
    worker_id: str,
) -> BatchRun:
    """Step `batch` (sector i on states[i]; gaps[i]: sectors its stream missed, colds[i]: on a fresh state)
    and answer each sector (`server.outcomes.sector_answer`, boxes scored at least `min_score` unless the
    sector asks otherwise)."""
    t0 = time.monotonic()
    try:
        names = engine.cfg.head.class_names
        results, stepped = engine.step([p.points for p in batch], states)
        model_s = time.monotonic() - t0
        answers: list[Answer] = [
            (p.future, p.transport, sector_answer(p, r, g, c, t0, model_s, names, worker_id, min_score))
            for p, r, g, c in zip(batch, results, gaps, colds, strict=True)
        ]
        new_states: list[EngineState | None] = [
            None if isinstance(r, SectorRejected) else s for r, s in zip(results, stepped, strict=True)
        ]
        return BatchRun(answers, new_states, model_s, False)
    except Exception as e:
        log.exception("forward of a batch of %d failed", len(batch))
        why = f"model failed on this batch of {len(batch)}: {type(e).__name__}: {e}"
        answers = [(p.future, p.transport, ServiceError(ErrorCode.INTERNAL, why)) for p in batch]
        return BatchRun(answers, [None] * len(batch), time.monotonic() - t0, True)


def observe(observer: Observer, batch: Sequence[Pending], answers: list[Answer]) -> None:
    """After the answers (a watcher never delays a reply): each answered sector to the observer; what it
    raises is logged, never the batch's failure."""
    for p, (_, _, out) in zip(batch, answers, strict=True):
        if isinstance(out, DetectionsReply):
            try:
                observer(p.msg, out)
            except Exception:
                log.exception("observer failed on %s seq %d; serving goes on", p.msg.stream_id, p.msg.seq)


def gap_of(p: Pending) -> int:
    """Sectors missed since the stream's last sector that ran (0 for a new or reset stream)."""
    last = p.entry.last_seq
    return 0 if p.msg.reset or last is None else max(0, p.msg.seq - last - 1)


def settle(metrics: Metrics, answers: list[Answer]) -> None:
    """Outside the worker's lock: count each sector (before its answer: a client that has it sees it counted)
    and give it its one answer."""
    for fut, transport, out in answers:
        metrics.count(transport, OK if isinstance(out, DetectionsReply) else out.code.value)
        if isinstance(out, DetectionsReply):
            t = out.timings
            metrics.queue_latency.observe(t.queue_ms / 1e3)
            metrics.model_latency.observe(t.model_ms / 1e3)
            metrics.sector_latency.observe(t.total_ms / 1e3)
        try:
            if isinstance(out, ServiceError):
                fut.set_exception(out)
            else:
                fut.set_result(out)
        except InvalidStateError:  # the caller cancelled (client went away); the sector still counted
            pass


def engine_buckets(engine: StreamEngine, max_streams: int) -> tuple[int, ...] | None:
    """A loaded engine's batch buckets (None: batches run unpadded), from its description; ValueError if it
    has fewer stream-state slots than `max_streams`."""
    info = engine.describe()
    if info.state_slots is not None and info.state_slots < max_streams:
        raise ValueError(
            f"max_streams: {max_streams}, but the detector has {info.state_slots} stream-state slots; "
            "expected at least max_streams (build it with slots=max_streams)"
        )
    return info.batch_buckets
