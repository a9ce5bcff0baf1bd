"""Recorded LiDAR scans on disk -> points with named columns, as the sensor fired them.

Formats (chosen by file name):
  - KITTI velodyne `*.bin`: float32 (N, 4) x, y, z, reflectance; x forward, y left, z up; spins CCW.
  - nuScenes `*.pcd.bin`: float32 (N, 5) x, y, z, intensity (0-255), ring in the LIDAR_TOP frame (x right,
    y forward); spins CW. Read into x forward, y left (rotated -90 degrees about z), intensity / 255.
  - native `*.npz` (see docs/protocol.md, "Native scan files"): `points` float32 (N, C) and `fields` (C,)
    column names starting x, y, z, intensity; optional `spin` ("ccw" | "cw") and `timestamp_ns`.
A drive is a folder of such files, replayed in name order.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clients.sectorizer import Spin

SCAN_SUFFIXES = (".bin", ".npz")


@dataclass(frozen=True)
class Scan:
    name: str  # file name without its suffixes
    path: Path
    points: np.ndarray  # (N, C) float32, columns named by `fields`, firing order
    fields: tuple[str, ...]
    spin: Spin
    timestamp_ns: int | None = None


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
        raw = np.fromfile(path, dtype="<f4")
        if raw.size % 4:
            raise ValueError(f"{path}: {raw.size} floats is not a multiple of 4 (KITTI x, y, z, reflectance)")
        return Scan(scan_name(path), path, raw.reshape(-1, 4), ("x", "y", "z", "intensity"), Spin.CCW)
    raise ValueError(f"{path}: unknown scan format; expected .bin (KITTI), .pcd.bin (nuScenes) or .npz")


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
    with np.load(path, allow_pickle=False) as f:
        if "points" not in f or "fields" not in f:
            raise ValueError(f"{path}: a native scan needs arrays 'points' (N, C) and 'fields' (C,)")
        points = np.ascontiguousarray(f["points"], dtype=np.float32)
        fields = tuple(str(x) for x in f["fields"].tolist())
        spin = Spin(str(f["spin"])) if "spin" in f else Spin.CCW
        stamp = int(f["timestamp_ns"]) if "timestamp_ns" in f else None
    if points.ndim != 2 or points.shape[1] != len(fields):
        raise ValueError(f"{path}: points {points.shape} do not match {len(fields)} fields {fields}")
    return Scan(scan_name(path), path, points, fields, spin, stamp)


def write_native_scan(
    path: Path,
    points: np.ndarray,
    fields: Sequence[str],
    spin: Spin = Spin.CCW,
    timestamp_ns: int | None = None,
) -> None:
    """Write a native .npz scan (points float32 (N, C), fields (C,) names, spin, optional timestamp_ns)."""
    arrays: dict[str, np.ndarray] = {
        "points": np.ascontiguousarray(points, dtype=np.float32),
        "fields": np.array(list(fields), dtype=np.str_),
        "spin": np.array(spin.value),
    }
    if timestamp_ns is not None:
        arrays["timestamp_ns"] = np.array(timestamp_ns, dtype=np.int64)
    np.savez(path, **arrays)
