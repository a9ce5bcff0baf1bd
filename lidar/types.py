"""Labelled scans: the one shape every data source (simulator, KITTI, nuScenes, native files) yields.

Frame: the sensor frame, x forward, y left, z up (metres). Boxes are (x, y, z, l, w, h, yaw): z the box
centre, l along the heading, yaw counter-clockwise from +x (radians), as `model.geometry.boxes`.
Classes are indices into `model.config.CLASS_NAMES` (VEHICLE, PEDESTRIAN, CYCLIST).
Difficulty follows Waymo: a box with at most `LEVEL_2_MAX_POINTS` points is LEVEL_2, and a box with no
point at all is not a target (evaluation drops it).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

CLASS_NAMES: tuple[str, ...] = ("VEHICLE", "PEDESTRIAN", "CYCLIST")  # the classes labels and models use
DEFAULT_SECTORS = 4  # sectors per turn unless a reader is told otherwise (the model's default too)

LEVEL_1 = 1
LEVEL_2 = 2
LEVEL_2_MAX_POINTS = 5


@dataclass(frozen=True)
class GroundTruth:
    boxes: np.ndarray  # (M, 7) float32 x, y, z, l, w, h, yaw
    labels: np.ndarray  # (M,) int64 index into CLASS_NAMES
    num_points: np.ndarray  # (M,) int64 points of the scan inside each box
    difficulty: np.ndarray  # (M,) int8 LEVEL_1 or LEVEL_2

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    @staticmethod
    def empty() -> GroundTruth:
        return GroundTruth(
            np.zeros((0, 7), np.float32), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int8)
        )

    @staticmethod
    def from_boxes(boxes: np.ndarray, labels: np.ndarray, points: np.ndarray) -> GroundTruth:
        """Counts each box's points in `points` (N, >=3) and sets Waymo's difficulty from the count."""
        boxes = np.asarray(boxes, np.float32).reshape(-1, 7)
        counts = points_in_boxes(points[:, :3], boxes).sum(axis=0).astype(np.int64)  # (M,)
        return GroundTruth(boxes, np.asarray(labels, np.int64), counts, difficulty_of(counts))

    def select(self, keep: np.ndarray) -> GroundTruth:
        return GroundTruth(self.boxes[keep], self.labels[keep], self.num_points[keep], self.difficulty[keep])


class Spin(enum.StrEnum):
    CCW = "ccw"  # azimuth increases with time (seen from above): Velodyne/KITTI, Waymo
    CW = "cw"  # azimuth decreases with time: e.g. nuScenes LIDAR_TOP

    def order(self, sectors: int, first: int = 0) -> list[int]:
        """The sector indices a sweep starting in sector `first` passes, in time order."""
        step = 1 if self is Spin.CCW else -1
        return [(first + step * i) % sectors for i in range(sectors)]


@dataclass(frozen=True)
class LabeledScan:
    name: str
    points: np.ndarray  # (N, C) float32, columns `fields` (x, y, z, intensity first), firing order
    fields: tuple[str, ...]
    gt: GroundTruth
    time: np.ndarray | None = None  # (N,) float32 seconds since the turn began, when known
    sector: np.ndarray | None = None  # (N,) int64 each point's sector (model.sectors.sector_of_points)
    # the azimuth range [lo, hi) in radians the labels cover (KITTI: the front camera); None: all around
    label_fov: tuple[float, float] | None = None
    spin: Spin = Spin.CCW  # the sweep's direction: the order its sectors come in


@dataclass(frozen=True)
class Predictions:
    """Detected boxes of one scan (or one partial turn), numpy, sorted by descending score."""

    boxes: np.ndarray  # (K, 7) float32
    scores: np.ndarray  # (K,) float32
    labels: np.ndarray  # (K,) int64 index into CLASS_NAMES

    def __len__(self) -> int:
        return int(self.labels.shape[0])


def difficulty_of(num_points: np.ndarray) -> np.ndarray:
    """(M,) points per box -> (M,) int8 LEVEL_1, or LEVEL_2 for at most LEVEL_2_MAX_POINTS points."""
    return np.where(np.asarray(num_points) <= LEVEL_2_MAX_POINTS, LEVEL_2, LEVEL_1).astype(np.int8)


def points_in_boxes(xyz: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(N, 3) points, (M, 7) boxes -> (N, M) bool: point inside box (borders included).

    Points are sorted by x once; each box then tests only the points whose x lies within its circumscribed
    radius (plus a margin), with the same float64 arithmetic as a dense test, so the result is identical.
    """
    inside = np.zeros((len(xyz), len(boxes)), bool)
    if len(boxes) == 0 or len(xyz) == 0:
        return inside
    cos, sin = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])  # (M,)
    half_l, half_w, half_h = boxes[:, 3] / 2, boxes[:, 4] / 2, boxes[:, 5] / 2  # (M,)
    reach = np.hypot(boxes[:, 3].astype(np.float64), boxes[:, 4]) / 2 + 1e-3  # (M,) conservative
    order = np.argsort(xyz[:, 0])  # (N,) NaN x sorts last and is never a candidate
    xs, ys = xyz[order, 0].astype(np.float64), xyz[order, 1].astype(np.float64)  # (N,) each
    lo = np.searchsorted(xs, boxes[:, 0] - reach, side="left")  # (M,)
    hi = np.searchsorted(xs, boxes[:, 0] + reach, side="right")  # (M,)
    for j in np.flatnonzero(hi > lo):
        near = np.flatnonzero(np.abs(ys[lo[j] : hi[j]] - boxes[j, 1]) <= reach[j])  # NaN y: never
        idx = order[lo[j] + near]  # (K,) candidates
        d = xyz[idx].astype(np.float64) - boxes[j, :3]  # (K, 3)
        u = d[:, 0] * cos[j] + d[:, 1] * sin[j]  # along the heading
        v = -d[:, 0] * sin[j] + d[:, 1] * cos[j]  # across it
        hit = (np.abs(u) <= half_l[j]) & (np.abs(v) <= half_w[j]) & (np.abs(d[:, 2]) <= half_h[j])  # (K,)
        inside[idx[hit], j] = True
    return inside
