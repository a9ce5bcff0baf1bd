"""The ROS 2 bridge: a vehicle's sensor_msgs/msg/PointCloud2 topic in over rmw_zenoh, each sector's boxes out
as vision_msgs/msg/Detection3DArray (and, if asked, visualization_msgs/msg/MarkerArray), without a ROS
install (docs/ros2.md). Keys, attachments and liveliness tokens: contract/ros2.py; messages and type
hashes: server/ros2_messages.py; PointCloud2 -> points: lidar/pointcloud2.py.

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
its context, never its stream. Points: one rule for a non-finite value, in a coordinate (a driver's "no
return") or the intensity alike: the point is dropped. `header.frame_id` (copied into every box's header) is
at most `max_string_len` characters; a longer one refuses the scan.

Threads, as in the zenoh transport (no Python in a zenoh callback, no zenoh call in a future's callback):
zenoh queues samples in a bounded FIFO; one receiver thread decodes, cuts and submits; the futures'
done-callbacks put answers in an outbox; one publisher thread encodes and publishes them.
"""

from __future__ import annotations

import hashlib
import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from functools import partial

import numpy as np
import zenoh

from contract import REQUIRED_FIELDS, DetectionsReply, ErrorCode, Limits, SectorMessage, ServiceError
from contract.ros2 import (
    RELIABLE,
    SENSOR_DATA,
    Attachment,
    EntityKind,
    Node,
    default_stream_id,
    topic_key,
)
from lidar.pointcloud2 import cloud_spin, decode_pointcloud2, pointcloud2_points, stamp_ns
from lidar.sectorizer import StreamSectorizer, split_scan
from server import ros2_messages as messages
from server.ros2_messages import DETECTION3D_ARRAY, MARKER_ARRAY, POINTCLOUD2, Header
from server.zenoh_transport import JOIN_TIMEOUT_S, Submit, ZenohConfig, open_session, submit_or_fail

log = logging.getLogger(__name__)

# messages zenoh holds for the receiver before it pushes back (on rmw_zenoh's keep-last publishers, which
# then drop): a second and a half of whole turns at 10 Hz, or many packets of a partial scan
CHANNEL_CAPACITY = {False: 16, True: 256}  # partial_scans -> messages
WARN_EVERY_S = 5.0  # one warning per error code this often (a broken topic sends 10 scans a second)
MAX_SENDERS = 256  # publisher GIDs remembered (to log each once)
SUBSCRIPTION_ID, DETECTIONS_ID, MARKERS_ID = 1, 2, 3  # entity IDs within the bridge's node (node ID 0)


@dataclass(frozen=True)
class Ros2Config:
    points: str  # the PointCloud2 topic, fully qualified
    detections: str  # the Detection3DArray topic
    markers: str | None = None  # the MarkerArray topic (None: none)
    domain_id: int = 0
    stream_id: str = ""  # '' : the points topic's first namespace (contract.ros2.default_stream_id)
    intensity_scale: float = 1.0  # times the raw intensity: 1/255 for drivers publishing 0..255
    partial_scans: bool = False  # each message a piece of a turn (sectorized as it comes), not a whole one
    node_name: str = "phim"

    @property
    def stream(self) -> str:
        return self.stream_id or default_stream_id(self.points)


@dataclass(eq=False)
class _Job:
    """One submitted sector, waiting for its answer."""

    seq: int
    sector_index: int
    header: Header


class _Cutter:
    """PointCloud2 points, message after message -> the sectors to send, each with the header it answers."""

    def __init__(self, sectors: int, partial_scans: bool):
        self.sectors, self.partial = sectors, partial_scans
        self._stream: StreamSectorizer | None = None

    def push(self, points: np.ndarray, header: Header) -> list[tuple[int, np.ndarray, Header]]:
        """points (N, 4) float32 in the message's (firing) order -> (sector index, (M, 4) points, header)."""
        if not self.partial:  # a whole turn: its sectors in sweep order, starting where the scan starts
            cut = split_scan(points, REQUIRED_FIELDS, self.sectors, cloud_spin(points))
            return [(s.index, s.points, header) for s in cut]
        if self._stream is None:
            if points.shape[0] < 2:
                return []  # the spin is unknown until there are two points
            self._stream = StreamSectorizer(REQUIRED_FIELDS, self.sectors, cloud_spin(points))
        return [(s.index, s.points, header) for s in self._stream.push(points)]


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
        self._cond = threading.Condition()
        self._session: zenoh.Session | None = None
        self._owns_session = False
        self._closing = False
        self._announced = False
        self._subscriber: zenoh.Subscriber | None = None
        self._publishers: dict[str, zenoh.Publisher] = {}  # topic -> publisher
        self._gids: dict[str, bytes] = {}  # topic -> the publisher's GID
        self._published: dict[str, int] = {}  # topic -> messages published (the attachment's seq)
        self._input_tokens: list[zenoh.LivelinessToken] = []  # withdrawn first on close
        self._output_tokens: list[zenoh.LivelinessToken] = []  # withdrawn after the drain
        self._inflight: set[_Job] = set()
        self._outbox: queue.SimpleQueue[tuple[_Job, DetectionsReply | ServiceError] | None] = (
            queue.SimpleQueue()
        )
        self._receiver: threading.Thread | None = None
        self._publisher: threading.Thread | None = None
        self._cutter: _Cutter | None = None  # made by announce: the model's sectors per turn are known then
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
    def node(self) -> Node:
        assert self._session is not None, "open() first"
        return Node(self.cfg.domain_id, str(self._session.zid()), self.cfg.node_name)

    def tokens(self) -> list[str]:
        """The liveliness tokens the bridge declares: its node, its subscription, its publishers."""
        node = self.node
        out = [
            node.token(),
            node.entity_token(
                SUBSCRIPTION_ID,
                EntityKind.SUBSCRIPTION,
                self.cfg.points,
                POINTCLOUD2,
                messages.type_hash(POINTCLOUD2),
                SENSOR_DATA,
            ),
        ]
        for entity_id, (topic, ros_type) in zip((DETECTIONS_ID, MARKERS_ID), self._outputs(), strict=False):
            type_hash = messages.type_hash(ros_type)
            out.append(
                node.entity_token(entity_id, EntityKind.PUBLISHER, topic, ros_type, type_hash, RELIABLE)
            )
        return out

    def announce(self, sectors_per_turn: int) -> None:
        """Join the ROS graph and take scans, cut into the model's `sectors_per_turn`: publishers, the
        subscriber, the tokens, the threads. Called once the worker is warmed up (scans before would only
        be answered NOT_READY). Idempotent; nothing once closing."""
        with self._cond:
            session = self._session
            if session is None or self._closing or self._announced:
                return
            self._announced = True
            self._cutter = _Cutter(sectors_per_turn, self.cfg.partial_scans)
            for topic, ros_type in self._outputs():
                self._publishers[topic] = session.declare_publisher(
                    self._key(topic, ros_type),
                    congestion_control=zenoh.CongestionControl.BLOCK,  # never drop an answer ourselves
                    reliability=zenoh.Reliability.RELIABLE,
                )
            self._publisher = self._thread(self._publish_loop, "publisher")
            subscriber = session.declare_subscriber(
                self._key(self.cfg.points, POINTCLOUD2),
                zenoh.handlers.FifoChannel(CHANNEL_CAPACITY[self.cfg.partial_scans]),
            )
            self._subscriber = subscriber
            self._receiver = self._thread(self._receive_loop, "receiver", subscriber.handler)
            node_token, sub_token, *pub_tokens = self.tokens()
            for (topic, _), token in zip(self._outputs(), pub_tokens, strict=True):
                # stable for the publisher's life (its token names the session); rmw_zenoh hashes the token
                # too, with XXH3-128, so `ros2 topic info -v` shows another GID for it than the samples carry
                self._gids[topic] = hashlib.sha256(token.encode()).digest()[:16]
            declare = session.liveliness().declare_token
            self._output_tokens = [declare(node_token), *(declare(t) for t in pub_tokens)]
            self._input_tokens = [declare(sub_token)]
        outputs = ", ".join(t for t, _ in self._outputs())
        log.info(
            "ros2: %s -> stream %s -> %s; tokens %s", self.cfg.points, self.cfg.stream, outputs, self.tokens()
        )

    def close(self, drain_timeout_s: float = 10.0) -> None:
        """Leave: stop taking scans (the subscription's token and subscriber go, the scans zenoh already
        queued are still cut and submitted), publish the answers of the sectors in flight (those not
        answered within `drain_timeout_s` are dropped, logged), withdraw the node and its publishers, close
        an own session. Idempotent."""
        with self._cond:
            if self._closing:
                return
            self._closing = True
            self._cond.notify_all()  # the receiver stops pacing: what is left is submitted at once
        for entity in (*self._input_tokens, self._subscriber):
            if entity is not None:
                entity.undeclare()  # closes the channel: the receiver drains it and stops
        if self._receiver is not None:
            self._receiver.join(JOIN_TIMEOUT_S)
        with self._cond:
            self._cond.wait_for(lambda: not self._inflight, drain_timeout_s)
            late, self._inflight = len(self._inflight), set()
        if late:
            log.warning(
                "ros2 closing: %d sectors unanswered after %.1f s, nothing published", late, drain_timeout_s
            )
        self._outbox.put(None)
        if self._publisher is not None:
            self._publisher.join(JOIN_TIMEOUT_S)
        for entity in (*self._output_tokens, *self._publishers.values()):
            entity.undeclare()
        if self._owns_session and self._session is not None:
            self._session.close()
        log.info("ros2 bridge %s closed", self.cfg.node_name)

    # ------------------------------------------------------------------------------------------- intake

    def _receive_loop(self, channel: zenoh.handlers.Handler[zenoh.Sample]) -> None:
        while (sample := _recv(channel)) is not None:
            if sample.kind != zenoh.SampleKind.PUT:
                continue
            try:
                self._accept(sample)
            except Exception:  # a bug: this scan is lost, the bridge goes on
                log.exception("ros2: a scan on %s failed", self.cfg.points)
                self._reject(ErrorCode.INTERNAL, "a scan failed in the bridge")

    def _accept(self, sample: zenoh.Sample) -> None:
        """One PointCloud2 sample -> its sectors submitted; a scan that cannot be read is counted, logged."""
        self._note_sender(sample.attachment)
        data = sample.payload.to_bytes()
        if len(data) > self.limits.max_body_bytes:
            why = f"{len(data)} bytes; the limit is {self.limits.max_body_bytes} (--max-body-bytes)"
            self._reject(ErrorCode.TOO_LARGE, why)
            return
        try:
            msg = decode_pointcloud2(data)
        except Exception as e:  # rosbags raises what the bytes make it hit: struct, index, value errors
            self._reject(ErrorCode.BAD_REQUEST, f"not a sensor_msgs/msg/PointCloud2 in CDR ({e!r})")
            return
        try:
            points = pointcloud2_points(msg, self.cfg.intensity_scale)  # (N, 4) float32
        except ValueError as e:
            self._reject(ErrorCode.INVALID_FIELD, str(e))
            return
        frame_id = str(msg.header.frame_id)
        if len(frame_id) > self.limits.max_string_len:  # copied into every box's and marker's header
            why = f"header.frame_id: {len(frame_id)} characters; at most {self.limits.max_string_len}"
            self._reject(ErrorCode.INVALID_FIELD, why + " (--max-string-len)")
            return
        points = points[np.isfinite(points[:, 3])]  # (N', 4): one rule, a point with any NaN/inf is dropped
        header = Header(max(0, stamp_ns(msg)), frame_id)
        assert self._cutter is not None  # announce made it before the subscriber
        for index, sector, head in self._cutter.push(points, header):
            self._submit(index, sector, head)

    def _submit(self, index: int, points: np.ndarray, header: Header) -> None:
        if points.shape[0] > self.limits.max_points:
            self._reject(ErrorCode.TOO_LARGE, f"a sector of {points.shape[0]} points (--max-points)")
            return
        job = _Job(self._seq, index, header)
        with self._cond:  # paced: a stream runs one sector at a time, so the next waits here, not queued
            self._cond.wait_for(lambda: not self._inflight or self._closing)
            reset, self._reset_next = self._reset_next or job.seq == 0, False
            self._inflight.add(job)
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
        with self._cond:
            if job not in self._inflight:
                return  # close() gave up on it
            self._inflight.discard(job)
            self._cond.notify_all()
        try:
            outcome: DetectionsReply | ServiceError = future.result(timeout=0)
        except ServiceError as e:
            outcome = e
            if e.code is ErrorCode.STALE_SEQUENCE:  # another sender moved the stream's seq on: restart it
                with self._cond:
                    self._reset_next = True
        except Exception as e:
            outcome = ServiceError(ErrorCode.INTERNAL, f"{type(e).__name__}: {e}")
        self._outbox.put((job, outcome))

    # ------------------------------------------------------------------------------------------- output

    def _publish_loop(self) -> None:
        while (item := self._outbox.get()) is not None:
            job, outcome = item
            try:
                self._deliver(job, outcome)
            except Exception:
                log.exception("ros2: could not publish the answer of %s seq %d", self.cfg.stream, job.seq)

    def _deliver(self, job: _Job, outcome: DetectionsReply | ServiceError) -> None:
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
        self._put(
            self.cfg.detections,
            messages.encode(messages.detection_array(outcome, job.header), DETECTION3D_ARRAY),
        )
        if self.cfg.markers is not None:
            self._put(
                self.cfg.markers, messages.encode(messages.marker_array(outcome, job.header), MARKER_ARRAY)
            )

    def _put(self, topic: str, cdr: bytes) -> None:
        """Publish one message with rmw_zenoh's attachment (this publisher's count from 1, now, its GID)."""
        seq = self._published.get(topic, 0) + 1
        self._published[topic] = seq
        attachment = Attachment(seq, time.time_ns(), self._gids[topic]).encode()
        self._publishers[topic].put(cdr, attachment=attachment)

    # ------------------------------------------------------------------------------------------ helpers

    def _outputs(self) -> list[tuple[str, str]]:
        out = [(self.cfg.detections, DETECTION3D_ARRAY)]
        return out + ([(self.cfg.markers, MARKER_ARRAY)] if self.cfg.markers is not None else [])

    def _key(self, topic: str, ros_type: str) -> str:
        return topic_key(self.cfg.domain_id, topic, ros_type, messages.type_hash(ros_type))

    def _thread(self, target: Callable[..., None], name: str, *args: object) -> threading.Thread:
        t = threading.Thread(target=target, args=args, name=f"ros2-{name}-{self.cfg.node_name}", daemon=True)
        t.start()
        return t


def _recv(channel: zenoh.handlers.Handler[zenoh.Sample]) -> zenoh.Sample | None:
    """The next sample, or None once the channel is closed (its subscriber undeclared) and empty."""
    try:
        return channel.recv()
    except zenoh.ZError:
        return None
