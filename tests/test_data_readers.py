"""Readers of real LiDAR data as labelled scans (lidar): the class mappings, the frames (boxes hold the
points the datasets say they hold), KITTI's label_fov, the native format's round trip and the data specs.
The numbers checked come from ../shared/data/README.md."""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import SHARED_DATA

import lidar.sectorizer
from lidar.datasets import DataKind, DataSpec, list_scan_paths, parse_data_spec
from lidar.labels import labels_for, nuscenes_boxes_path, read_kitti_labels, read_nuscenes_boxes
from lidar.readers import Spin, read_labeled, read_scan, sector_of_xy, write_labeled, write_native_scan
from lidar.sources import iter_labeled
from lidar.types import LEVEL_1, LEVEL_2, GroundTruth, LabeledScan, points_in_boxes
from model.config import CLASS_NAMES
from model.sectors import sector_of_points

KITTI = SHARED_DATA / "kitti_object"
ARGOVERSE = SHARED_DATA / "argoverse_kitti_format"
NUSCENES = (
    SHARED_DATA / "nuscenes_sample" / "n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin"
)
VEHICLE, PEDESTRIAN, CYCLIST = range(3)
SAMPLES = pytest.mark.samples


def _kitti_types(root: Path, name: str) -> list[str]:
    return [line.split()[0] for line in (root / "label_2" / f"{name}.txt").read_text().splitlines() if line]


def test_spin_moved_with_the_readers() -> None:
    assert lidar.sectorizer.Spin is Spin


@pytest.mark.samples
def test_kitti_frames_map_classes_and_every_box_holds_points() -> None:
    """Frames 000000..000005: Car x5 + Truck -> VEHICLE, Pedestrian x2, Cyclist; Misc and DontCare dropped."""
    want = {"Car": VEHICLE, "Truck": VEHICLE, "Pedestrian": PEDESTRIAN, "Cyclist": CYCLIST}
    totals: Counter[int] = Counter()
    for i in range(6):
        path = KITTI / "velodyne" / f"{i:06d}.bin"
        scan = read_labeled(path)
        types = _kitti_types(KITTI, scan.name)
        assert scan.gt.labels.tolist() == [want[t] for t in types if t not in ("Misc", "DontCare")], types
        assert scan.fields == ("x", "y", "z", "intensity") and scan.time is None
        direct = points_in_boxes(scan.points[:, :3], scan.gt.boxes).sum(axis=0)  # (M,)
        np.testing.assert_array_equal(scan.gt.num_points, direct)
        assert (scan.gt.num_points > 0).all(), (scan.name, scan.gt.num_points)  # measured: 9 .. 674
        lo, hi = scan.label_fov or (0.0, 0.0)
        azimuth = np.arctan2(scan.gt.boxes[:, 1], scan.gt.boxes[:, 0])
        assert ((azimuth >= lo) & (azimuth <= hi)).all()
        totals.update(scan.gt.labels.tolist())
    assert totals == {VEHICLE: 6, PEDESTRIAN: 2, CYCLIST: 1}


@pytest.mark.samples
def test_kitti_label_fov_is_the_left_camera_image() -> None:
    """P2 of frames 000001..5 (fx 721.5, cx 609.6) over 1242 px: about -41.2 .. +40.2 degrees; 000000's
    camera (fx 707.0, cx 604.1) sees a little wider."""
    for i, (lo_deg, hi_deg) in [(1, (-41.2, 40.2)), (0, (-42.1, 40.4))]:
        scan = read_labeled(KITTI / "velodyne" / f"{i:06d}.bin")
        assert scan.label_fov is not None
        lo, hi = (math.degrees(a) for a in scan.label_fov)
        assert abs(lo - lo_deg) < 0.3 and abs(hi - hi_deg) < 0.3, (lo, hi)


@pytest.mark.samples
def test_sectors_match_the_model_split() -> None:
    scan = read_labeled(KITTI / "velodyne" / "000002.bin", sectors=8)
    pts = torch.from_numpy(scan.points)
    want = sector_of_points(pts[:, 0].contiguous(), pts[:, 1].contiguous(), 8).numpy()
    assert scan.sector is not None
    np.testing.assert_array_equal(scan.sector, want)
    edges = np.array([-1.0, -1.0, 1.0, 1.0], np.float32), np.array([0.0, -0.0, 1e-9, -1e-9], np.float32)
    np.testing.assert_array_equal(
        sector_of_xy(*edges, 4), sector_of_points(torch.from_numpy(edges[0]), torch.from_numpy(edges[1]), 4)
    )


@pytest.mark.samples
def test_argoverse_upper_case_classes_and_boxes_on_points() -> None:
    """Car / PEDESTRIAN (upper case) map case-insensitively; ON_ROAD_OBSTACLE is dropped; only 4-6 boxes
    per frame hold no points (measured: 6, 6, 4)."""
    empty = []
    for i in range(3):
        scan = read_labeled(ARGOVERSE / "velodyne" / f"{i:06d}.bin")
        types = Counter(_kitti_types(ARGOVERSE, scan.name))
        assert Counter(scan.gt.labels.tolist()) == {VEHICLE: types["Car"], PEDESTRIAN: types["PEDESTRIAN"]}
        assert types["PEDESTRIAN"] > 40 and len(scan.gt) == types["Car"] + types["PEDESTRIAN"]
        empty.append(int((scan.gt.num_points == 0).sum()))
        np.testing.assert_array_equal(scan.gt.difficulty == LEVEL_2, scan.gt.num_points <= 5)
        assert (scan.gt.difficulty == LEVEL_1).sum() > 20
    assert all(4 <= n <= 6 for n in empty), empty


def _nuscenes_table() -> tuple[list[str], np.ndarray, np.ndarray]:
    """The boxes file as written: names, boxes (69, 7) in LIDAR_TOP (x right, y forward), num_lidar_pts."""
    rows = [r.split() for r in nuscenes_boxes_path(NUSCENES).read_text().splitlines()]
    rows = [r for r in rows if r and not r[0].startswith("#")]
    boxes = np.array([[float(v) for v in r[1:8]] for r in rows], np.float32)
    return [r[0] for r in rows], boxes, np.array([int(r[10]) for r in rows])


@pytest.mark.samples
def test_nuscenes_counts_agree_with_num_lidar_pts_in_either_frame() -> None:
    """README: for 61 of the 69 boxes our point-in-box count equals num_lidar_pts (65 within one), counted
    in the file's own frame; turning points and boxes into x forward, y left changes no count."""
    names, raw_boxes, num_lidar_pts = _nuscenes_table()
    raw = np.fromfile(NUSCENES, dtype="<f4").reshape(-1, 5)
    counts = points_in_boxes(raw[:, :3], raw_boxes).sum(axis=0)  # (69,)
    assert len(names) == 69
    assert int((counts == num_lidar_pts).sum()) == 61
    assert int((np.abs(counts - num_lidar_pts) <= 1).sum()) == 65
    ours = read_nuscenes_boxes(nuscenes_boxes_path(NUSCENES), keep_ignored=True)
    assert ours.names == tuple(names)
    turned = points_in_boxes(read_scan(NUSCENES).points[:, :3], ours.boxes).sum(axis=0)  # x forward, y left
    np.testing.assert_array_equal(turned, counts)

    scan = read_labeled(NUSCENES)
    targets = [i for i, n in enumerate(names) if n not in ("barrier", "traffic_cone", "ignore")]
    assert Counter(scan.gt.labels.tolist()) == {VEHICLE: 12, PEDESTRIAN: 30, CYCLIST: 1}
    np.testing.assert_array_equal(scan.gt.num_points, counts[targets])
    assert scan.label_fov is None and scan.fields == ("x", "y", "z", "intensity", "ring")


def _labeled_kitti_with_time() -> LabeledScan:
    scan = read_labeled(KITTI / "velodyne" / "000001.bin")
    time = np.linspace(0.0, 0.1, scan.points.shape[0], dtype=np.float32)  # (N,)
    return LabeledScan(scan.name, scan.points, scan.fields, scan.gt, time, scan.sector, scan.label_fov)


@pytest.mark.samples
def test_native_round_trip(tmp_path: Path) -> None:
    scan = _labeled_kitti_with_time()
    write_labeled(tmp_path / "000001.npz", scan)
    back = read_labeled(tmp_path / "000001.npz")
    assert back.name == scan.name and back.fields == scan.fields and back.label_fov == scan.label_fov
    for a, b in [(back.points, scan.points), (back.time, scan.time), (back.sector, scan.sector)]:
        np.testing.assert_array_equal(a, b)
    for a, b in zip(vars(back.gt).values(), vars(scan.gt).values(), strict=True):
        np.testing.assert_array_equal(a, b)
        assert a.dtype == b.dtype
    stored = labels_for(tmp_path / "000001.npz")
    assert stored is not None and stored.names == tuple(CLASS_NAMES[i] for i in scan.gt.labels)


def test_native_without_gt_other_columns_and_bad_names(tmp_path: Path) -> None:
    pts = np.array([[0.5, 10.0, 1.0, 0.0, 7.0], [0.2, -3.0, 4.0, -1.0, 8.0]], np.float32)  # (2, 5)
    write_native_scan(tmp_path / "a.npz", pts, ("intensity", "x", "y", "z", "ring"))
    scan = read_labeled(tmp_path / "a.npz")
    assert scan.fields == ("x", "y", "z", "intensity", "ring") and len(scan.gt) == 0 and scan.time is None
    np.testing.assert_array_equal(scan.points, pts[:, [1, 2, 3, 0, 4]])
    assert scan.gt.boxes.shape == (0, 7) and scan.label_fov is None

    box = GroundTruth.from_boxes(np.array([[10.0, 1.0, 0.0, 2.0, 2.0, 2.0, 0.0]]), np.array([2]), scan.points)
    assert box.num_points.tolist() == [1] and box.difficulty.tolist() == [LEVEL_2]
    np.savez(tmp_path / "b.npz", points=pts, fields=np.array(["intensity", "x", "y", "z", "ring"]),
             gt_boxes=box.boxes, gt_names=np.array(["Bus"]))  # fmt: skip
    with pytest.raises(ValueError, match="Bus"):
        read_labeled(tmp_path / "b.npz")
    np.savez(tmp_path / "c.npz", points=pts, fields=np.array(["intensity", "x", "y", "z", "ring"]),
             gt_boxes=box.boxes)  # fmt: skip
    with pytest.raises(ValueError, match="gt_names"):
        read_labeled(tmp_path / "c.npz")


@pytest.mark.samples
def test_data_specs_parse_and_iterate(tmp_path: Path) -> None:
    assert parse_data_spec("sim") == DataSpec(DataKind.SIM)
    assert parse_data_spec(f"kitti:{KITTI}") == DataSpec(DataKind.KITTI, KITTI)
    assert [s.name for s in iter_labeled(f"kitti:{KITTI}")] == [f"{i:06d}" for i in range(6)]
    assert list_scan_paths(parse_data_spec(f"kitti:{KITTI}"))[0] == KITTI / "velodyne" / "000000.bin"
    assert [len(s.gt) for s in iter_labeled(f"nuscenes:{NUSCENES.parent}")] == [43]
    write_labeled(tmp_path / "x.npz", _labeled_kitti_with_time())
    assert [len(s.gt) for s in iter_labeled(f"native:{tmp_path}")] == [3]


@pytest.mark.parametrize(
    ("spec", "error", "says"),
    [
        ("waymo:/data", ValueError, "unknown kind 'waymo'.*kitti:DIR"),
        ("kitti", ValueError, "kitti needs a folder"),
        ("sim:3", ValueError, "sim takes no argument"),
        ("kitti:/no/such/folder", FileNotFoundError, "/no/such/folder is not a folder"),
        pytest.param(
            f"kitti:{SHARED_DATA}", FileNotFoundError, "lacks.*velodyne/, label_2/ and calib/", marks=SAMPLES
        ),
        pytest.param(f"nuscenes:{KITTI}", FileNotFoundError, r"no \*\.pcd\.bin", marks=SAMPLES),
        pytest.param(f"native:{KITTI}", FileNotFoundError, r"no \*\.npz", marks=SAMPLES),
    ],
)
def test_bad_specs_say_what_was_expected(spec: str, error: type[Exception], says: str) -> None:
    with pytest.raises(error, match=says) as info:
        iter_labeled(spec)
    assert spec.split(":")[0] in str(info.value)


@pytest.mark.samples
def test_kitti_scan_without_labels_is_an_error(tmp_path: Path) -> None:
    (tmp_path / "velodyne").mkdir()
    read_scan(KITTI / "velodyne" / "000003.bin").points.tofile(tmp_path / "velodyne" / "000003.bin")
    with pytest.raises(FileNotFoundError, match="label_2"):
        read_labeled(tmp_path / "velodyne" / "000003.bin")
    assert len(read_kitti_labels(KITTI / "label_2" / "000003.txt", KITTI / "calib" / "000003.txt").names) >= 1
