"""The ROS 2 bridge against what a stranger (or a restarting driver) sends, with a real server (the default
model, the bridge on its zenoh session) and a vehicle as rmw_zenoh runs one: a sector with seq 2^63-1 on the
bridge's stream costs the vehicle one sector, never its stream; a driver's restart changes nothing; a huge
frame_id refuses its scan; NaN intensities and NaN coordinates follow one rule (the point is dropped)."""

from __future__ import annotations

import contextlib
import queue
import time
from collections.abc import Iterator

import httpx
import numpy as np
import pytest
from ros2_helpers import assert_boxes, http_replies, pointcloud2_cdr
from server_helpers import START_TIMEOUT_S, default_detector, free_endpoint, serve
from test_ros2_bridge import (
    FIELDS,
    STAMP_NS,
    Vehicle,
    cloud_spin,
    scan_points,
    sectors_total,
    split_scan,
)

from contract import INT64_MAX, MSGPACK, DetectionsReply, SectorMessage, decode_response, encode_sector

WAIT_S = START_TIMEOUT_S  # bounded, generous: each wait ends once met


@pytest.fixture(scope="module")
def server() -> Iterator[tuple[str, str]]:
    endpoint = free_endpoint()
    settings = dict(zenoh_enabled=True, zenoh_listen=(endpoint,), deadline_ms=60_000)
    with serve(default_detector(), **settings, ros2_points="/car1/lidar/points") as running:
        yield running.url, endpoint


def answered(url: str) -> float:
    """The bridge's sectors answered so far, whatever the answer."""
    text = httpx.get(f"{url}/metrics", timeout=10).text
    prefix = "phim_sectors_total{"
    lines = [x for x in text.splitlines() if x.startswith(prefix) and 'transport="ros2"' in x]
    return sum(float(x.split()[-1]) for x in lines)


def publish_and_settle(url: str, vehicle: Vehicle, cdr: bytes, sectors: int = 4, published: int = 4) -> int:
    """Publish one scan, wait until its sectors are answered and `published` arrays came back (each wait
    ends once met, however slow the machine); the arrays published for it, extras included."""
    before = answered(url)
    vehicle.publish(cdr)
    deadline = time.monotonic() + WAIT_S
    while answered(url) < before + sectors:
        assert time.monotonic() < deadline, "the scan's sectors were not all answered"
        time.sleep(0.05)
    return drain(vehicle, expected=published)


def drain(vehicle: Vehicle, expected: int = 0) -> int:
    """The arrays that came: the first `expected` awaited (up to WAIT_S each), then any more."""
    (got,) = vehicle.got.values()
    n = 0
    with contextlib.suppress(queue.Empty):
        for _ in range(expected):
            got.get(timeout=WAIT_S)
            n += 1
    while True:
        try:
            got.get(timeout=0.2)
        except queue.Empty:
            return n
        n += 1


def test_a_huge_seq_on_the_bridges_stream_does_not_lock_the_vehicle_out(server: tuple[str, str]) -> None:
    url, endpoint = server
    points = scan_points()
    cdr = pointcloud2_cdr(points, stamp_ns=STAMP_NS, frame_id="velodyne")
    vehicle = Vehicle(endpoint)
    try:
        vehicle.wait_matched()
        assert publish_and_settle(url, vehicle, cdr) == 4
        # a stranger's sector on the bridge's stream ID, as far ahead as a seq goes
        forged = SectorMessage(
            "car1", INT64_MAX, 0, STAMP_NS, points[:200], ("x", "y", "z", "intensity"), True
        )
        r = httpx.post(
            f"{url}/v1/streams/car1/sectors",
            content=encode_sector(forged),
            headers={"Content-Type": MSGPACK},
            timeout=WAIT_S,
        )
        assert isinstance(decode_response(r.content), DetectionsReply)
        stale = sectors_total(url, "stale_sequence")
        assert (
            publish_and_settle(url, vehicle, cdr, published=3) == 3
        )  # the first is stale, the next restarts
        assert sectors_total(url, "stale_sequence") == stale + 1
        assert publish_and_settle(url, vehicle, cdr) == 4  # and the vehicle goes on
    finally:
        vehicle.close()
    restarted = Vehicle(endpoint)  # the driver restarts: a new session, its message count from 1 again
    try:
        restarted.wait_matched()
        assert publish_and_settle(url, restarted, cdr) == 4
    finally:
        restarted.close()


def test_a_huge_frame_id_refuses_its_scan(server: tuple[str, str]) -> None:
    url, endpoint = server
    points = scan_points()
    vehicle = Vehicle(endpoint)
    try:
        vehicle.wait_matched()
        refused = sectors_total(url, "invalid_field")
        vehicle.publish(pointcloud2_cdr(points, stamp_ns=STAMP_NS, frame_id="f" * 100_000))
        deadline = time.monotonic() + WAIT_S
        while sectors_total(url, "invalid_field") < refused + 1:
            assert time.monotonic() < deadline, "the scan was not refused"
            time.sleep(0.05)
        assert drain(vehicle) == 0  # nothing published for it
        longest = "f" * 256  # --max-string-len: still taken, echoed in every header
        assert (
            publish_and_settle(url, vehicle, pointcloud2_cdr(points, stamp_ns=STAMP_NS, frame_id=longest))
            == 4
        )
    finally:
        vehicle.close()


def test_nan_intensities_and_nan_coordinates_follow_one_rule(server: tuple[str, str]) -> None:
    """Every sector answered, with the boxes of the same scan without those points: each point with a NaN
    was dropped (not patched, nor its sector refused)."""
    url, endpoint = server
    points = scan_points().copy()
    rng = np.random.default_rng(11)
    tenth = len(points) // 10  # enough that patching them instead would change the boxes
    points[rng.choice(len(points), tenth, replace=False), 3] = np.nan  # intensity
    points[rng.choice(len(points), tenth, replace=False), 0] = np.nan  # x: a driver's "no return"
    kept = points[np.isfinite(points).all(axis=1)]  # (N', 4): what the rule leaves
    vehicle = Vehicle(endpoint)
    try:
        vehicle.wait_matched()
        # the bridge's stream starts cold, as the reference stream below
        assert httpx.delete(f"{url}/v1/streams/car1", timeout=WAIT_S).status_code in (200, 204, 404)
        ok = sectors_total(url, "ok")
        vehicle.publish(pointcloud2_cdr(points, stamp_ns=STAMP_NS))
        arrays = vehicle.take(4)
        sectors = split_scan(kept, FIELDS, 4, cloud_spin(kept))
        for array, reply in zip(
            arrays, http_replies(url, "nan-ref", sectors, FIELDS, STAMP_NS, WAIT_S), strict=True
        ):
            assert_boxes(array, reply, atol=1e-4)
        assert sum(len(a.detections) for a in arrays) > 0  # the comparison compared boxes
        assert sectors_total(url, "ok") == ok + 4  # the bridge's sectors (the reference came over HTTP)
    finally:
        vehicle.close()
