"""Street layout: roads (lanes, parking, sidewalks), the ground, sidewalk slabs with curbs, buildings, and
static clutter (poles, signs, trees, bushes, bins, hydrants, bollards, parked bicycles).

Everything is in the sensor frame (x forward, y left, z up); the sensor sits on road 0. Right-hand traffic:
a road's forward lanes lie right of its centre line (negative lateral offset), oncoming lanes left of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from model.data.sim.ground import ASPHALT, Ground
from model.data.sim.raycast import SolidList

SLAB_LENGTH = 6.0  # metres of sidewalk per slab (each sits level at the ground height of its centre)
SLAB_DEPTH = 0.5  # how far a slab reaches below the ground
LOT_DEPTH = 12.0  # raised ground behind the sidewalk (under buildings and in the gaps between them)


@dataclass(frozen=True)
class Road:
    origin: np.ndarray  # (2,) a point on the centre line
    yaw: float  # heading of the forward lanes
    lanes: int  # driving lanes per direction
    lane_width: float
    parking: tuple[bool, bool]  # a parking lane on the right, on the left
    parking_width: float
    sidewalk: float  # sidewalk width (m)
    curb: float  # curb height (m)

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


def make_ground(
    rng: np.random.Generator, height: float, max_slope: float, bump: float, roads: list[Road]
) -> Ground:
    """A plane of slope up to `max_slope`, three long bumps of up to `bump` metres, the roads' lane lines."""
    slope = rng.uniform(0, max_slope) * np.array([math.cos(a := rng.uniform(0, 2 * math.pi)), math.sin(a)])
    wavelength = rng.uniform(20.0, 60.0, 3)  # metres
    heading = rng.uniform(0, 2 * math.pi, 3)
    wave = (2 * math.pi / wavelength)[:, None] * np.stack([np.cos(heading), np.sin(heading)], 1)  # (3, 2)
    lines = []
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
        width = road.sidewalk + LOT_DEPTH
        for side in (-1, 1):
            centre = road.point(s, np.full_like(s, road.edge(side) + side * width / 2))  # (K, 2)
            yaw = np.full(len(s), road.yaw)
            corners = footprint(centre, np.full(len(s), SLAB_LENGTH), np.full(len(s), width), yaw)
            keep = ~np.any([o.overlaps(corners) for o in others], axis=0) if others else np.ones(len(s), bool)
            top = ground.height_at(centre[keep, 0], centre[keep, 1]) + road.curb
            refl = rng.uniform(0.25, 0.45, int(keep.sum()))
            solids.boxes(centre[keep], top - road.curb - SLAB_DEPTH, top, SLAB_LENGTH, width, road.yaw, refl)


def buildings(
    solids: SolidList, rng: np.random.Generator, roads: list[Road], ground: Ground, reach: float
) -> None:
    """Rows of buildings (walls facing the street) behind the sidewalks, with gaps, fences and hedges."""
    for i, road in enumerate(roads):
        others = [r for j, r in enumerate(roads) if j != i]
        for side in (-1, 1):
            s = -reach + rng.uniform(0, 10)
            while s < reach:
                length, gap = rng.uniform(8, 40), rng.uniform(0, 14) * (rng.random() < 0.6)
                setback, depth = rng.uniform(0, 4), rng.uniform(8, 20)
                lateral = road.edge(side) + side * (road.sidewalk + setback + depth / 2)
                c = road.point(np.array([s + length / 2]), np.array([lateral]))  # (1, 2)
                box = footprint(c, np.array([length]), np.array([depth]), np.array([road.yaw]))
                if not any(o.overlaps(box, margin=o.sidewalk + 1)[0] for o in others):
                    z = ground.height_at(c[:, 0], c[:, 1])
                    solids.boxes(
                        c, z - 1, z + rng.uniform(3, 25), length, depth, road.yaw, rng.uniform(0.15, 0.6)
                    )
                if gap > 2:
                    _fill_gap(solids, rng, road, side, s + length, gap, ground, others)
                s += length + gap


def _fill_gap(
    solids: SolidList,
    rng: np.random.Generator,
    road: Road,
    side: int,
    s: float,
    gap: float,
    ground: Ground,
    others: list[Road],
) -> None:
    """A fence or a hedge along the building line of a gap between buildings (or nothing)."""
    pick = rng.random()
    if pick > 0.6:
        return
    hedge = pick < 0.3
    thick, height = (rng.uniform(0.6, 1.2), rng.uniform(0.8, 1.6)) if hedge else (0.1, rng.uniform(1.0, 2.2))
    lateral = road.edge(side) + side * (road.sidewalk + rng.uniform(0.2, 1.5) + thick / 2)
    c = road.point(np.array([s + gap / 2]), np.array([lateral]))
    box = footprint(c, np.array([gap]), np.array([thick]), np.array([road.yaw]))
    if any(o.overlaps(box, margin=1.0)[0] for o in others):
        return
    z = ground.height_at(c[:, 0], c[:, 1]) + road.curb
    refl, porosity = (rng.uniform(0.35, 0.6), 0.35) if hedge else (rng.uniform(0.2, 0.5), 0.3)
    solids.boxes(c, z - 0.2, z + height, gap, thick, road.yaw, refl, porosity)
