"""Street layout: roads (lanes, parking, sidewalks), the ground (grade, bumps, crossfall) and the sidewalk
slabs with their curbs. What stands beside the roads is in frontage.py (by layout: urban, suburban, open).

Everything is in the sensor frame (x forward, y left, z up); the sensor sits on road 0. Right-hand traffic:
a road's forward lanes lie right of its centre line (negative lateral offset), oncoming lanes left of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lidar.sim.ground import ASPHALT, Ground
from lidar.sim.raycast import SolidList

SLAB_LENGTH = 6.0  # metres of sidewalk per slab (each sits level at the ground height of its centre)
SLAB_DEPTH = 0.5  # how far a slab reaches below the ground
LOT_DEPTH = 12.0  # raised ground behind the sidewalk (under buildings and in the gaps between them)
URBAN, SUBURBAN, OPEN = 0, 1, 2  # layouts (SceneConfig.layouts)
LAYOUT_NAMES = ("urban", "suburban", "open")


@dataclass(frozen=True)
class Road:
    origin: np.ndarray  # (2,) a point on the centre line
    yaw: float  # heading of the forward lanes
    lanes: int  # driving lanes per direction
    lane_width: float
    parking: tuple[bool, bool]  # a parking lane on the right, on the left
    parking_width: float
    sidewalk: float  # sidewalk width (m; a grass verge in open layouts)
    curb: float  # curb height (m)
    layout: int = URBAN
    lot: float = LOT_DEPTH  # raised ground behind the sidewalk (m)

    @property
    def u(self) -> np.ndarray:
        return np.array([math.cos(self.yaw), math.sin(self.yaw)])

    @property
    def n(self) -> np.ndarray:
        return np.array([-math.sin(self.yaw), math.cos(self.yaw)])

    def edge(self, side: int) -> float:
        """Lateral offset of the curb: side -1 right, +1 left."""
        park = self.parking[0] if side < 0 else self.parking[1]
        return side * (self.lanes * self.lane_width + park * self.parking_width)

    def back(self, side: int) -> float:
        """Lateral offset of the back of the sidewalk (where lots, yards and vegetation begin)."""
        return self.edge(side) + side * self.sidewalk

    def outward(self, side: int, s: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(K,) along, (K,) metres beyond the back of the sidewalk on `side` -> (K, 2) points."""
        return self.point(s, self.back(side) + side * np.asarray(d, np.float64))

    def point(self, s: np.ndarray, lateral: np.ndarray) -> np.ndarray:
        """(K,) along, (K,) lateral -> (K, 2) sensor-frame points."""
        s, lateral = np.asarray(s, np.float64), np.asarray(lateral, np.float64)
        return self.origin + s[..., None] * self.u + lateral[..., None] * self.n

    def local(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(..., 2) points -> along (...), lateral (...)."""
        d = np.asarray(xy) - self.origin
        return d @ self.u, d @ self.n

    def overlaps(self, xy: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(K, C, 2) corner sets (or (K, 2) points) -> (K,) bool: touches the carriageway grown by margin."""
        _, lat = self.local(xy)
        lat = lat.reshape(len(lat), -1)
        return (lat.min(axis=1) <= self.edge(1) + margin) & (lat.max(axis=1) >= self.edge(-1) - margin)


def footprint(centre: np.ndarray, length: np.ndarray, width: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(K, 2) centres, (K,) sizes and headings -> (K, 4, 2) corners."""
    signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], np.float64) / 2  # (4, 2)
    lx, ly = signs[:, 0] * np.asarray(length)[:, None], signs[:, 1] * np.asarray(width)[:, None]  # (K, 4)
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    return np.stack([centre[:, None, 0] + lx * c - ly * s, centre[:, None, 1] + lx * s + ly * c], axis=-1)


class Occupancy:
    """Discs already taken on the ground plane; new objects must not overlap them."""

    def __init__(self) -> None:
        self.xy = np.zeros((0, 2))  # (D, 2)
        self.r = np.zeros(0)  # (D,)

    def free(self, xy: np.ndarray, r: np.ndarray) -> bool:
        """(K, 2) discs of one object, (K,) radii -> whether none overlaps a taken disc."""
        if len(self.r) == 0:
            return True
        d = np.hypot(xy[:, None, 0] - self.xy[None, :, 0], xy[:, None, 1] - self.xy[None, :, 1])  # (K, D)
        return bool(np.all(d >= r[:, None] + self.r[None, :]))

    def take(self, xy: np.ndarray, r: np.ndarray) -> None:
        self.xy = np.concatenate([self.xy, xy.reshape(-1, 2)])
        self.r = np.concatenate([self.r, np.asarray(r, np.float64).reshape(-1)])


def clear_of(others: list[Road], corners: np.ndarray, margin: float = 0.5) -> np.ndarray:
    """(K, C, 2) footprints -> (K,) bool: off the carriageways and sidewalks (grown by margin) of `others`."""
    keep = np.ones(len(corners), bool)
    for o in others if len(corners) else ():
        keep &= ~o.overlaps(corners, margin=o.sidewalk + margin)
    return keep


def disc_corners(xy: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(K, 2) centres, (K,) radii -> (K, 4, 2) corners of their bounding squares."""
    signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], np.float64)  # (4, 2)
    return xy[:, None, :] + signs[None] * np.asarray(r, np.float64).reshape(-1, 1, 1)


def ground_z(ground: Ground, road: Road, xy: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(K, 2) points `d` (K,) metres beyond the back of a sidewalk -> (K,) ground z (raised on the lot)."""
    z = ground.height_at(xy[:, 0], xy[:, 1])
    return z + np.where(np.asarray(d) < road.lot, road.curb, 0.0)


def make_ground(
    rng: np.random.Generator,
    height: float,
    max_slope: float,
    bump: float,
    roads: list[Road],
    crossfall: tuple[float, float] = (0.0, 0.0),
) -> Ground:
    """A plane of slope up to `max_slope`, three long bumps of up to `bump` metres, the roads' lane lines and
    a crossfall drawn from `crossfall` on road 0 (it falls from the centre line to both curbs)."""
    slope = rng.uniform(0, max_slope) * np.array([math.cos(a := rng.uniform(0, 2 * math.pi)), math.sin(a)])
    wavelength = rng.uniform(20.0, 60.0, 3)  # metres
    heading = rng.uniform(0, 2 * math.pi, 3)
    wave = (2 * math.pi / wavelength)[:, None] * np.stack([np.cos(heading), np.sin(heading)], 1)  # (3, 2)
    lines, road0 = [], roads[0]
    for i, road in enumerate(roads):
        gap = _crossing_gap(road, [r for j, r in enumerate(roads) if j != i])
        lines.append([*road.origin, *road.u, road.lane_width, road.lanes, *gap])
    return Ground(
        height=height,
        slope=slope,
        amplitude=rng.uniform(0, bump, 3),
        wave=wave,
        phase=rng.uniform(0, 2 * math.pi, 3),
        asphalt=float(rng.uniform(*ASPHALT)),
        lines=np.asarray(lines, np.float64).reshape(-1, 8),
        crowns=np.array([[*road0.origin, *road0.u, rng.uniform(*crossfall), road0.edge(-1), road0.edge(1)]]),
    )


def _crossing_gap(road: Road, others: list[Road]) -> tuple[float, float]:
    """Along-road interval of `road` where another road crosses it (no lane lines there), or empty."""
    return crossing_span(road, others[0], 2.0) if others else (0.0, 0.0)


def crossing_span(road: Road, other: Road, margin: float) -> tuple[float, float]:
    """Along-road interval of `road` covered by the carriageway of the crossing `other`, grown by margin."""
    s, _ = road.local(other.origin[None])
    reach = max(-other.edge(-1), other.edge(1)) / max(abs(math.sin(other.yaw - road.yaw)), 0.3)
    return float(s[0] - reach - margin), float(s[0] + reach + margin)


def sidewalks(
    solids: SolidList, rng: np.random.Generator, roads: list[Road], ground: Ground, reach: float
) -> None:
    """Raised slabs (sidewalk + lot behind it) along both sides of every road; their road sides are curbs."""
    for i, road in enumerate(roads):
        others = [r for j, r in enumerate(roads) if j != i]
        s = np.arange(-reach, reach, SLAB_LENGTH) + SLAB_LENGTH / 2  # (K,)
        width = road.sidewalk + road.lot
        for side in (-1, 1):
            centre = road.point(s, np.full_like(s, road.edge(side) + side * width / 2))  # (K, 2)
            yaw = np.full(len(s), road.yaw)
            corners = footprint(centre, np.full(len(s), SLAB_LENGTH), np.full(len(s), width), yaw)
            keep = ~np.any([o.overlaps(corners) for o in others], axis=0) if others else np.ones(len(s), bool)
            top = ground.height_at(centre[keep, 0], centre[keep, 1]) + road.curb
            refl = rng.uniform(0.25, 0.45, int(keep.sum()))
            solids.boxes(centre[keep], top - road.curb - SLAB_DEPTH, top, SLAB_LENGTH, width, road.yaw, refl)
