"""What stands beside the roads, by layout (docs/simulator.md):

- urban: near-continuous building fronts (facades.py) with a few gaps holding hedges, fences or walls, and
  rows of street trees along the curbs;
- suburban: detached houses set back behind front yards, property lines of hedges, fences or walls broken by
  driveways (some with a parked car: `Slots`), bushes and trees in the yards, wheelie bins at the driveways;
- open: belts of vegetation (hedgerows, forest edges, tree rows) beyond a grass verge, fields behind fences,
  now and then a farm building.

Nothing here stands on another road or its sidewalks (boundaries.free_runs, layout.clear_of).
"""

from __future__ import annotations

import math

import numpy as np

from lidar.sim import boundaries, vegetation
from lidar.sim.facades import HOUSE_FACADE, URBAN_FACADE, Front, building
from lidar.sim.ground import Ground
from lidar.sim.layout import OPEN, SUBURBAN, Occupancy, Road, clear_of, disc_corners, footprint, ground_z
from lidar.sim.parts import BUILDING, FURNITURE, TaggedSolidList

OPEN_KINDS = (0.45, 0.33, 0.1, 0.12)  # chances of a hedgerow, forest edge, tree row, field per stretch
Slots = np.ndarray  # (K, 5) driveway places for a parked car: x, y, ground z, heading, room (m of length)


def frontage(
    solids: TaggedSolidList,
    occ: Occupancy,
    rng: np.random.Generator,
    roads: list[Road],
    ground: Ground,
    reach: float,
) -> Slots:
    """Both sides of every road, built by its layout; returns the driveway slots (suburban)."""
    slots = [np.zeros((0, 5))]
    for i, road in enumerate(roads):
        others = tuple(r for j, r in enumerate(roads) if j != i)
        for side in (-1, 1):
            if road.layout == SUBURBAN:
                slots.append(_suburban(solids, occ, rng, road, side, others, ground, reach))
            elif road.layout == OPEN:
                _open(solids, rng, road, side, others, ground, reach)
            else:
                _urban(solids, occ, rng, road, side, others, ground, reach)
    return np.concatenate(slots)


def _fits(
    road: Road, side: int, others: tuple[Road, ...], s: tuple[float, float], d: tuple[float, float]
) -> bool:
    """Whether the rectangle s[0]..s[1] x d[0]..d[1] beyond the sidewalk keeps clear of the other roads."""
    c = road.outward(side, np.array([(s[0] + s[1]) / 2]), np.array([(d[0] + d[1]) / 2]))
    box = footprint(c, np.array([s[1] - s[0]]), np.array([d[1] - d[0]]), np.array([road.yaw]))
    return bool(clear_of(list(others), box, margin=1.0)[0])


def _urban(
    solids: TaggedSolidList,
    occ: Occupancy,
    rng: np.random.Generator,
    road: Road,
    side: int,
    others: tuple[Road, ...],
    ground: Ground,
    reach: float,
) -> None:
    """Building fronts with few gaps; hedges, fences or walls in some gaps; maybe a row of street trees."""
    s = -reach + rng.uniform(0, 10)
    while s < reach:
        length, gap = rng.uniform(8, 40), rng.uniform(2, 14) * (rng.random() < 0.35)
        setback = rng.uniform(0, 2.5) if rng.random() < 0.75 else rng.uniform(2.5, 6)
        depth = rng.uniform(10, 20)
        if _fits(road, side, others, (s, s + length), (setback, setback + depth)):
            floors = int(rng.integers(1, 8))
            building(
                solids, rng, Front(road, side, (s, s + length), setback, depth), ground, floors, URBAN_FACADE
            )
        if gap > 2:
            d = rng.uniform(0.3, 1.5)
            for run in boundaries.free_runs(road, side, others, (s + length, s + length + gap), (d, d + 1.5)):
                boundaries.boundary(solids, rng, road, side, run, d, ground, boundaries.pick_kind(rng))
        s += length + gap
    if rng.random() < 0.5:
        _street_trees(solids, occ, rng, road, side, others, ground, reach)


def _street_trees(
    solids: TaggedSolidList,
    occ: Occupancy,
    rng: np.random.Generator,
    road: Road,
    side: int,
    others: tuple[Road, ...],
    ground: Ground,
    reach: float,
) -> None:
    """A row of trees in pits along the curb, 6-14 m apart."""
    s = -reach + np.cumsum(rng.uniform(6, 14, int(2 * reach / 6) + 1))
    s = s[s < reach]
    xy = road.point(s, np.full(len(s), road.edge(side) + side * rng.uniform(0.5, 0.9)))
    keep = clear_of(list(others), disc_corners(xy, np.full(len(s), 1.0)))
    keep &= np.array([occ.free(p[None], np.array([0.6])) for p in xy], bool)
    xy = xy[keep]
    z = ground.height_at(xy[:, 0], xy[:, 1]) + road.curb
    trunks = vegetation.trees(solids, rng, xy, z, vegetation.STREET_TREE)
    occ.take(xy, trunks + 0.3)


def _suburban(
    solids: TaggedSolidList,
    occ: Occupancy,
    rng: np.random.Generator,
    road: Road,
    side: int,
    others: tuple[Road, ...],
    ground: Ground,
    reach: float,
) -> Slots:
    """Lots of 12-28 m: a house behind a front yard, a property line broken by a driveway."""
    slots, s = [], -reach + rng.uniform(0, 8)
    while s < reach:
        lot, setback = rng.uniform(12, 28), rng.uniform(4, 12)
        depth = rng.uniform(8, 12)
        if _fits(road, side, others, (s, s + lot), (0.0, setback + depth)):
            slots.extend(_lot(solids, occ, rng, road, side, (s, s + lot), setback, depth, ground))
        s += lot
    return np.asarray(slots, np.float64).reshape(-1, 5)


def _lot(
    solids: TaggedSolidList,
    occ: Occupancy,
    rng: np.random.Generator,
    road: Road,
    side: int,
    s: tuple[float, float],
    setback: float,
    depth: float,
    ground: Ground,
) -> list[list[float]]:
    """One suburban lot -> its driveway slot (none or one)."""
    lot = s[1] - s[0]
    house = rng.uniform(8, min(16, lot - 4))
    h0 = s[0] + rng.uniform(0.5, lot - house - 0.5)
    floors = int(rng.integers(1, 3))
    top = building(
        solids, rng, Front(road, side, (h0, h0 + house), setback, depth), ground, floors, HOUSE_FACADE
    )
    _roof(solids, rng, road, side, (h0, h0 + house), (setback, setback + depth), ground, top)
    line = rng.uniform(0.3, 0.8)
    kind = boundaries.pick_kind(rng)
    width = rng.uniform(3.0, 3.8)
    left, right = h0 - s[0], s[1] - h0 - house  # room beside the house
    drive = rng.random() < 0.8
    a = s[0] + rng.uniform(0.3, max(0.4, left - width)) if left > right else h0 + house + 0.3
    a = min(a, s[1] - width - 0.3)
    if not drive:
        boundaries.boundary(solids, rng, road, side, s, line, ground, kind)
    else:
        boundaries.boundary(solids, rng, road, side, (s[0], a), line, ground, kind)
        boundaries.boundary(solids, rng, road, side, (a + width, s[1]), line, ground, kind)
    _yard(
        solids,
        rng,
        road,
        side,
        s,
        (line + 1.0, setback - 0.5),
        (a, a + width) if drive else (0.0, 0.0),
        ground,
    )
    if not drive:
        return []
    _driveway_mouth(solids, occ, rng, road, side, (a, a + width), ground)
    if setback < 5.5:
        return []
    mid = road.outward(side, np.array([a + width / 2]), np.array([(line + setback) / 2]))
    z = float(ground_z(ground, road, mid, np.array([1.0]))[0])
    return [[mid[0, 0], mid[0, 1], z, road.yaw + side * math.pi / 2, setback - line - 1.0]]


def _roof(
    solids: TaggedSolidList,
    rng: np.random.Generator,
    road: Road,
    side: int,
    s: tuple[float, float],
    d: tuple[float, float],
    ground: Ground,
    top: float,
) -> None:
    """A pitched roof as two stacked boxes, narrower towards the ridge (which runs along the road)."""
    c = road.outward(side, np.array([(s[0] + s[1]) / 2]), np.array([(d[0] + d[1]) / 2]))
    z = float(ground.height_at(c[:, 0], c[:, 1])[0]) + road.curb + top
    rise, depth = rng.uniform(1.5, 3.5), d[1] - d[0]
    solids.tag = BUILDING
    refl = rng.uniform(0.1, 0.4)
    solids.boxes(c, z, z + rise / 2, s[1] - s[0] + 0.4, depth * 0.7, road.yaw, refl)
    solids.boxes(c, z + rise / 2, z + rise, s[1] - s[0] + 0.4, depth * 0.3, road.yaw, refl)


def _yard(
    solids: TaggedSolidList,
    rng: np.random.Generator,
    road: Road,
    side: int,
    s: tuple[float, float],
    d: tuple[float, float],
    drive: tuple[float, float],
    ground: Ground,
) -> None:
    """0-5 bushes and 0-2 trees in a front yard, off the driveway."""
    if d[1] - d[0] < 1.0:
        return
    k = int(rng.integers(0, 6)) + int(rng.integers(0, 3))
    along, out = rng.uniform(s[0] + 1, s[1] - 1, k), rng.uniform(*d, k)
    keep = (along < drive[0] - 2.0) | (along > drive[1] + 2.0)
    along, out = along[keep], out[keep]
    xy = road.outward(side, along, out)
    z = ground_z(ground, road, xy, out)
    tree = rng.random(len(out)) < 0.3
    vegetation.trees(solids, rng, xy[tree], z[tree], vegetation.STREET_TREE)
    n = int((~tree).sum())
    radius = np.minimum(rng.uniform(0.5, 1.5, n), 1.5)
    vegetation.bushes(solids, rng, xy[~tree], z[~tree], radius, rng.uniform(0.6, 2.2, n))


def _driveway_mouth(
    solids: TaggedSolidList,
    occ: Occupancy,
    rng: np.random.Generator,
    road: Road,
    side: int,
    s: tuple[float, float],
    ground: Ground,
) -> None:
    """No parking across a driveway; wheelie bins beside it on the yard side now and then."""
    park = road.parking[0] if side < 0 else road.parking[1]
    if park:
        xy = road.point(
            np.array([(s[0] + s[1]) / 2]), np.array([road.edge(side) - side * road.parking_width / 2])
        )
        occ.take(xy, np.array([(s[1] - s[0]) / 2 + 0.5]))
    if rng.random() < 0.4:
        n = int(rng.integers(1, 3))
        along = s[0] - 0.5 - 0.7 * np.arange(n)
        xy = road.outward(side, along, np.full(n, 0.4))
        z = ground_z(ground, road, xy, np.full(n, 0.4))
        solids.tag = FURNITURE
        solids.boxes(
            xy, z - 0.05, z + rng.uniform(0.95, 1.1, n), 0.6, 0.7, road.yaw, rng.uniform(0.1, 0.5, n)
        )


def _open(
    solids: TaggedSolidList,
    rng: np.random.Generator,
    road: Road,
    side: int,
    others: tuple[Road, ...],
    ground: Ground,
    reach: float,
) -> None:
    """Stretches of 15-60 m: hedgerows, forest edges, tree rows or fields behind a fence; few buildings."""
    s = -reach
    while s < reach:
        length = rng.uniform(15, 60)
        kind = int(rng.choice(4, p=OPEN_KINDS))
        d0 = rng.uniform(0.3, 3.0)
        d1 = d0 + (rng.uniform(2, 6), rng.uniform(4, 12), 1.0, 0.5)[kind]
        for run in boundaries.free_runs(road, side, others, (s, s + length), (d0, d1 + 3.0)):
            if kind < 3:
                strip = vegetation.Strip(road, side, others, run, (d0, d1))
                vegetation.belt(solids, rng, strip, ground, kind)
            elif rng.random() < 0.6:
                boundaries.boundary(solids, rng, road, side, run, d0, ground, boundaries.FENCE_LINE)
        if rng.random() < 0.1:
            setback, depth = rng.uniform(8, 25), rng.uniform(8, 15)
            span = (s + rng.uniform(0, 10), s + rng.uniform(20, 30))
            if _fits(road, side, others, span, (setback, setback + depth)):
                front = Front(road, side, span, setback, depth)
                building(solids, rng, front, ground, int(rng.integers(1, 3)), HOUSE_FACADE)
        s += length
