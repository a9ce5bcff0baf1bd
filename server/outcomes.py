"""A sector's answer from its step outcome: its detections scored at least the sector's `min_score` (else the
server's), or its own error when the step rejected it; a queued sector's error when it never ran."""

from __future__ import annotations

import time

import numpy as np

from contract import DetectionsReply, ErrorCode, ServiceError, Timings
from model.engine import SectorOutcome, SectorRejected
from server.streams import Pending


def sector_answer(
    p: Pending,
    r: SectorOutcome,
    gap: int,
    cold: bool,
    t0: float,
    model_s: float,
    class_names: tuple[str, ...],
    worker_id: str,
    min_score: float = 0.0,
) -> DetectionsReply | ServiceError:
    """cold: the sector ran on a fresh state; t0: time.monotonic() when the forward started; model_s: its
    seconds; worker_id: the worker that ran it; min_score: the server's threshold, unless the sector has
    its own."""
    if isinstance(r, SectorRejected):  # the engine could not run it: this sector only, state unchanged
        return ServiceError(ErrorCode.INVALID_FIELD, f"{r.message} (seq {p.msg.seq} not run)", r.field)
    d = r.detections
    least = min_score if p.msg.min_score is None else p.msg.min_score
    scores = d.scores.cpu().numpy().astype(np.float32, copy=False)  # (K,)
    keep = scores >= np.float32(least)  # (K,)
    labels = d.labels.cpu().numpy().astype(np.int32)[keep]  # (K',)
    return DetectionsReply(
        stream_id=p.msg.stream_id,
        seq=p.msg.seq,
        boxes=d.boxes.cpu().numpy().astype(np.float32, copy=False)[keep],  # (K', 7)
        scores=scores[keep],  # (K',)
        labels=labels,
        class_names=tuple(class_names[i] for i in labels),
        context_sectors=r.context_sectors,
        gap=gap,
        timings=Timings(
            queue_ms=(t0 - p.submitted) * 1e3,
            model_ms=model_s * 1e3,
            total_ms=(time.monotonic() - p.submitted) * 1e3,
        ),
        cold_start=cold,
        worker_id=worker_id,
    )


def expired_error(
    p: Pending, now: float, shutting_down: bool, worker_id: str, deadline_ms: float
) -> ServiceError:
    """A queued sector's answer when it never ran: the worker shut down, or its deadline passed."""
    if shutting_down:
        return ServiceError(ErrorCode.NOT_READY, f"worker {worker_id} shut down before this sector ran")
    return ServiceError(
        ErrorCode.DEADLINE_EXCEEDED,
        f"deadline: seq {p.msg.seq} waited {(now - p.submitted) * 1e3:.0f} ms in the queue; "
        f"the deadline is {deadline_ms:g} ms (deadline_ms)",
    )
