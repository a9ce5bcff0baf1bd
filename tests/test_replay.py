"""`phim replay` against a real server: one prediction record per sector, the scan's prediction on its
last sector, BEV frames that are real pictures; the scan readers (KITTI, nuScenes, .npz); KITTI labels."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from client_helpers import EVERY, Served, png_is_a_picture, serve_both
from conftest import KITTI_VELODYNE, SHARED_DATA
from server_helpers import default_detector

from clients.connect import Transport
from clients.predictions import read_predictions, scan_predictions
from clients.replay import ReplayConfig, replay
from lidar.labels import kitti_labels_for, nuscenes_labels_for
from lidar.readers import Spin, find_scans, read_scan, write_native_scan
from phim.cli import main as app

pytestmark = pytest.mark.samples  # every test replays or reads the real KITTI and nuScenes samples
NUSCENES = (
    SHARED_DATA / "nuscenes_sample" / "n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin"
)


@pytest.fixture(scope="module")
def served() -> Iterator[Served]:
    with serve_both(default_detector()) as s:
        yield s


def test_replay_kitti_writes_one_record_per_sector_and_frames(served: Served, tmp_path: Path) -> None:
    out, frames = tmp_path / "pred.jsonl", tmp_path / "frames"
    args = ["replay", str(KITTI_VELODYNE), "--url", served.url, "--out", str(out), "--frames", str(frames)]
    result = CliRunner().invoke(app, [*args, "--rate", "0", "--every", str(EVERY), "--max-scans", "2"])
    assert result.exit_code == 0, result.output
    header, records = read_predictions(out)
    assert header["sectors_per_turn"] == 4 and header["model"]["config"] == "tiny"
    assert len(records) == 2 * 4 and [r.seq for r in records] == list(range(8))
    assert all(r.error is None for r in records)
    scans = scan_predictions(records)
    assert sorted(scans) == ["000000", "000001"]
    assert all(r.context_sectors == 4 and r.position == 3 for r in scans.values())
    assert sorted({r.sector_index for r in records if r.scan == "000000"}) == [0, 1, 2, 3]
    assert all(r.boxes.shape == (len(r.class_names), 7) for r in records)
    for name in scans:
        png_is_a_picture(frames / f"{name}.png")


def test_replay_native_and_nuscenes_over_zenoh_at_sensor_rate(served: Served, tmp_path: Path) -> None:
    drive = tmp_path / "drive"
    drive.mkdir()
    kitti = read_scan(KITTI_VELODYNE / "000002.bin")
    elongation = np.zeros((kitti.points.shape[0], 1), np.float32)
    pts = np.concatenate([kitti.points[:, [3, 0, 1, 2]], elongation], axis=1)[::EVERY]  # other column order
    write_native_scan(drive / "a.npz", pts, ("intensity", "x", "y", "z", "elongation"), Spin.CCW, 123)
    nus = read_scan(NUSCENES)
    write_native_scan(drive / "b.npz", nus.points[::4], nus.fields, nus.spin)
    cfg = ReplayConfig(
        source=drive,
        predictions=tmp_path / "p.jsonl",
        connect=served.connect(Transport.ZENOH),
        turns_per_s=5.0,
    )
    start = time.monotonic()
    summary = replay(cfg)
    assert summary.scans == 2 and summary.sectors == 8 and summary.ok == 8 and summary.errors == 0
    assert time.monotonic() - start >= 7 / 20  # paced: 8 sectors at 20 sectors/s
    _, records = read_predictions(cfg.predictions)
    assert [r.scan for r in records] == ["a"] * 4 + ["b"] * 4
    assert records[0].points > 0 and sum(r.points for r in records[:4]) == pts.shape[0]


def test_scan_readers() -> None:
    kitti = read_scan(KITTI_VELODYNE / "000000.bin")
    assert kitti.fields == ("x", "y", "z", "intensity") and kitti.spin is Spin.CCW and kitti.name == "000000"
    nus = read_scan(NUSCENES)
    assert nus.spin is Spin.CW and nus.fields[:4] == ("x", "y", "z", "intensity") and nus.points.shape[1] == 5
    assert float(nus.points[:, 3].max()) <= 1.0
    raw = np.fromfile(NUSCENES, dtype="<f4").reshape(-1, 5)
    np.testing.assert_allclose(nus.points[:, 0], raw[:, 1])  # x forward = nuScenes y
    assert [p.name for p in find_scans(KITTI_VELODYNE)][:2] == ["000000.bin", "000001.bin"]


def test_kitti_labels_land_on_their_points() -> None:
    """label_2 boxes in the velodyne frame hold LiDAR points (calib conversion and yaw are right)."""
    scan = read_scan(KITTI_VELODYNE / "000001.bin")
    labels = kitti_labels_for(scan.path)
    assert labels is not None and len(labels.names) > 0 and "DontCare" not in labels.names
    inside = []
    for (x, y, z, length, w, h, yaw), name in zip(labels.boxes, labels.names, strict=True):
        d = scan.points[:, :3] - np.array([x, y, z])
        c, s = math.cos(-yaw), math.sin(-yaw)
        u, v = d[:, 0] * c - d[:, 1] * s, d[:, 0] * s + d[:, 1] * c
        hit = (np.abs(u) <= length / 2) & (np.abs(v) <= w / 2) & (np.abs(d[:, 2]) <= h / 2)
        inside.append((name, int(hit.sum())))
    assert sum(n > 10 for _, n in inside) >= len(inside) // 2, inside


def test_nuscenes_labels_land_on_their_points() -> None:
    """The sample's boxes, turned into the x-forward frame the sweep is read in, hold the points nuScenes
    counted for them (its README: 61 of 69 boxes agree exactly, 65 within one point)."""
    scan = read_scan(NUSCENES)
    labels = nuscenes_labels_for(scan.path)
    assert labels is not None and len(labels.names) == 68 and "ignore" not in labels.names
    boxes_file = NUSCENES.with_name(NUSCENES.name.removesuffix(".pcd.bin") + "_boxes.txt")
    table = [line.split() for line in boxes_file.read_text().splitlines()]
    expected = [int(row[10]) for row in table if row and not row[0].startswith("#") and row[0] != "ignore"]
    agree = 0
    for (x, y, z, length, w, h, yaw), want in zip(labels.boxes, expected, strict=True):
        d = scan.points[:, :3] - np.array([x, y, z])
        c, s = math.cos(-yaw), math.sin(-yaw)
        u, v = d[:, 0] * c - d[:, 1] * s, d[:, 0] * s + d[:, 1] * c
        hit = (np.abs(u) <= length / 2) & (np.abs(v) <= w / 2) & (np.abs(d[:, 2]) <= h / 2)
        agree += abs(int(hit.sum()) - want) <= 1
    assert agree >= 60, agree
