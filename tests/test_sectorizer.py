"""Client-side sectorizer: exact partition, sweep order, wrap, spin direction, packet-by-packet input."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from lidar.sectorizer import Spin, StreamSectorizer, detect_spin, sector_of_azimuth, split_scan
from model.sectors import split_turn
from tests.conftest import SHARED_DATA, kitti_scan

FIELDS_IDX = ("x", "y", "z", "intensity", "idx")


def with_index(points: np.ndarray) -> np.ndarray:
    """Append the row number as a column, so every output point can be traced back to its input row."""
    return np.concatenate([points, np.arange(points.shape[0], dtype=np.float32)[:, None]], axis=1)


def rows(sectors) -> np.ndarray:
    return np.concatenate([s.points[:, -1] for s in sectors]).astype(np.int64)


@pytest.mark.samples
@pytest.mark.parametrize(("spin", "order"), [(Spin.CCW, [2, 3, 0, 1]), (Spin.CW, [2, 1, 0, 3])])
def test_split_scan_partitions_a_kitti_scan_in_sweep_order(spin: Spin, order: list[int]) -> None:
    scan = kitti_scan(0).numpy()  # starts at azimuth ~0 deg: sector 2 of 4
    sectors = split_scan(with_index(scan), FIELDS_IDX, 4, spin, output_fields=FIELDS_IDX)
    assert [s.index for s in sectors] == order
    idx = rows(sectors)
    assert np.array_equal(np.sort(idx), np.arange(scan.shape[0]))  # every point exactly once
    for s in sectors:
        assert np.all(np.diff(s.points[:, -1]) > 0)  # original (firing) order kept
        az = np.arctan2(s.points[:, 1], s.points[:, 0])
        assert np.all(sector_of_azimuth(az, 4) == s.index)
    # the same partition as the model's own split
    model_split = split_turn(torch.from_numpy(scan), 4)
    for s in sectors:
        assert np.array_equal(np.sort(s.points[:, :4], axis=0), np.sort(model_split[s.index].numpy(), axis=0))


@pytest.mark.samples
def test_fields_in_any_order_and_missing_fields() -> None:
    scan = kitti_scan(1).numpy()[:1000]
    shuffled = scan[:, [3, 0, 2, 1]]  # intensity, x, z, y
    a = split_scan(scan, ("x", "y", "z", "intensity"))
    b = split_scan(shuffled, ("intensity", "X", "z", "y"))
    assert all(np.array_equal(sa.points, sb.points) for sa, sb in zip(a, b, strict=True))
    assert a[0].points.dtype == np.float32 and a[0].points.shape[1] == 4
    with pytest.raises(ValueError, match=r"\['intensity'\] not among"):
        split_scan(scan[:, :3], ("x", "y", "z"))
    with pytest.raises(ValueError, match="duplicate"):
        split_scan(scan, ("x", "y", "x", "intensity"))


def sweep(
    turns: float, spin: Spin, start_deg: float, seed: int, beams: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """A simulated spinning sensor: firings every 0.5 deg, `beams` points each with +-0.3 deg beam offsets
    (so points near a sector boundary fall on both sides of it). -> points (N, 5) with row index, azimuth."""
    rng = np.random.default_rng(seed)
    firings = int(turns * 720)
    sign = 1.0 if spin is Spin.CCW else -1.0
    fire_az = np.deg2rad(start_deg + sign * 0.5 * np.arange(firings))  # (F,)
    az = (fire_az[:, None] + np.deg2rad(rng.uniform(-0.3, 0.3, (firings, beams)))).reshape(-1)  # (N,)
    r = rng.uniform(2, 60, az.size)
    pts = np.stack([r * np.cos(az), r * np.sin(az), rng.uniform(-2, 1, az.size), rng.random(az.size)], 1)
    return with_index(pts.astype(np.float32)), np.angle(np.exp(1j * az))


@pytest.mark.parametrize("spin", list(Spin))
@pytest.mark.parametrize("start_deg", [-179.0, 10.0, 135.0])
def test_stream_sectorizer_packets_cover_every_point_once_in_order(spin: Spin, start_deg: float) -> None:
    points, az = sweep(2.6, spin, start_deg, seed=abs(int(start_deg)) + 7)
    assert detect_spin(az[::8]) is spin
    sec = StreamSectorizer(FIELDS_IDX, 4, spin, output_fields=FIELDS_IDX)
    rng = np.random.default_rng(0)
    out, i = [], 0
    while i < points.shape[0]:  # packets of random size, some of them a single point
        n = int(rng.integers(1, 700))
        out += sec.push(points[i : i + n])
        i += n
    out += sec.flush()
    idx = rows(out)
    assert np.array_equal(idx, np.arange(points.shape[0]))  # every point once, in firing order
    step = 1 if spin is Spin.CCW else -1
    assert all((b.index - a.index) % 4 == step % 4 for a, b in itertools.pairwise(out))
    assert 10 <= len(out) <= 12 and out[-1].turn == 2 and out[4].turn == 1
    for s in out:  # every point is in its sector, or within the beam jitter (0.3 deg) of its boundary
        k = sector_of_azimuth(az[s.points[:, -1].astype(np.int64)], 4)
        stray = k != s.index
        lo = -math.pi + s.index * math.pi / 2
        dist = np.abs(np.angle(np.exp(1j * (az[s.points[stray, -1].astype(np.int64)] - lo))))
        assert np.all(np.minimum(dist, np.abs(dist - math.pi / 2)) < np.deg2rad(0.61))


def test_skipped_sectors_are_emitted_empty() -> None:
    sec = StreamSectorizer(("x", "y", "z", "intensity"), 4, Spin.CCW)
    p0 = np.array([[-5.0, -0.5, 0.0, 0.5]], dtype=np.float32)  # azimuth ~ -174 deg: sector 0
    p2 = np.array([[5.0, 0.9, 0.0, 0.5]], dtype=np.float32)  # azimuth ~ +10 deg: sector 2
    assert sec.push(p0) == []
    out = sec.push(p2)  # the packets for sector 1 were lost
    assert [s.index for s in out] == [0, 1] and [len(s.points) for s in out] == [1, 0]
    assert [s.index for s in sec.flush()] == [2]


@pytest.mark.samples
def test_nuscenes_sweep_packet_by_packet() -> None:
    """Real firing-order data: nuScenes LIDAR_TOP (32 beams, azimuth decreasing), 12 firings a packet."""
    path = next((SHARED_DATA / "nuscenes_sample").glob("*.pcd.bin"))
    raw = np.fromfile(path, dtype=np.float32).reshape(-1, 5)  # x, y, z, intensity, ring
    fields = ("x", "y", "z", "intensity", "ring", "idx")
    points = with_index(raw)
    az = np.arctan2(raw[:, 1], raw[:, 0])
    far = np.hypot(raw[:, 0], raw[:, 1]) > 1.0  # ego-vehicle returns have no meaningful azimuth
    assert detect_spin(az[far]) is Spin.CW
    sec = StreamSectorizer(fields, 4, Spin.CW, output_fields=("x", "y", "z", "intensity", "idx"))
    out = []
    for start in range(0, points.shape[0], 12 * 32):
        out += sec.push(points[start : start + 12 * 32])
    out += sec.flush()
    assert np.array_equal(rows(out), np.arange(points.shape[0]))
    assert len(out) in (4, 5, 6)  # a little more than one turn (about 363 degrees)
    assert all((a.index - b.index) % 4 == 1 for a, b in itertools.pairwise(out))
