"""Ground-truth boxes of recorded scans, in the frame the clients read the scans in (to draw beside the
predictions).

KITTI: label_2 boxes are in the rectified camera frame with (x, y, z) the bottom centre; with calib R0_rect
and Tr_velo_to_cam: centre_velo = inv(R0 · Tr) · (x, y − h/2, z, 1), yaw_velo = −ry − π/2, dims (l, w, h).
nuScenes: see `nuscenes_labels_for`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

IGNORED = ("DontCare",)


@dataclass(frozen=True)
class LabelBoxes:
    boxes: np.ndarray  # (M, 7) float32 x, y, z, l, w, h, yaw in the velodyne frame (box centre)
    names: tuple[str, ...]  # (M,) KITTI class names


def read_calib(path: Path) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for line in Path(path).read_text().splitlines():
        if ":" in line:
            key, values = line.split(":", 1)
            if values.strip():
                out[key.strip()] = np.array([float(v) for v in values.split()], dtype=np.float64)
    return out


def velo_from_rect(calib: dict[str, np.ndarray]) -> np.ndarray:
    """(4, 4) transform from the rectified camera frame to the velodyne frame: inv(R0 · Tr)."""
    r0 = np.eye(4)
    r0[:3, :3] = calib["R0_rect"].reshape(3, 3)
    tr = np.eye(4)
    tr[:3, :4] = calib["Tr_velo_to_cam"].reshape(3, 4)
    return np.linalg.inv(r0 @ tr)


def read_kitti_labels(label_path: Path, calib_path: Path) -> LabelBoxes:
    m = velo_from_rect(read_calib(calib_path))
    boxes, names = [], []
    for line in Path(label_path).read_text().splitlines():
        parts = line.split()
        if len(parts) < 15 or parts[0] in IGNORED:
            continue
        h, w, length, x, y, z, ry = (float(v) for v in parts[8:15])
        centre = m @ np.array([x, y - h / 2, z, 1.0])
        boxes.append([centre[0], centre[1], centre[2], length, w, h, -ry - math.pi / 2])
        names.append(parts[0])
    arr = np.array(boxes, dtype=np.float32).reshape(-1, 7)
    return LabelBoxes(arr, tuple(names))


def kitti_labels_for(scan_path: Path) -> LabelBoxes | None:
    """The labels of a KITTI velodyne scan (…/velodyne/NAME.bin -> …/label_2/NAME.txt + …/calib/NAME.txt)."""
    scan_path = Path(scan_path)
    root, name = scan_path.parent.parent, scan_path.name.split(".")[0]
    label, calib = root / "label_2" / f"{name}.txt", root / "calib" / f"{name}.txt"
    if not (label.is_file() and calib.is_file()):
        return None
    return read_kitti_labels(label, calib)


def nuscenes_labels_for(scan_path: Path) -> LabelBoxes | None:
    """The boxes of a nuScenes LIDAR_TOP sweep (NAME.pcd.bin -> NAME_boxes.txt beside it), turned into the
    frame `clients.recordings` reads the sweep in (x forward, y left: x' = y, y' = -x, yaw' = yaw - pi/2).

    The boxes file: `class x y z l w h yaw ...` per line, box centres in the LIDAR_TOP frame (x right,
    y forward), yaw counter-clockwise from +x; `#` starts a comment; class `ignore` is skipped.
    """
    scan_path = Path(scan_path)
    boxes_path = scan_path.with_name(scan_path.name.removesuffix(".pcd.bin") + "_boxes.txt")
    if not boxes_path.is_file():
        return None
    boxes, names = [], []
    for line in boxes_path.read_text().splitlines():
        parts = line.split()
        if not parts or parts[0].startswith("#") or parts[0] == "ignore":
            continue
        x, y, z, length, w, h, yaw = (float(v) for v in parts[1:8])
        boxes.append([y, -x, z, length, w, h, yaw - math.pi / 2])
        names.append(parts[0])
    return LabelBoxes(np.array(boxes, dtype=np.float32).reshape(-1, 7), tuple(names))


def labels_for(scan_path: Path) -> LabelBoxes | None:
    """Ground-truth boxes beside a recorded scan, if any (KITTI label_2 + calib, nuScenes boxes file)."""
    scan_path = Path(scan_path)
    if scan_path.name.endswith(".pcd.bin"):
        return nuscenes_labels_for(scan_path)
    return kitti_labels_for(scan_path) if scan_path.suffix == ".bin" else None
