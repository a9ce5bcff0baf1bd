"""Cut LiDAR data into the model's azimuth sectors (numpy only: clients and the server's ROS 2 bridge use it).

Sector k of K covers azimuth [-pi + k * 2pi/K, -pi + (k + 1) * 2pi/K), azimuth = atan2(y, x) in the sensor
frame (x forward, y left, z up), the same split as the model's polar grid (`model.sectors`).

- `split_scan`: a whole recorded turn -> its K sectors in sweep order (starting with the sector the scan
  starts in, following the spin), points of each sector in their original (firing) order.
- `StreamSectorizer`: points or packets as the sensor turns -> each sector as soon as the azimuth crosses
  into the next one. Works for either spin direction and across the +-180 degree wrap.

Both take points with any column order, declared by name, and return float32 (N, len(output_fields)) arrays
in the model's order (x, y, z, intensity by default). Every input point lands in exactly one sector.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from contract import REQUIRED_FIELDS
from lidar.readers import Spin


@dataclass(frozen=True)
class Sector:
    index: int  # sector within the turn, 0..K-1 (by azimuth, see module docstring)
    turn: int  # turns started so far by this sectorizer (0 for the first)
    points: np.ndarray  # (N, C) float32 in `output_fields` order


def column_picker(fields: Sequence[str], output_fields: Sequence[str] = REQUIRED_FIELDS) -> list[int]:
    """Column index of every output field in the input; ValueError naming a missing or duplicate field."""
    names = [f.lower() for f in fields]
    if len(set(names)) != len(names):
        raise ValueError(f"fields: duplicate names in {list(fields)}")
    missing = [f for f in output_fields if f.lower() not in names]
    if missing:
        raise ValueError(f"fields: {missing} not among the declared fields {list(fields)}")
    return [names.index(f.lower()) for f in output_fields]


def sector_of_azimuth(azimuth: np.ndarray, sectors: int) -> np.ndarray:
    """(N,) azimuth in radians (any range) -> (N,) int64 sector index in [0, sectors)."""
    wrapped = np.mod(azimuth + math.pi, 2 * math.pi)  # [0, 2pi)
    return np.minimum((wrapped / (2 * math.pi / sectors)).astype(np.int64), sectors - 1)


def detect_spin(azimuth: np.ndarray) -> Spin:
    """Spin direction from consecutive azimuths in firing order (median of wrapped differences)."""
    if azimuth.size < 2:
        raise ValueError("azimuth: need at least 2 points to tell the spin direction")
    step = np.angle(np.exp(1j * np.diff(azimuth.astype(np.float64))))  # wrapped to (-pi, pi]
    return Spin.CCW if float(np.median(step)) >= 0 else Spin.CW


def _select(points: np.ndarray, columns: list[int]) -> np.ndarray:
    if points.ndim != 2:
        raise ValueError(f"points: shape {points.shape}; expected 2-D (N, C)")
    return np.ascontiguousarray(points[:, columns], dtype=np.float32)


def split_scan(
    points: np.ndarray,
    fields: Sequence[str],
    sectors: int = 4,
    spin: Spin = Spin.CCW,
    output_fields: Sequence[str] = REQUIRED_FIELDS,
) -> list[Sector]:
    """A whole turn (N, C) -> `sectors` Sectors in sweep order, first the one holding the first point.

    Every point is in exactly one sector, in its original order; sectors without points are empty.
    """
    cols = column_picker(fields, output_fields)
    out = _select(points, cols)
    xi, yi = column_picker(fields, ("x", "y"))
    k = sector_of_azimuth(np.arctan2(points[:, yi], points[:, xi]), sectors)  # (N,)
    first = int(k[0]) if k.size else 0
    step = 1 if spin is Spin.CCW else -1
    order = [(first + step * i) % sectors for i in range(sectors)]
    return [Sector(index=s, turn=0, points=out[k == s]) for s in order]


class StreamSectorizer:
    """Points in firing order, packet by packet -> Sectors, each emitted once the sweep has left it.

    A point in the next sector (in spin order) closes the current one. A point that lands in the previous
    sector (beam azimuth offsets jitter around a boundary) stays in the current sector, so nothing is lost
    or sent twice. A jump over several sectors (dropped packets) emits the skipped sectors empty, so the
    server sees the sweep as it happened. When azimuths are computed from x, y, points closer than
    `min_range` (ego-vehicle returns, whose azimuth means nothing) follow the points before them.
    """

    def __init__(
        self,
        fields: Sequence[str],
        sectors: int = 4,
        spin: Spin = Spin.CCW,
        output_fields: Sequence[str] = REQUIRED_FIELDS,
        min_range: float = 1.0,
    ):
        if sectors < 1:
            raise ValueError(f"sectors: {sectors}; expected >= 1")
        self.sectors = sectors
        self.spin = spin
        self.min_range = min_range
        self._cols = column_picker(fields, output_fields)
        self._xy = column_picker(fields, ("x", "y"))
        self._width = len(self._cols)
        self._current: int | None = None
        self._first = 0  # the sector the data started in: coming back to it starts a new turn
        self._turn = 0
        self._pending: list[np.ndarray] = []

    def _ahead(self, k: int) -> int:
        """Sectors from the current one to k in spin order, 0..K-1."""
        assert self._current is not None
        diff = k - self._current if self.spin is Spin.CCW else self._current - k
        return diff % self.sectors

    def _close(self) -> Sector:
        assert self._current is not None
        pts = np.concatenate(self._pending) if self._pending else np.zeros((0, self._width), np.float32)
        self._pending = []
        return Sector(index=self._current, turn=self._turn, points=pts)

    def _advance(self, steps: int) -> list[Sector]:
        """Close the current sector, emit steps - 1 skipped ones empty, open the next."""
        out = [self._close()]
        step = 1 if self.spin is Spin.CCW else -1
        for _ in range(steps):
            assert self._current is not None
            self._current = (self._current + step) % self.sectors
            if self._current == self._first:
                self._turn += 1
            if len(out) < steps:
                out.append(self._close())
        return out

    def push(self, points: np.ndarray, azimuth: np.ndarray | None = None) -> list[Sector]:
        """Add points (N, C) in firing order (azimuth (N,) radians, default atan2(y, x)) -> closed Sectors."""
        if points.shape[0] == 0:
            return []
        data = _select(points, self._cols)
        if azimuth is None:
            k = self._sectors_from_xy(points[:, self._xy[0]], points[:, self._xy[1]])
            if k is None:  # only near points so far: they wait for the first far one
                self._pending.append(data)
                return []
        elif azimuth.shape != (points.shape[0],):
            raise ValueError(f"azimuth: shape {azimuth.shape}; expected ({points.shape[0]},)")
        else:
            k = sector_of_azimuth(azimuth, self.sectors)
        if self._current is None:
            self._current = self._first = int(k[0])
        emitted: list[Sector] = []
        start = 0
        changes = np.flatnonzero(np.diff(k)) + 1  # where the sector id changes: candidates for a crossing
        for i in changes if k[0] == self._current else np.concatenate([[0], changes]):
            ahead = self._ahead(int(k[i]))
            if ahead == 0 or (self.sectors > 2 and ahead == self.sectors - 1):  # jitter back: stay
                continue
            self._pending.append(data[start:i])
            start = i
            emitted += self._advance(ahead)
        self._pending.append(data[start:])
        return emitted

    def _sectors_from_xy(self, x: np.ndarray, y: np.ndarray) -> np.ndarray | None:
        """(N,) sector of every point; near points take the sector of the last far point before them."""
        k = sector_of_azimuth(np.arctan2(y, x), self.sectors)
        far = np.hypot(x, y) >= self.min_range
        if not far.any():
            return None if self._current is None else np.full(k.shape, self._current)
        last_far = np.maximum.accumulate(np.where(far, np.arange(k.size), -1))  # (N,)
        before = k[int(np.argmax(far))] if self._current is None else self._current
        return np.where(last_far >= 0, k[np.maximum(last_far, 0)], before)

    def flush(self) -> list[Sector]:
        """The open sector (end of the data), if any points are in it."""
        if self._current is None or not any(p.shape[0] for p in self._pending):
            return []
        return [self._close()]
