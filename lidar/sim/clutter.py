"""Static street furniture and vegetation on the sidewalks. Several pieces are the size and shape of a
pedestrian, a cyclist or part of a car (posts, bins, bushes, bollards, sign boards, bare trunks, advertising
columns, low walls, road barriers, bicycles without a rider): hard negatives."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lidar.sim import vegetation
from lidar.sim.ground import Ground
from lidar.sim.layout import Occupancy, Road
from lidar.sim.parts import FURNITURE, TaggedSolidList


@dataclass(frozen=True)
class Spot:
    """A place on a sidewalk."""

    xy: np.ndarray  # (2,)
    z: float  # sidewalk top
    yaw: float  # the road's heading there
    road: int
    side: int  # -1 right, +1 left of the road


def sidewalk_spot(
    rng: np.random.Generator,
    roads: list[Road],
    ground: Ground,
    reach: float,
    band: tuple[float, float],
) -> Spot | None:
    """A random spot on a sidewalk within `reach` of the sensor, at a lateral fraction `band` of its width
    (0 curb, 1 building line); None when it lands on another road."""
    i = int(rng.integers(len(roads)))
    road, side = roads[i], int(rng.choice([-1, 1]))
    s = rng.uniform(-reach, reach)
    lateral = road.edge(side) + side * (0.3 + rng.uniform(*band) * (road.sidewalk - 0.6))
    xy = road.point(np.array([s]), np.array([lateral]))  # (1, 2)
    if any(o.overlaps(xy, margin=0.5)[0] for j, o in enumerate(roads) if j != i):
        return None
    z = float(ground.height_at(xy[:, 0], xy[:, 1])[0]) + road.curb
    return Spot(xy[0], z, road.yaw, i, side)


def _pole(solids: TaggedSolidList, rng: np.random.Generator, spot: Spot) -> float:
    r = rng.uniform(0.1, 0.2)
    solids.cylinders(spot.xy, spot.z - 0.2, spot.z + rng.uniform(5, 9), r, rng.uniform(0.3, 0.5))
    return r


def _sign(solids: TaggedSolidList, rng: np.random.Generator, spot: Spot) -> float:
    top = spot.z + rng.uniform(2.0, 2.8)
    size = rng.uniform(0.6, 0.9)
    solids.cylinders(spot.xy, spot.z - 0.2, top, 0.04, 0.4)
    solids.boxes(spot.xy, top, top + size, 0.05, size, spot.yaw, 0.9)  # retroreflective plate facing traffic
    return size / 2


def _tree(solids: TaggedSolidList, rng: np.random.Generator, spot: Spot) -> float:
    vegetation.trees(solids, rng, spot.xy[None], np.array([spot.z]), vegetation.STREET_TREE)
    return 0.4


def _hydrant(solids: TaggedSolidList, rng: np.random.Generator, spot: Spot) -> float:
    solids.cylinders(spot.xy, spot.z - 0.1, spot.z + rng.uniform(0.6, 0.8), 0.15, 0.45)
    return 0.2


def _bollard(solids: TaggedSolidList, rng: np.random.Generator, spot: Spot) -> float:
    solids.cylinders(spot.xy, spot.z - 0.1, spot.z + rng.uniform(0.9, 1.1), 0.1, rng.uniform(0.3, 0.8))
    return 0.15


def _bin(solids: TaggedSolidList, rng: np.random.Generator, spot: Spot) -> float:
    length, width = rng.uniform(0.5, 0.8, 2)
    yaw = spot.yaw + rng.uniform(-0.3, 0.3)
    solids.boxes(
        spot.xy, spot.z - 0.05, spot.z + rng.uniform(0.9, 1.3), length, width, yaw, rng.uniform(0.1, 0.4)
    )
    return 0.5


def _bush(solids: TaggedSolidList, rng: np.random.Generator, spot: Spot) -> float:
    r = rng.uniform(0.3, 0.9)
    vegetation.bushes(solids, rng, spot.xy[None], np.array([spot.z]), np.array([r]), rng.uniform(0.5, 1.6, 1))
    return r + 0.2


def _board(solids: TaggedSolidList, rng: np.random.Generator, spot: Spot) -> float:
    """A sign board, mailbox or parking meter: a pedestrian-sized box."""
    yaw = spot.yaw + rng.uniform(-math.pi, math.pi)
    length, width = rng.uniform(0.3, 0.6), rng.uniform(0.4, 0.7)
    solids.boxes(
        spot.xy, spot.z - 0.05, spot.z + rng.uniform(1.0, 1.5), length, width, yaw, rng.uniform(0.2, 0.7)
    )
    return 0.45


def _bicycle(solids: TaggedSolidList, rng: np.random.Generator, spot: Spot) -> float:
    """A parked bicycle without a rider (not a CYCLIST target)."""
    yaw = spot.yaw + (math.pi / 2 if rng.random() < 0.5 else 0.0)
    solids.boxes(spot.xy, spot.z, spot.z + 1.0, rng.uniform(1.6, 1.9), 0.12, yaw, rng.uniform(0.3, 0.6), 0.5)
    return 1.0


def _post(solids: TaggedSolidList, rng: np.random.Generator, spot: Spot) -> float:
    """A post of a person's height and girth (a parking meter, a pillar, a short lamp)."""
    r = rng.uniform(0.06, 0.16)
    solids.cylinders(spot.xy, spot.z - 0.1, spot.z + rng.uniform(1.0, 1.9), r, rng.uniform(0.2, 0.6))
    return r + 0.1


def _trunk(solids: TaggedSolidList, rng: np.random.Generator, spot: Spot) -> float:
    """A bare or pollarded tree trunk, with a small knot of branches at the top."""
    r, top = rng.uniform(0.12, 0.3), spot.z + rng.uniform(2.0, 4.0)
    solids.cylinders(spot.xy, spot.z - 0.1, top, r, rng.uniform(*vegetation.BARK))
    solids.cylinders(spot.xy, top, top + rng.uniform(0.3, 0.8), r * 2.5, rng.uniform(0.2, 0.4), 0.8)
    return r * 2.5


def _column(solids: TaggedSolidList, rng: np.random.Generator, spot: Spot) -> float:
    """An advertising column or a utility cabinet."""
    if rng.random() < 0.5:
        r = rng.uniform(0.5, 0.7)
        solids.cylinders(spot.xy, spot.z - 0.1, spot.z + rng.uniform(2.5, 3.2), r, rng.uniform(0.3, 0.7))
        return r
    length, width = rng.uniform(0.6, 1.2), rng.uniform(0.3, 0.5)
    top = spot.z + rng.uniform(1.0, 1.6)
    solids.boxes(spot.xy, spot.z - 0.05, top, length, width, spot.yaw, rng.uniform(0.2, 0.6))
    return length / 2 + 0.1


def _wall(solids: TaggedSolidList, rng: np.random.Generator, spot: Spot) -> float:
    """A low wall or planter along the road, car-bonnet high."""
    length = rng.uniform(1.5, 8.0)
    top = spot.z + rng.uniform(0.4, 1.0)
    solids.boxes(spot.xy, spot.z - 0.05, top, length, rng.uniform(0.2, 0.4), spot.yaw, rng.uniform(0.2, 0.5))
    return length / 2


def _barrier(solids: TaggedSolidList, rng: np.random.Generator, spot: Spot) -> float:
    """A road barrier at the curb: a plank with retroreflective stripes on two legs."""
    length = rng.uniform(1.2, 2.5)
    solids.boxes(spot.xy, spot.z + 0.7, spot.z + 1.0, length, 0.05, spot.yaw, 0.95)
    for end in (-1.0, 1.0):
        leg = spot.xy + end * (length / 2 - 0.1) * np.array([math.cos(spot.yaw), math.sin(spot.yaw)])
        solids.boxes(leg, spot.z, spot.z + 0.7, 0.1, 0.5, spot.yaw, 0.3)
    return length / 2


def _jersey(solids: TaggedSolidList, rng: np.random.Generator, spot: Spot) -> float:
    """A run of 2-4 concrete road barriers end to end at the curb (a work zone): each 3-3.8 m long, a wide
    foot and a narrow top, 0.8-1.05 m high; as long and as high as a car's side, and straight."""
    n, each = int(rng.integers(2, 5)), rng.uniform(3.0, 3.8)
    along = (np.arange(n) - (n - 1) / 2) * (each + rng.uniform(0.0, 0.1))  # (n,) segment centres
    xy = spot.xy + along[:, None] * np.array([math.cos(spot.yaw), math.sin(spot.yaw)])
    top, shade = spot.z + rng.uniform(0.8, 1.05), rng.uniform(0.2, 0.5)
    solids.boxes(xy, spot.z - 0.05, spot.z + 0.3, each, 0.6, spot.yaw, shade)
    solids.boxes(xy, spot.z + 0.3, top, each, 0.25, spot.yaw, shade)
    return n * each / 2


# (name, placement band across the sidewalk, relative frequency, builder returning its footprint radius)
KINDS: tuple[tuple[str, tuple[float, float], float, Callable[..., float]], ...] = (
    ("pole", (0.0, 0.1), 0.15, _pole),
    ("sign", (0.0, 0.1), 0.10, _sign),
    ("tree", (0.0, 0.15), 0.15, _tree),
    ("hydrant", (0.0, 0.15), 0.05, _hydrant),
    ("bollard", (0.0, 0.2), 0.08, _bollard),
    ("bin", (0.6, 1.0), 0.12, _bin),
    ("bush", (0.7, 1.0), 0.15, _bush),
    ("board", (0.3, 1.0), 0.10, _board),
    ("bicycle", (0.7, 1.0), 0.10, _bicycle),
    ("post", (0.0, 0.3), 0.10, _post),
    ("trunk", (0.0, 0.15), 0.05, _trunk),
    ("column", (0.4, 1.0), 0.03, _column),
    ("wall", (0.8, 1.0), 0.04, _wall),
    ("barrier", (0.0, 0.1), 0.03, _barrier),
    ("jersey", (0.0, 0.1), 0.02, _jersey),
)
# what a pedestrian may stand beside (BESIDE in actors.py): furniture of a person's size or taller
BESIDE_KINDS = frozenset(
    {"pole", "sign", "tree", "hydrant", "bollard", "bin", "board", "post", "trunk", "column"}
)


def clutter(
    solids: TaggedSolidList,
    occ: Occupancy,
    rng: np.random.Generator,
    roads: list[Road],
    ground: Ground,
    count: int,
    reach: float,
) -> np.ndarray:
    """`count` tries at placing random furniture on the sidewalks (overlapping tries are skipped). Returns
    (A, 5) x, y, sidewalk z, footprint radius and road heading of each piece a person may stand beside."""
    weights = np.array([k[2] for k in KINDS])
    picks = rng.choice(len(KINDS), size=count, p=weights / weights.sum())
    beside = []
    for k in picks:
        name, band, _, build = KINDS[k]
        spot = sidewalk_spot(rng, roads, ground, reach, band)
        if spot is None or not occ.free(spot.xy[None], np.array([0.5])):
            continue
        solids.tag = FURNITURE
        r = build(solids, rng, spot)
        occ.take(spot.xy, np.array([r]))
        if name in BESIDE_KINDS:
            beside.append([*spot.xy, spot.z, r, spot.yaw])
    return np.asarray(beside, np.float64).reshape(-1, 5)
