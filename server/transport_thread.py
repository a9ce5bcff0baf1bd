"""The thread skeleton of the zenoh transport (server/zenoh_transport.py) and the ROS 2 bridge
(server/ros2_bridge.py), so that no Python runs in a zenoh callback and no zenoh call in a future's:

  - zenoh pushes what arrives into bounded FIFO channels (no Python callback at all);
  - a receiver thread per channel `recv`s, decodes and submits (`receive`); `submit` never blocks;
  - the future's done-callback (on the worker's device thread) only settles its job and puts the outcome
    in the outbox (`settle`, `send`);
  - one sender thread owns every outgoing zenoh call: it hands each (job, outcome) to `deliver`.

Closing: `begin_close` once; the entities undeclared close their channels, so the receivers drain them and
stop (`join_receivers`); `drain` waits for the jobs in flight; `stop_sender` ends the sender once the
outbox is empty.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from concurrent.futures import Future
from typing import Generic, TypeVar

import zenoh

from contract import DetectionsReply, SectorMessage

log = logging.getLogger(__name__)

JOIN_TIMEOUT_S = 10.0

Submit = Callable[[SectorMessage], "Future[DetectionsReply]"]
J = TypeVar("J")  # a job: one sector waiting for its answer (hashable by identity)
R = TypeVar("R")  # its outcome, as the sender delivers it
T = TypeVar("T")


class TransportThreads(Generic[J, R]):
    """The receivers, the jobs in flight, the outbox and the sender of one transport. Threads are named
    `{kind}-{role}-{owner}` (zenoh-replier-w1, ros2-receiver-phim_w1)."""

    def __init__(self, kind: str, owner: str, deliver: Callable[[J, R], None], what: Callable[[J], str]):
        """`deliver` sends one outcome (on the sender thread); `what` names a job in a log line."""
        self.kind, self.owner = kind, owner
        self._deliver, self._what = deliver, what
        self.cond = threading.Condition()  # guards `closing` and `inflight`; notified when either changes
        self.closing = False
        self.inflight: set[J] = set()  # submitted, outcome not yet in the outbox
        self._outbox: queue.SimpleQueue[tuple[J, R] | None] = queue.SimpleQueue()
        self._receivers: list[threading.Thread] = []
        self._sender: threading.Thread | None = None

    def thread(self, target: Callable[..., None], role: str, *args: object) -> threading.Thread:
        t = threading.Thread(target=target, args=args, name=f"{self.kind}-{role}-{self.owner}", daemon=True)
        t.start()
        return t

    def start_sender(self, role: str) -> None:
        self._sender = self.thread(self._send_loop, role)

    def receive(self, channel: zenoh.handlers.Handler[T], handle: Callable[[T], None], role: str) -> None:
        """A receiver thread: `handle` each item of `channel` until it is closed and empty."""

        def loop() -> None:
            while (item := recv(channel)) is not None:
                handle(item)

        self._receivers.append(self.thread(loop, role))

    def admit(self, job: J) -> None:
        with self.cond:
            self.inflight.add(job)

    def settle(self, job: J) -> bool:
        """The job's answer came (done-callback): False when closing already gave up on it."""
        with self.cond:
            if job not in self.inflight:
                return False
            self.inflight.discard(job)
            self.cond.notify_all()
        return True

    def send(self, job: J, outcome: R) -> None:
        self._outbox.put((job, outcome))

    def begin_close(self) -> bool:
        """Mark the transport closing: True the first time, False after."""
        with self.cond:
            if self.closing:
                return False
            self.closing = True
            self.cond.notify_all()
        return True

    def join_receivers(self) -> None:
        for t in self._receivers:
            t.join(JOIN_TIMEOUT_S)

    def drain(self, timeout_s: float) -> list[J]:
        """Wait up to `timeout_s` for the jobs in flight; the ones still unanswered (given up on)."""
        with self.cond:
            self.cond.wait_for(lambda: not self.inflight, timeout_s)
            late, self.inflight = list(self.inflight), set()
        return late

    def stop_sender(self) -> None:
        """Deliver what is in the outbox, then end the sender."""
        self._outbox.put(None)
        if self._sender is not None:
            self._sender.join(JOIN_TIMEOUT_S)

    def _send_loop(self) -> None:
        while (item := self._outbox.get()) is not None:
            job, outcome = item
            try:
                self._deliver(job, outcome)
            except Exception:
                log.exception("%s: could not deliver the answer of %s", self.kind, self._what(job))


def submit_or_fail(submit: Submit, msg: SectorMessage) -> Future[DetectionsReply]:
    """`submit(msg)`, whose future answers the sector; a submit that raises (it should fail its future
    instead) gives a failed future, so that the sector is answered all the same."""
    try:
        return submit(msg)
    except Exception as e:
        log.exception("submit raised for %s seq %d", msg.stream_id, msg.seq)
        future: Future[DetectionsReply] = Future()
        future.set_exception(e)
        return future


def recv(channel: zenoh.handlers.Handler[T]) -> T | None:
    """The next item, or None once the channel is closed (its entity undeclared) and empty."""
    try:
        return channel.recv()
    except zenoh.ZError:
        return None
