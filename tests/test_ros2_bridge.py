"""The ROS 2 bridge (server/ros2_bridge.py) over real zenoh sessions on loopback, against a "vehicle" built
the way rmw_zenoh_cpp publishes (its node and publisher tokens, CDR PointCloud2 under the topic's key, the
attachment on every sample), with the key strings written out here, not built by the code under test.

The wire facts the literals come from: ros2/rmw_zenoh docs/design.md (key expressions, tokens, the
attachment's bytes, the RIHS01 hash of std_msgs/msg/String) and its liveliness_utils.cpp / qos.cpp (the QoS
chunk)."""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Iterator
from concurrent.futures import Future
from typing import Any

import httpx
import numpy as np
import pytest
import zenoh
from ros2_helpers import (
    UINT8_INTENSITY,
    VELODYNE_XYZIRT,
    assert_boxes,
    http_replies,
    pointcloud2_cdr,
    reply_for,
)
from server_helpers import START_TIMEOUT_S, default_detector, free_endpoint, serve

from contract import (
    DetectionsReply,
    ErrorCode,
    Limits,
    SectorMessage,
    ServiceError,
)
from contract.ros2 import (
    Attachment,
)
from lidar.samples import KITTI_VELODYNE
from lidar.sectorizer import StreamSectorizer, split_scan
from lidar.synthetic import synthetic_turn
from ros import messages
from ros.messages import DETECTION3D_ARRAY, MARKER_ARRAY
from ros.node import Ros2Config
from ros.pointcloud2 import cloud_spin
from server.ros2_bridge import Ros2Bridge
from server.zenoh_transport import ZenohConfig, open_session

WAIT_S = START_TIMEOUT_S  # a guard against hangs, generous; answers come as soon as the forward is done
PC2_HASH = "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5"
DET_HASH = "RIHS01_793f5eab9595ac1c0da07873cc859db42eae51f0ee76056db8562515d830e018"
POINTS_KEY = f"0/car1/lidar/points/sensor_msgs::msg::dds_::PointCloud2_/{PC2_HASH}"
DETECTIONS_KEY = f"0/car1/detections/vision_msgs::msg::dds_::Detection3DArray_/{DET_HASH}"
MARKERS_KEY = "0/car1/markers/visualization_msgs::msg::dds_::MarkerArray_/" + messages.type_hash(MARKER_ARRAY)
FIELDS = ("x", "y", "z", "intensity")
STAMP_NS = 1_700_000_000_250_000_000


# ------------------------------------------------------------------------------------------- a vehicle


class Vehicle:
    """A ROS 2 vehicle as rmw_zenoh runs one: a client session, its node's and publisher's liveliness tokens,
    PointCloud2 under the topic's key with an attachment, subscribers on the bridge's output keys."""

    def __init__(self, endpoint: str, outputs: tuple[str, ...] = (DETECTIONS_KEY,)):
        self.session = open_session(ZenohConfig(mode="client", listen=(), connect=(endpoint,)))
        zid = str(self.session.zid())
        self.token_keys = [
            f"@ros2_lv/0/{zid}/0/0/NN/%/%car1/velodyne",
            f"@ros2_lv/0/{zid}/0/10/MP/%/%car1/velodyne/%car1%lidar%points/"
            f"sensor_msgs::msg::dds_::PointCloud2_/{PC2_HASH}/2::,5:,:,:,,",
        ]
        self.tokens = [self.session.liveliness().declare_token(k) for k in self.token_keys]
        self.got: dict[str, queue.Queue[zenoh.Sample]] = {key: queue.Queue() for key in outputs}
        self.subscribers = [self.session.declare_subscriber(k, q.put) for k, q in self.got.items()]
        # as a reliable keep-all publisher (rmw_zenoh's keep-last ones drop when the network pushes back)
        self.publisher = self.session.declare_publisher(
            POINTS_KEY,
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        self.sent = 0
        self.gid = bytes(range(16))

    def wait_matched(self) -> None:
        """Until the bridge's subscriber is known here (declared once the worker is warmed up)."""
        deadline = time.monotonic() + WAIT_S
        while not self.publisher.matching_status.matching:
            assert time.monotonic() < deadline, "the bridge never subscribed"
            time.sleep(0.02)

    def publish(self, cdr: bytes) -> None:
        self.sent += 1
        self.publisher.put(cdr, attachment=Attachment(self.sent, time.time_ns(), self.gid).encode())

    def take(self, n: int, key: str = DETECTIONS_KEY, ros_type: str = DETECTION3D_ARRAY) -> list[Any]:
        """The next n messages on `key`, decoded (their attachments checked); then none for a moment."""
        samples = [self.got[key].get(timeout=WAIT_S) for _ in range(n)]
        with pytest.raises(queue.Empty):
            self.got[key].get(timeout=0.3)
        for s in samples:
            att = Attachment.decode(s.attachment.to_bytes())
            assert att.source_timestamp_ns > STAMP_NS and len(att.source_gid) == 16
        return [messages.decode(s.payload.to_bytes(), ros_type) for s in samples]

    def close(self) -> None:
        self.session.close()


# --------------------------------------------------------------------------- the bridge, a fake worker


class FakeWorker:
    """`submit` as the worker's: records each sector; answers at once, with an error for `fail`, or holds."""

    def __init__(self, fail: tuple[int, ...] = (), hold: bool = False):
        self.sectors: list[SectorMessage] = []
        self.held: list[tuple[SectorMessage, Future[DetectionsReply]]] = []
        self.fail, self.hold = fail, hold
        self.rejected: list[ErrorCode] = []

    def submit(self, msg: SectorMessage) -> Future[DetectionsReply]:
        self.sectors.append(msg)
        fut: Future[DetectionsReply] = Future()
        if self.hold:
            self.held.append((msg, fut))
        elif msg.seq in self.fail:
            fut.set_exception(ServiceError(ErrorCode.OVERLOADED, "queue full"))
        else:
            fut.set_result(reply_for(msg))
        return fut


@pytest.fixture
def bridged() -> Iterator[Any]:
    """make(worker, own_session, **cfg) -> (bridge, worker, vehicle): a bridge on a peer session listening on
    a free port (the test's, shared as the server shares its zenoh transport's; or, `own_session`, its
    own), a vehicle connected to it."""
    made: list[tuple[Ros2Bridge, Vehicle, zenoh.Session | None]] = []

    def make(worker: FakeWorker | None = None, own_session: bool = False, **cfg: Any) -> tuple[Any, ...]:
        worker = worker or FakeWorker()
        server_cfg = ZenohConfig(mode="peer", listen=(free_endpoint(),))
        shared = None if own_session else open_session(server_cfg)
        config = Ros2Config("/car1/lidar/points", "/car1/detections", node_name="phim_t", **cfg)
        bridge = Ros2Bridge(
            worker.submit, config, Limits(max_points=50_000), worker.rejected.append, server_cfg
        )
        bridge.open(shared)
        bridge.announce(sectors_per_turn=4)
        vehicle = Vehicle(server_cfg.listen[0])
        made.append((bridge, vehicle, shared))
        vehicle.wait_matched()
        return bridge, worker, vehicle

    yield make
    for bridge, vehicle, shared in made:
        bridge.close(drain_timeout_s=5.0)
        vehicle.close()
        if shared is not None:
            shared.close()


def test_a_turn_becomes_one_array_per_sector_in_sweep_order(bridged: Any) -> None:
    _, worker, vehicle = bridged()
    turn = synthetic_turn(seed=1)  # (N, 4) in firing order
    vehicle.publish(pointcloud2_cdr(turn, stamp_ns=STAMP_NS, frame_id="velodyne"))
    arrays = vehicle.take(4)
    want = split_scan(turn, FIELDS, 4, cloud_spin(turn))
    assert [(m.stream_id, m.seq, m.sector_index, m.reset) for m in worker.sectors] == [
        ("car1", i, s.index, i == 0) for i, s in enumerate(want)
    ]
    for msg, sector, array in zip(worker.sectors, want, arrays, strict=True):
        np.testing.assert_array_equal(msg.points, sector.points)
        assert (msg.timestamp_ns, msg.fields) == (STAMP_NS, FIELDS)
        assert (array.header.frame_id, array.header.stamp.nanosec) == ("velodyne", 250_000_000)
        assert_boxes(array, reply_for(msg))
    vehicle.publish(pointcloud2_cdr(turn[::2], stamp_ns=STAMP_NS + 10**8))  # the next turn: seq goes on
    vehicle.take(4)
    assert [m.seq for m in worker.sectors] == list(range(8)) and not worker.sectors[4].reset


def test_partial_scans_are_sectorized_as_they_come(bridged: Any) -> None:
    _, worker, vehicle = bridged(partial_scans=True)
    turn = synthetic_turn(seed=2)
    packets = [turn[i : i + 3000] for i in range(0, len(turn), 3000)]
    for k, packet in enumerate(packets):
        vehicle.publish(pointcloud2_cdr(packet, stamp_ns=STAMP_NS + k))
    cutter = StreamSectorizer(FIELDS, 4, cloud_spin(packets[0]))
    want = [s for p in packets for s in cutter.push(p)]  # the last sector stays open: its turn goes on
    assert len(vehicle.take(len(want))) == len(want) == 3
    for msg, sector in zip(worker.sectors, want, strict=True):
        assert msg.sector_index == sector.index
        np.testing.assert_array_equal(msg.points, sector.points)


def test_intensity_is_scaled(bridged: Any) -> None:
    _, worker, vehicle = bridged(intensity_scale=1 / 255)
    turn = synthetic_turn(seed=3)
    vehicle.publish(pointcloud2_cdr(turn, UINT8_INTENSITY, intensity_scale=1 / 255))  # stored as 0..255
    vehicle.take(4)
    got = np.concatenate([m.points for m in worker.sectors])
    np.testing.assert_allclose(np.sort(got[:, 3]), np.sort(turn[:, 3]), atol=0.5 / 255)


def test_a_bad_scan_or_error_answer_publishes_nothing_and_the_next_is_answered(bridged: Any) -> None:
    _, worker, vehicle = bridged(worker=FakeWorker(fail=(1,)))
    turn = synthetic_turn(seed=4)
    good = pointcloud2_cdr(turn, VELODYNE_XYZIRT)
    vehicle.publish(b"\x00\x01\x00\x00garbage")  # not CDR of a PointCloud2
    vehicle.publish(good[: len(good) // 2])  # truncated
    no_intensity = pointcloud2_cdr(turn, VELODYNE_XYZIRT).replace(b"intensity", b"intensitx")
    vehicle.publish(no_intensity)  # decodes, but lacks a field the model reads
    vehicle.publish(good)
    arrays = vehicle.take(3)  # sector seq 1 was answered OVERLOADED: nothing for it
    assert worker.rejected == [ErrorCode.BAD_REQUEST, ErrorCode.BAD_REQUEST, ErrorCode.INVALID_FIELD]
    assert [m.seq for m in worker.sectors] == [0, 1, 2, 3]
    for array, msg in zip(arrays, [worker.sectors[i] for i in (0, 2, 3)], strict=True):
        assert_boxes(array, reply_for(msg))


def graph(vehicle: Vehicle) -> list[str]:
    """The liveliness tokens of domain 0 the vehicle sees."""
    # a set: zenoh may answer a token once per route to it (the vehicle's own come back through the peer)
    return sorted({str(r.ok.key_expr) for r in vehicle.session.liveliness().get("@ros2_lv/0/**", timeout=5)})


def test_close_publishes_the_answers_in_flight_then_leaves_the_graph(bridged: Any) -> None:
    bridge, worker, vehicle = bridged(worker=FakeWorker(hold=True))
    own = sorted(vehicle.token_keys)
    assert graph(vehicle) == sorted(bridge.tokens() + own)
    vehicle.publish(pointcloud2_cdr(synthetic_turn(seed=5)))
    held(worker, 1)  # paced: one sector in flight
    closing = threading.Thread(target=bridge.close, args=(WAIT_S,))
    closing.start()
    held(worker, 4)  # closing: the turn's other sectors are submitted at once
    time.sleep(0.3)
    assert closing.is_alive()  # waiting for the sectors in flight
    for msg, fut in worker.held:
        fut.set_result(reply_for(msg))
    closing.join(WAIT_S)
    assert len(vehicle.take(4)) == 4
    assert graph(vehicle) == own  # the server's session is still there; the bridge's tokens are not


def held(worker: FakeWorker, n: int) -> None:
    deadline = time.monotonic() + WAIT_S
    while len(worker.held) < n:
        assert time.monotonic() < deadline, f"{len(worker.held)} of {n} sectors submitted"
        time.sleep(0.02)


def test_a_turns_sectors_are_submitted_one_at_a_time(bridged: Any) -> None:
    """Paced: a stream runs one sector per step, so a turn's sectors queued at once would wait out their
    deadlines on a busy CPU; the next goes once the previous is answered."""
    _, worker, vehicle = bridged(worker=FakeWorker(hold=True))
    vehicle.publish(pointcloud2_cdr(synthetic_turn(seed=9)))
    for n in range(1, 5):
        held(worker, n)
        time.sleep(0.2)
        assert len(worker.held) == n  # nothing more until this one is answered
        msg, fut = worker.held[-1]
        fut.set_result(reply_for(msg))
    assert len(vehicle.take(4)) == 4 and [m.seq for m, _ in worker.held] == [0, 1, 2, 3]


def test_with_its_own_session_the_bridge_works_and_closes_it(bridged: Any) -> None:
    bridge, worker, vehicle = bridged(own_session=True)
    assert graph(vehicle) == sorted(bridge.tokens() + vehicle.token_keys)
    vehicle.publish(pointcloud2_cdr(synthetic_turn(seed=6)))
    assert len(vehicle.take(4)) == len(worker.sectors) == 4
    bridge.close()
    deadline = time.monotonic() + WAIT_S
    while vehicle.publisher.matching_status.matching:  # its session closed: nobody takes the points
        assert time.monotonic() < deadline, "the bridge's session is still open"
        time.sleep(0.02)


# ------------------------------------------------------------------------------- a real server (model)


def scan_points() -> np.ndarray:
    """A KITTI scan (every 4th point, for speed) where the samples are, else the synthetic turn."""
    path = KITTI_VELODYNE / "000000.bin"
    if path.exists():
        return np.fromfile(path, dtype="<f4").reshape(-1, 4)[::4].copy()
    return synthetic_turn(seed=7)


@pytest.fixture(scope="module")
def server() -> Iterator[tuple[str, str]]:
    endpoint = free_endpoint()
    settings = dict(zenoh_enabled=True, zenoh_listen=(endpoint,), deadline_ms=60_000)
    ros2 = dict(ros2_points="/car1/lidar/points", ros2_markers="/car1/markers")
    with serve(default_detector(), **settings, **ros2) as running:
        yield running.url, endpoint


def sectors_total(url: str, outcome: str) -> float:
    text = httpx.get(f"{url}/metrics", timeout=10).text
    line = f'phim_sectors_total{{outcome="{outcome}",transport="ros2"}}'
    return sum(float(x.split()[-1]) for x in text.splitlines() if x.startswith(line))


def test_a_ros_graph_sees_the_servers_node_subscription_and_publishers(server: tuple[str, str]) -> None:
    _, endpoint = server
    vehicle = Vehicle(endpoint)
    try:
        vehicle.wait_matched()
        graph = vehicle.session.liveliness()
        worker = [str(r.ok.key_expr) for r in graph.get("phim/v1/workers/test-worker/*", timeout=5)]
        assert len(worker) == 1
        zid = worker[0].rsplit("/", 1)[1]  # the bridge shares the zenoh transport's session
        head = f"@ros2_lv/0/{zid}/0"
        assert sorted(str(r.ok.key_expr) for r in graph.get(f"@ros2_lv/0/{zid}/**", timeout=5)) == sorted([
            f"{head}/0/NN/%/%/phim_test_worker",
            f"{head}/1/MS/%/%/phim_test_worker/%car1%lidar%points/sensor_msgs::msg::dds_::PointCloud2_/"
            f"{PC2_HASH}/2::,5:,:,:,,",
            f"{head}/2/MP/%/%/phim_test_worker/%car1%detections/vision_msgs::msg::dds_::Detection3DArray_/"
            f"{DET_HASH}/::,10:,:,:,,",
            f"{head}/3/MP/%/%/phim_test_worker/%car1%markers/visualization_msgs::msg::dds_::MarkerArray_/"
            f"{messages.type_hash(MARKER_ARRAY)}/::,10:,:,:,,",
        ])  # fmt: skip
    finally:
        vehicle.close()


def test_a_scan_gives_the_boxes_http_gives_and_markers(server: tuple[str, str]) -> None:
    url, endpoint = server
    vehicle = Vehicle(endpoint, (DETECTIONS_KEY, MARKERS_KEY))
    try:
        vehicle.wait_matched()
        ok_before, bad_before = sectors_total(url, "ok"), sectors_total(url, "bad_request")
        points = scan_points()
        vehicle.publish(b"\x00\x01\x00\x00 not a point cloud")  # harms nothing
        vehicle.publish(pointcloud2_cdr(points, stamp_ns=STAMP_NS, frame_id="velodyne"))
        arrays = vehicle.take(4)
        markers = vehicle.take(4, MARKERS_KEY, MARKER_ARRAY)
        sectors = split_scan(points, FIELDS, 4, cloud_spin(points))
        replies = http_replies(url, "ros2-ref", sectors, FIELDS, STAMP_NS, WAIT_S)
        for reply, array, marker in zip(replies, arrays, markers, strict=True):
            assert_boxes(array, reply, atol=1e-4)
            assert len(marker.markers) == len(reply.boxes) + 1 and marker.markers[0].action == 3
        assert len(arrays[-1].detections) > 0  # the comparison compared boxes
        assert sectors_total(url, "ok") == ok_before + 4
        assert sectors_total(url, "bad_request") == bad_before + 1
    finally:
        vehicle.close()


def test_with_zenoh_off_the_bridge_opens_its_own_session() -> None:
    endpoint = free_endpoint()
    with serve(default_detector(), zenoh_listen=(endpoint,), ros2_points="/car1/lidar/points"):
        vehicle = Vehicle(endpoint)
        try:
            vehicle.wait_matched()
            vehicle.publish(pointcloud2_cdr(synthetic_turn(seed=8)[::4], stamp_ns=STAMP_NS))
            assert len(vehicle.take(4)) == 4
            graph = vehicle.session.liveliness()
            assert list(graph.get("phim/v1/workers/**", timeout=2)) == []  # no zenoh transport
        finally:
            vehicle.close()
