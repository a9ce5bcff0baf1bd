"""Recorded LiDAR scans on disk -> points with named columns, as the sensor fired them, and labelled scans
(`read_labeled`: the points with their ground truth, for training and evaluation). Numpy only.

Formats (chosen by file name):
  - KITTI velodyne `*.bin`: float32 (N, 4) x, y, z, reflectance; x forward, y left, z up; spins CCW.
  - nuScenes `*.pcd.bin`: float32 (N, 5) x, y, z, intensity (0-255), ring in the LIDAR_TOP frame (x right,
    y forward); spins CW. Read into x forward, y left (rotated -90 degrees about z), intensity / 255.
  - native `*.npz` (see docs/data.md, "Native scan"): `points` float32 (N, C) and `fields` (C,) column
    names including x, y, z, intensity; optional `spin` ("ccw" | "cw"), `timestamp_ns`, `time` (N,) and
    ground truth `gt_boxes` (M, 7) + `gt_names` (M,) + `label_fov` (2,) (read by `lidar.labels`).
A drive is a folder of such files, replayed in name order. Label files and class mappings:
`lidar.labels`.
"""

from __future__ import annotations

import math
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from contract import POINT_FIELDS, REQUIRED_FIELDS
from lidar.labels import AS_IS, FileFrame, labeled_targets
from lidar.types import CLASS_NAMES, DEFAULT_SECTORS, GroundTruth, LabeledScan, Spin

SCAN_SUFFIXES = (".bin", ".npz")


@dataclass(frozen=True)
class Scan:
    name: str  # file name without its suffixes
    path: Path
    points: np.ndarray  # (N, C) float32, columns named by `fields`, firing order
    fields: tuple[str, ...]
    spin: Spin
    timestamp_ns: int | None = None
    time: np.ndarray | None = None  # (N,) float32 seconds since the turn began (native files only)


def scan_name(path: Path) -> str:
    name = path.name
    for suffix in (".pcd.bin", ".bin", ".npz"):
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return path.stem


def find_scans(folder: Path) -> list[Path]:
    """The scan files of a drive folder (or the file itself), in name order."""
    folder = Path(folder)
    if folder.is_file():
        return [folder]
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such file or folder")
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix in SCAN_SUFFIXES)


def read_scan(path: Path) -> Scan:
    path = Path(path)
    if path.name.endswith(".pcd.bin"):
        return _nuscenes(path)
    if path.suffix == ".npz":
        return _native(path)
    if path.suffix == ".bin":
        return _kitti(path)
    raise ValueError(f"{path}: unknown scan format; expected .bin (KITTI), .pcd.bin (nuScenes) or .npz")


def _kitti(path: Path) -> Scan:
    """A KITTI velodyne .bin: 16 bytes a point; a file of another length, or without one finite point, is
    refused (ValueError naming it), never truncated or sent as empty sectors."""
    size = path.stat().st_size
    if size % 16:
        raise ValueError(
            f"{path}: {size} bytes is not a multiple of 16 (KITTI: float32 x, y, z, reflectance per point)"
        )
    points = np.fromfile(path, dtype="<f4").reshape(-1, 4)  # (N, 4)
    if points.size and not np.isfinite(points[:, :3]).all(axis=1).any():
        raise ValueError(f"{path}: none of its {len(points)} points has finite x, y, z")
    return Scan(scan_name(path), path, points, ("x", "y", "z", "intensity"), Spin.CCW)


def _nuscenes(path: Path) -> Scan:
    raw = np.fromfile(path, dtype="<f4")
    if raw.size % 5:
        raise ValueError(
            f"{path}: {raw.size} floats is not a multiple of 5 (nuScenes x, y, z, intensity, ring)"
        )
    p = raw.reshape(-1, 5)
    pts = np.stack([p[:, 1], -p[:, 0], p[:, 2], p[:, 3] / 255.0, p[:, 4]], axis=1).astype(np.float32)
    return Scan(scan_name(path), path, pts, ("x", "y", "z", "intensity", "ring"), Spin.CW)


def _native(path: Path) -> Scan:
    try:
        return _read_native(path)
    except ValueError as e:
        if str(e).startswith(str(path)):  # ours, naming the file already
            raise
        raise ValueError(f"{path}: not a readable native scan (.npz): {e}") from e
    except (OSError, EOFError, KeyError, zipfile.BadZipFile) as e:  # a corrupt or foreign file
        raise ValueError(f"{path}: not a readable native scan (.npz): {e}") from e


def _read_native(path: Path) -> Scan:
    with open(path, "rb") as file, np.load(file, allow_pickle=False) as f:  # closed also when np.load fails
        if "points" not in f or "fields" not in f:
            raise ValueError(f"{path}: a native scan needs arrays 'points' (N, C) and 'fields' (C,)")
        points = np.ascontiguousarray(f["points"], dtype=np.float32)
        fields = tuple(str(x) for x in f["fields"].tolist())
        spin = Spin(str(f["spin"])) if "spin" in f else Spin.CCW
        stamp = int(f["timestamp_ns"]) if "timestamp_ns" in f else None
        time = np.ascontiguousarray(f["time"], dtype=np.float32) if "time" in f else None
    if points.ndim != 2 or points.shape[1] != len(fields):
        raise ValueError(f"{path}: points {points.shape} do not match {len(fields)} fields {fields}")
    if time is not None and time.shape != (points.shape[0],):
        raise ValueError(f"{path}: time {time.shape} does not match {points.shape[0]} points")
    return Scan(scan_name(path), path, points, fields, spin, stamp, time)


def write_native_scan(
    path: Path,
    points: np.ndarray,
    fields: Sequence[str],
    spin: Spin = Spin.CCW,
    timestamp_ns: int | None = None,
    gt: GroundTruth | None = None,
    time: np.ndarray | None = None,
    label_fov: tuple[float, float] | None = None,
) -> None:
    """Write a native .npz scan: points float32 (N, C), fields (C,) names, spin, optional timestamp_ns,
    optional ground truth (stored as gt_boxes (M, 7) + gt_names (M,) from CLASS_NAMES; the point counts
    and difficulty are not stored, a reader recounts them), optional per-point time (N,) in seconds and
    optional label_fov (2,) (the azimuth range in radians the ground truth covers)."""
    points = np.ascontiguousarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != len(fields):
        raise ValueError(f"points {points.shape} do not match {len(fields)} fields {list(fields)}")
    arrays: dict[str, np.ndarray] = {
        "points": points,
        "fields": np.array(list(fields), dtype=np.str_),
        "spin": np.array(spin.value),
    }
    if timestamp_ns is not None:
        arrays["timestamp_ns"] = np.array(timestamp_ns, dtype=np.int64)
    if gt is not None:
        arrays["gt_boxes"] = np.asarray(gt.boxes, dtype=np.float32).reshape(-1, 7)
        arrays["gt_names"] = np.array([CLASS_NAMES[int(i)] for i in gt.labels], dtype=np.str_).reshape(-1)
    if time is not None:
        t = np.ascontiguousarray(time, dtype=np.float32)
        if t.shape != (points.shape[0],):
            raise ValueError(f"time {t.shape} does not match {points.shape[0]} points")
        arrays["time"] = t
    if label_fov is not None:
        arrays["label_fov"] = np.array(label_fov, dtype=np.float64).reshape(2)
    np.savez(path, **arrays)


# ---- labelled scans -----------------------------------------------------------------------------------


def sector_of_xy(x: np.ndarray, y: np.ndarray, sectors: int) -> np.ndarray:
    """(N,) x, y -> (N,) int64 sector index in [0, sectors); the numpy twin of
    `model.sectors.sector_of_points` (same float32 arithmetic for float32 input)."""
    theta = np.arctan2(y, x)  # [-pi, pi], the dtype of x and y
    k = np.floor((theta + math.pi) / (2 * math.pi / sectors)).astype(np.int64)
    return np.clip(k, 0, sectors - 1)


def model_columns(points: np.ndarray, fields: tuple[str, ...]) -> tuple[np.ndarray, tuple[str, ...]]:
    """Reorder (N, C) columns to x, y, z, intensity first (matched case-insensitively), the rest after."""
    lower = [f.lower() for f in fields]
    missing = [f for f in REQUIRED_FIELDS if f not in lower]
    if missing:
        raise ValueError(f"fields: {missing} not among the scan's fields {list(fields)}")
    first = [lower.index(f) for f in REQUIRED_FIELDS]
    order = first + [i for i in range(len(fields)) if i not in first]
    names = REQUIRED_FIELDS + tuple(fields[i] for i in order[len(REQUIRED_FIELDS) :])
    return np.ascontiguousarray(points[:, order], dtype=np.float32), names


def feature_columns(scan: LabeledScan, point_features: int) -> np.ndarray:
    """The scan's points as the model's columns x, y, z, intensity[, elongation] -> (N, max(point_features,
    4)): the four columns every sector carries at least (a model reading 3 leaves out the intensity)."""
    names = POINT_FIELDS[: max(point_features, len(REQUIRED_FIELDS))]
    cols = [
        scan.points[:, scan.fields.index(n)] if n in scan.fields else np.zeros(len(scan.points), np.float32)
        for n in names
    ]
    return np.stack(cols, axis=1).astype(np.float32)


def read_labeled(path: Path, sectors: int = DEFAULT_SECTORS, frame: FileFrame = AS_IS) -> LabeledScan:
    """A recorded scan with its ground truth: KITTI velodyne .bin (+ ../label_2, ../calib), nuScenes
    .pcd.bin (+ NAME_boxes.txt beside it) or native .npz (ground truth optional: empty without it).

    Points come with x, y, z, intensity first; `sector` is each point's sector of `sectors`. `frame`: how the
    file departs from its format's conventions (points and boxes are moved into the sensor's frame).
    """
    path = Path(path)
    scan = read_scan(path)
    points, fields = model_columns(scan.points, scan.fields)  # (N, C)
    if any(frame.origin):
        points = points.copy()
        points[:, :3] -= np.asarray(frame.origin, np.float32)
    boxes, labels, label_fov = labeled_targets(path, frame)
    gt = GroundTruth.from_boxes(boxes, labels, points)
    sector = sector_of_xy(points[:, 0], points[:, 1], sectors)  # (N,)
    return LabeledScan(scan.name, points, fields, gt, scan.time, sector, label_fov, scan.spin)


def write_labeled(path: Path, scan: LabeledScan, timestamp_ns: int | None = None) -> None:
    """Write a `LabeledScan` as a native .npz (points, fields, spin, ground truth, time, label_fov);
    `read_labeled` reads it back (point counts, difficulty and sectors are recomputed from the points)."""
    gt, time, fov = scan.gt, scan.time, scan.label_fov
    write_native_scan(
        path, scan.points, scan.fields, scan.spin, timestamp_ns, gt=gt, time=time, label_fov=fov
    )
