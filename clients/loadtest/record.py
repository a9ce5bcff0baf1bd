"""One record per sector a load test schedules: every sector is counted exactly once, by its outcome."""

from __future__ import annotations

import enum
from dataclasses import dataclass

from clients.base import RequestTimeout, ServerError, TransportError
from contract import DetectionsReply


class Lost(enum.StrEnum):
    TIMEOUT = "timeout"  # the request's own timeout passed (no answer)
    TRANSPORT = "transport"  # connection failed or the reply could not be read
    DRAIN = "drain"  # still unanswered when the drain timeout after the last send passed


@dataclass(eq=False)
class Record:
    vehicle: int
    seq: int
    scheduled: float  # loop time (s) the sector was due: latency is measured from here
    sent: float | None = None  # loop time the send actually started
    done: float | None = None  # loop time the answer (or the failure) came back
    ok: bool = False  # a detections reply came back
    error_code: str | None = None  # the server's error code
    lost: Lost | None = None  # no answer
    boxes: int = 0
    context_sectors: int = 0
    worker_id: str = ""  # the worker that answered with detections
    cold_start: bool = False  # ... on a fresh stream state
    queue_ms: float = 0.0  # the server's timings (detections replies only)
    model_ms: float = 0.0
    server_ms: float = 0.0

    @property
    def answered(self) -> bool:
        return self.ok or self.error_code is not None

    @property
    def latency_ms(self) -> float:
        assert self.done is not None
        return (self.done - self.scheduled) * 1e3

    def settle_ok(self, now: float, reply: DetectionsReply) -> None:
        self.done, self.ok = now, True
        self.boxes, self.context_sectors = int(reply.boxes.shape[0]), reply.context_sectors
        self.worker_id, self.cold_start = reply.worker_id, reply.cold_start
        t = reply.timings
        self.queue_ms, self.model_ms, self.server_ms = t.queue_ms, t.model_ms, t.total_ms

    def settle_error(self, now: float, e: ServerError | TransportError) -> None:
        self.done = now
        if isinstance(e, ServerError):
            self.error_code = e.code.value
        else:
            self.lost = Lost.TIMEOUT if isinstance(e, RequestTimeout) else Lost.TRANSPORT

    def settle_unanswered(self) -> None:
        if not self.answered and self.lost is None:
            self.lost = Lost.DRAIN
