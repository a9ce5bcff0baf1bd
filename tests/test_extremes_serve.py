"""The contract's coordinate range at the door and the issue's killer inputs sent to a real worker (issue 51).

`contract.MAX_COORDINATE_M`, checked in `server.admission` for HTTP, zenoh and the ROS 2 bridge alike; a
PointCloud2 whose `is_bigendian` lies (coordinates up to 3e38 as read); and the issue's killer sector and
cloud sent to a real `phim serve` (a process of its own: a crash fails the test, not pytest) over HTTP,
zenoh and ROS 2: each is answered with an error naming `points` or counted as refused, and the worker goes
on answering other streams. Should a native crash happen anyway, its log holds the stack. The kernels
themselves meet the extremes in tests/test_extremes.py."""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from test_extremes import F32_MAX, FIELDS, REPO, cluster, killer_sector

from contract import (
    MAX_COORDINATE_M,
    MSGPACK,
    DetectionsReply,
    ErrorCode,
    ErrorReply,
    SectorMessage,
    ServiceError,
    decode_response,
    encode_sector,
)

# ------------------------------------------------------------------------- the contract's range, at the door


@pytest.mark.parametrize("column", [0, 1, 2])
def test_the_contract_refuses_a_coordinate_beyond_its_range_naming_it(column: int) -> None:
    """`sector_points` (every transport's way in): +-MAX_COORDINATE_M pass, the next float32 beyond is
    INVALID_FIELD on `points`, naming the column, the value, the row and the bound. Intensity has no range."""
    from model.config import tiny
    from server.admission import sector_points

    pts = cluster(np.random.default_rng(column))
    pts[0, column], pts[1, column], pts[2, 3] = MAX_COORDINATE_M, -MAX_COORDINATE_M, F32_MAX
    assert sector_points(SectorMessage("s", 0, 1, 0, pts, FIELDS), tiny()).shape == pts.shape
    beyond = np.nextafter(np.float32(MAX_COORDINATE_M), np.float32(np.inf))
    for value in (-beyond, beyond, 1e19, -1e30, F32_MAX):
        pts[5, column] = value
        with pytest.raises(ServiceError) as e:
            sector_points(SectorMessage("s", 0, 1, 0, pts, FIELDS), tiny())
        assert e.value.code is ErrorCode.INVALID_FIELD and e.value.field == "points"
        named = f"row 5 first: {FIELDS[column]} = {float(np.float32(value)):g}"
        assert named in e.value.message and "10000 m" in e.value.message, e.value.message


def mislabelled_cloud() -> bytes:
    """A little-endian PointCloud2 flagged `is_bigendian` (CDR): finite coordinates up to ~3e38 as read."""
    from ros2_helpers import VELODYNE_XYZIRT, pointcloud2_message

    from lidar.synthetic import synthetic_turn
    from ros.pointcloud2 import POINTCLOUD2, typestore

    msg = dataclasses.replace(pointcloud2_message(synthetic_turn(seed=3)), is_bigendian=True)
    assert not VELODYNE_XYZIRT.big_endian  # the data under the flag is little-endian
    return bytes(typestore().serialize_cdr(msg, POINTCLOUD2))


def test_a_pointcloud2_whose_byte_order_lies_is_refused_naming_the_field() -> None:
    from ros.pointcloud2 import decode_pointcloud2, pointcloud2_points

    msg = decode_pointcloud2(mislabelled_cloud())
    with pytest.raises(ValueError, match=r"PointCloud2 field 'x': \d+ points beyond 10000 m .*is_bigendian"):
        pointcloud2_points(msg)
    right = pointcloud2_points(dataclasses.replace(msg, is_bigendian=False))  # the same bytes, the true order
    assert len(right) == msg.width and float(np.abs(right[:, :3]).max()) < 100


# ----------------------------------------------------------------------------- a real `phim serve`


@pytest.fixture(scope="module")
def worker(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str, subprocess.Popen, Path]]:
    """`phim serve` in a process of its own (a crash must not take pytest with it): HTTP, zenoh, the ROS 2
    bridge on /car1/lidar/points -> (url, zenoh endpoint, process, its log)."""
    from server_helpers import free_endpoint, free_port

    port, endpoint = free_port(), free_endpoint()
    env = {**os.environ, "PHIM_PORT": str(port), "PHIM_ZENOH_LISTEN": endpoint, "PHIM_WARMUP_SECTORS": "1"}
    env |= {"PHIM_ROS2_POINTS": "/car1/lidar/points", "PHIM_DEADLINE_MS": "120000"}
    log_path = tmp_path_factory.mktemp("serve") / "serve.log"
    with log_path.open("w") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "phim", "serve"], cwd=REPO, env=env, stdout=log, stderr=log
        )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 300
        while not _ready(url):
            assert proc.poll() is None and time.monotonic() < deadline, log_path.read_text()[-3000:]
            time.sleep(0.3)
        yield url, endpoint, proc, log_path
    finally:
        proc.terminate()
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(30)


def _ready(url: str) -> bool:
    try:
        return httpx.get(f"{url}/health/ready", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


def _post(url: str, stream: str, points: np.ndarray, index: int) -> httpx.Response:
    body = encode_sector(SectorMessage(stream, 0, index, 0, points, FIELDS))
    return httpx.post(
        f"{url}/v1/streams/{stream}/sectors", content=body, headers={"Content-Type": MSGPACK}, timeout=120
    )


def _rejected_ros2(url: str) -> float:
    line = 'phim_sectors_total{outcome="invalid_field",transport="ros2"}'
    text = httpx.get(f"{url}/metrics", timeout=10).text
    return sum(float(x.split()[-1]) for x in text.splitlines() if x.startswith(line))


def test_the_issues_sector_and_cloud_are_answered_and_the_worker_goes_on(worker) -> None:
    """Issue 51's killer sector (sector 1 of a fresh stream) over HTTP and zenoh, and the mislabelled
    PointCloud2 over ROS 2: each answered with an error naming `points` or counted as refused; then a good
    cloud and another HTTP stream get boxes from the same, living worker."""
    from ros2_helpers import pointcloud2_cdr
    from test_ros2_bridge import Vehicle

    from clients.base import ServerError
    from clients.connect import ConnectConfig, Transport, make_client
    from lidar.synthetic import synthetic_turn

    url, endpoint, proc, _ = worker
    r = _post(url, "killer-http", killer_sector(), 1)
    error = decode_response(r.content)
    assert r.status_code == 422 and isinstance(error, ErrorReply), r.content
    assert error.field == "points" and "row 300 first: x = -1e+30" in error.message, error.message
    with (
        make_client(
            ConnectConfig(Transport.ZENOH, url=url, zenoh_connect=(endpoint,), timeout_s=120)
        ) as client,
        pytest.raises(ServerError) as e,
    ):
        client.send(SectorMessage("killer-zenoh", 0, 1, 0, killer_sector(), FIELDS))
    assert (
        e.value.code is ErrorCode.INVALID_FIELD and e.value.field == "points" and "-1e+30" in e.value.message
    )
    vehicle = Vehicle(endpoint)
    try:
        vehicle.wait_matched()
        before = _rejected_ros2(url)
        vehicle.publish(mislabelled_cloud())
        deadline = time.monotonic() + 120
        while _rejected_ros2(url) < before + 1:
            assert time.monotonic() < deadline and proc.poll() is None, (
                "the mislabelled cloud was not refused"
            )
            time.sleep(0.2)
        vehicle.publish(pointcloud2_cdr(synthetic_turn(seed=8, firings=500)))
        assert len(vehicle.take(4)) == 4  # a sector's detections each: the bridge goes on
    finally:
        vehicle.close()
    reply = _post(url, "after", cluster(np.random.default_rng(1)), 1)
    assert reply.status_code == 200 and isinstance(decode_response(reply.content), DetectionsReply)
    assert proc.poll() is None


def test_a_native_crash_leaves_its_stack_in_the_log_and_a_failed_exit(worker) -> None:
    """Should a native crash happen anyway: the process dies with the signal's exit status (what a
    supervisor restarts on: docs/security.md) and the log holds every thread's Python stack."""
    url, _, proc, log_path = worker
    assert proc.poll() is None and _ready(url)  # the tests before left it alive
    proc.send_signal(signal.SIGSEGV)
    assert proc.wait(60) == -signal.SIGSEGV
    log = log_path.read_text()
    assert "Fatal Python error: Segmentation fault" in log and "Thread 0x" in log, log[-3000:]
