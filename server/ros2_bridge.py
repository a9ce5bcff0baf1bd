"""The ROS 2 bridge: a vehicle's sensor_msgs/msg/PointCloud2 topic in over rmw_zenoh, each sector's boxes out
as vision_msgs/msg/Detection3DArray (and, if asked, visualization_msgs/msg/MarkerArray), without a ROS
install (docs/ros2.md). Keys, attachments and liveliness tokens: contract/ros2.py; the node, its tokens and
what it publishes: ros/node.py; a sample -> checked points -> sectors: ros/scans.py. This module is the
transport: the zenoh session's entities, the threads, the pacing and the worker it submits to.

A ROS node, as a ROS 2 graph sees it (`ros2 node list`, `ros2 topic list`, `ros2 topic echo`): one
subscription (the points topic) and one or two publishers, announced once the worker is warmed up. Each
message is one turn cut into the model's sectors (or, with `partial_scans`, a piece of one, sectorized as
it comes); each sector goes to the worker's `submit` on one stream, in sweep order with increasing seq, and
its answer is published on the detections topic with the input's stamp and frame_id. An error answer is
logged and counted, and nothing is published (ROS has no error channel).

Pacing: one sector in flight; the next is submitted once the previous is answered (a stream runs one sector
per step anyway, so a turn's sectors queued at once would only wait out their deadlines on a busy CPU).
Sequence: the bridge numbers its own sectors (a driver's restart changes nothing); when another sender has
moved the stream's seq on (a sector with a huge seq on the bridge's stream ID), the worker answers the next
sector stale and the bridge sends the one after as a reset, so such a sender costs the vehicle a sector and
its context, never its stream.

Threads, the zenoh transport's skeleton (server/transport_thread.py: no Python in a zenoh callback, no zenoh
call in a future's callback): zenoh queues samples in a bounded FIFO; one receiver thread decodes, cuts and
submits; the futures' done-callbacks put answers in an outbox; one publisher thread encodes and publishes.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from functools import partial

import numpy as np
import zenoh

from contract import REQUIRED_FIELDS, DetectionsReply, ErrorCode, Limits, SectorMessage, ServiceError
from contract.ros2 import Attachment, Node
from ros import messages
from ros.messages import POINTCLOUD2, Header
from ros.node import BridgeNode, Ros2Config, answer_messages
from ros.scans import ScanCutter, read_scan
from server.transport_thread import Submit, TransportThreads, submit_or_fail
from server.zenoh_transport import ZenohConfig, open_session

log = logging.getLogger(__name__)

# messages zenoh holds for the receiver before it pushes back (on rmw_zenoh's keep-last publishers, which
# then drop): a second and a half of whole turns at 10 Hz, or many packets of a partial scan
CHANNEL_CAPACITY = {False: 16, True: 256}  # partial_scans -> messages
WARN_EVERY_S = 5.0  # one warning per error code this often (a broken topic sends 10 scans a second)
MAX_SENDERS = 256  # publisher GIDs remembered (to log each once)

Outcome = DetectionsReply | ServiceError


@dataclass(eq=False)
class _Job:
    """One submitted sector, waiting for its answer."""

    seq: int
    sector_index: int
    header: Header


@dataclass
class _Throttle:
    """At most one warning per key every WARN_EVERY_S, saying how many were held back."""

    last: dict[str, float] = field(default_factory=dict)
    held: dict[str, int] = field(default_factory=dict)

    def warn(self, key: str, message: str, *args: object) -> None:
        now = time.monotonic()
        if now - self.last.get(key, -math.inf) < WARN_EVERY_S:
            self.held[key] = self.held.get(key, 0) + 1
            return
        self.last[key] = now
        held = self.held.pop(key, 0)
        log.warning(message + (f" (and {held} more since the last such warning)" if held else ""), *args)


class Ros2Bridge:
    """Subscribes to `cfg.points` as rmw_zenoh publishes it; publishes each sector's answer on
    `cfg.detections` (and `cfg.markers`); announces itself to the ROS graph as node `cfg.node_name`."""

    def __init__(
        self,
        submit: Submit,
        cfg: Ros2Config,
        limits: Limits,
        on_reject: Callable[[ErrorCode], None] | None = None,
        zenoh_cfg: ZenohConfig | None = None,
    ):
        """`on_reject` hears of every scan or sector refused before it reached `submit` (metrics);
        `zenoh_cfg` opens the bridge's own session when `open` is given none to share."""
        self.submit, self.on_reject = submit, on_reject
        self.cfg, self.limits, self.zenoh_cfg = cfg, limits, zenoh_cfg
        self._threads: TransportThreads[_Job, Outcome] = TransportThreads(
            "ros2", cfg.node_name, self._deliver, lambda job: f"{cfg.stream} seq {job.seq}"
        )
        self._session: zenoh.Session | None = None
        self._owns_session = False
        self._announced = False
        self._subscriber: zenoh.Subscriber | None = None
        self._publishers: dict[str, zenoh.Publisher] = {}  # topic -> publisher
        self._gids: dict[str, bytes] = {}  # topic -> the publisher's GID
        self._published: dict[str, int] = {}  # topic -> messages published (the attachment's seq)
        self._input_tokens: list[zenoh.LivelinessToken] = []  # withdrawn first on close
        self._output_tokens: list[zenoh.LivelinessToken] = []  # withdrawn after the drain
        self._cutter: ScanCutter | None = (
            None  # made by announce: the model's sectors per turn are known then
        )
        self._seq = 0  # the bridge numbers its own sectors: a driver's restart changes nothing here
        self._reset_next = False  # the next sector restarts the stream (its seq was taken over)
        self._senders: set[bytes] = set()  # GIDs of the publishers heard (logged once each)
        self._throttle = _Throttle()

    # ------------------------------------------------------------------------------------ public surface

    def open(self, session: zenoh.Session | None = None) -> None:
        """Share `session` (the zenoh transport's: the caller closes it), or open one from `zenoh_cfg`. Raises
        here, at start-up, when rosbags is missing or the session cannot open."""
        try:
            messages.typestore()  # rosbags, now rather than on the first scan
        except ImportError as e:
            raise RuntimeError(f"the ROS 2 bridge needs rosbags ({e}): pip install '.[ros2]'") from e
        if session is None:
            if self.zenoh_cfg is None:
                raise ValueError("Ros2Bridge.open: no session to share and no zenoh_cfg to open one")
            session = open_session(self.zenoh_cfg)
            self._owns_session = True
        self._session = session

    @property
    def ros_node(self) -> BridgeNode:
        assert self._session is not None, "open() first"
        return BridgeNode(self.cfg, str(self._session.zid()))

    @property
    def node(self) -> Node:
        return self.ros_node.node

    def tokens(self) -> list[str]:
        """The liveliness tokens the bridge declares: its node, its subscription, its publishers."""
        return self.ros_node.tokens()

    def announce(self, sectors_per_turn: int) -> None:
        """Join the ROS graph and take scans, cut into the model's `sectors_per_turn`: publishers, the
        subscriber, the tokens, the threads. Called once the worker is warmed up (scans before would only
        be answered NOT_READY). Idempotent; nothing once closing."""
        with self._threads.cond:
            session = self._session
            if session is None or self._threads.closing or self._announced:
                return
            self._announced = True
            self._cutter = ScanCutter(sectors_per_turn, self.cfg.partial_scans)
            for topic, ros_type in self.cfg.outputs():
                self._publishers[topic] = session.declare_publisher(
                    self.cfg.key(topic, ros_type),
                    congestion_control=zenoh.CongestionControl.BLOCK,  # never drop an answer ourselves
                    reliability=zenoh.Reliability.RELIABLE,
                )
            self._threads.start_sender("publisher")
            subscriber = session.declare_subscriber(
                self.cfg.key(self.cfg.points, POINTCLOUD2),
                zenoh.handlers.FifoChannel(CHANNEL_CAPACITY[self.cfg.partial_scans]),
            )
            self._subscriber = subscriber
            self._threads.receive(subscriber.handler, self._receive, "receiver")
            node = self.ros_node
            node_token, sub_token, *pub_tokens = node.tokens()
            self._gids = node.gids()
            declare = session.liveliness().declare_token
            self._output_tokens = [declare(node_token), *(declare(t) for t in pub_tokens)]
            self._input_tokens = [declare(sub_token)]
        outputs = ", ".join(t for t, _ in self.cfg.outputs())
        log.info(
            "ros2: %s -> stream %s -> %s; tokens %s", self.cfg.points, self.cfg.stream, outputs, self.tokens()
        )

    def close(self, drain_timeout_s: float = 10.0) -> None:
        """Leave: stop taking scans (the subscription's token and subscriber go, the scans zenoh already
        queued are still cut and submitted), publish the answers of the sectors in flight (those not
        answered within `drain_timeout_s` are dropped, logged), withdraw the node and its publishers, close
        an own session. Idempotent."""
        if not self._threads.begin_close():  # the receiver stops pacing: what is left is submitted at once
            return
        for entity in (*self._input_tokens, self._subscriber):
            if entity is not None:
                entity.undeclare()  # closes the channel: the receiver drains it and stops
        self._threads.join_receivers()
        late = len(self._threads.drain(drain_timeout_s))
        if late:
            log.warning(
                "ros2 closing: %d sectors unanswered after %.1f s, nothing published", late, drain_timeout_s
            )
        self._threads.stop_sender()
        for entity in (*self._output_tokens, *self._publishers.values()):
            entity.undeclare()
        if self._owns_session and self._session is not None:
            self._session.close()
        log.info("ros2 bridge %s closed", self.cfg.node_name)

    # ------------------------------------------------------------------------------------------- intake

    def _receive(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return
        try:
            self._accept(sample)
        except Exception:  # a bug: this scan is lost, the bridge goes on
            log.exception("ros2: a scan on %s failed", self.cfg.points)
            self._reject(ErrorCode.INTERNAL, "a scan failed in the bridge")

    def _accept(self, sample: zenoh.Sample) -> None:
        """One PointCloud2 sample -> its sectors submitted; a scan that cannot be read is counted, logged."""
        self._note_sender(sample.attachment)
        try:
            points, header = read_scan(sample.payload.to_bytes(), self.limits, self.cfg.intensity_scale)
        except ServiceError as e:
            self._reject(e.code, e.message)
            return
        assert self._cutter is not None  # announce made it before the subscriber
        for index, sector, head in self._cutter.push(points, header):
            self._submit(index, sector, head)

    def _submit(self, index: int, points: np.ndarray, header: Header) -> None:
        if points.shape[0] > self.limits.max_points:
            self._reject(ErrorCode.TOO_LARGE, f"a sector of {points.shape[0]} points (--max-points)")
            return
        job = _Job(self._seq, index, header)
        threads = self._threads
        with threads.cond:  # paced: a stream runs one sector at a time, so the next waits here, not queued
            threads.cond.wait_for(lambda: not threads.inflight or threads.closing)
            reset, self._reset_next = self._reset_next or job.seq == 0, False
            threads.inflight.add(job)
        msg = SectorMessage(
            self.cfg.stream, job.seq, index, header.stamp_ns, points, REQUIRED_FIELDS, reset=reset
        )
        self._seq += 1
        future = submit_or_fail(self.submit, msg)
        future.add_done_callback(partial(self._settled, job))

    def _reject(self, code: ErrorCode, why: str) -> None:
        if self.on_reject is not None:
            self.on_reject(code)
        self._throttle.warn(
            code.value, "ros2: a scan on %s refused (%s): %s", self.cfg.points, code.value, why
        )

    def _note_sender(self, attachment: zenoh.ZBytes | None) -> None:
        """Log each new publisher on the points topic once (its GID, from rmw_zenoh's attachment)."""
        try:
            gid = Attachment.decode(attachment.to_bytes()).source_gid if attachment is not None else b""
        except ValueError as e:
            gid = b"?"
            log.debug("ros2: an attachment on %s: %s", self.cfg.points, e)
        if gid not in self._senders:
            if len(self._senders) >= MAX_SENDERS:  # a publisher per session: restarts add up, slowly
                self._senders.clear()
            self._senders.add(gid)
            who = gid.hex() if len(gid) > 1 else "a publisher without an rmw_zenoh attachment"
            log.info("ros2: scans on %s from %s", self.cfg.points, who)

    def _settled(self, job: _Job, future: Future[DetectionsReply]) -> None:
        """Done-callback (worker thread): hand the outcome to the publisher; never touches zenoh."""
        if not self._threads.settle(job):
            return  # close() gave up on it
        try:
            outcome: Outcome = future.result(timeout=0)
        except ServiceError as e:
            outcome = e
            if e.code is ErrorCode.STALE_SEQUENCE:  # another sender moved the stream's seq on: restart it
                with self._threads.cond:
                    self._reset_next = True
        except Exception as e:
            outcome = ServiceError(ErrorCode.INTERNAL, f"{type(e).__name__}: {e}")
        self._threads.send(job, outcome)

    # ------------------------------------------------------------------------------------------- output

    def _deliver(self, job: _Job, outcome: Outcome) -> None:
        if isinstance(outcome, ServiceError):  # counted by the worker; ROS has nowhere to send it
            self._throttle.warn(
                outcome.code.value,
                "ros2: %s seq %d (sector %d) answered %s: %s; nothing published",
                self.cfg.stream,
                job.seq,
                job.sector_index,
                outcome.code.value,
                outcome.message,
            )
            return
        for topic, cdr in answer_messages(self.cfg, outcome, job.header):
            self._put(topic, cdr)

    def _put(self, topic: str, cdr: bytes) -> None:
        """Publish one message with rmw_zenoh's attachment (this publisher's count from 1, now, its GID)."""
        seq = self._published.get(topic, 0) + 1
        self._published[topic] = seq
        attachment = Attachment(seq, time.time_ns(), self._gids[topic]).encode()
        self._publishers[topic].put(cdr, attachment=attachment)
