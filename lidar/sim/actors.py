"""Targets: VEHICLE (body types in vehicles.py), PEDESTRIAN and CYCLIST (people.py). Candidates are drawn
densely along lanes and sidewalks, then a configured number is kept inside the placement radius (and a few
beyond it), skipping any that would overlap what is placed.

A label box is (x, y, z, l, w, h, yaw) with z the box centre; the solids of an object lie inside its box and
reach its faces (a tight box, as annotators draw them), occluded parts included.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lidar.sim import people, stats, vehicles
from lidar.sim.clutter import sidewalk_spot
from lidar.sim.ground import Ground
from lidar.sim.layout import Occupancy, Road, crossing_span, footprint
from lidar.sim.parts import Obstacles
from lidar.sim.raycast import SolidList

ROW_BREAK = 0.12  # chance that a parked row breaks after a car (a driveway, a hydrant, an empty stretch)
ROW_BREAK_M = (4.0, 20.0)  # length of such a break
TURNING = 0.1  # chance that a moving vehicle is turning or changing lanes: heading off its lane's
TURN_RAD = (0.15, 0.7)  # by this much, either way
TRAILERS = (0.3, 2)  # chance that a scene has small trailers parked at the curb, and at most how many
TRAILER_SIZE = ((2.6, 1.3, 0.75), (4.2, 2.0, 1.3))  # label-free (l, w, h) range, drawbar included
# chance that a pedestrian (and the group) stands beside street furniture (a pole, a sign, a tree, a bin ..),
# its centre 0.45-0.9 m beyond the piece's footprint: a person's points then come with something else's in
# the same metre or two, as on real streets (docs/model-card.md, the pedestrians' diagnosis)
BESIDE = 0.5
# chance that a pedestrian (and the group) stands behind a vehicle as the sensor sees it, 0.4-2.4 m beyond the
# vehicle's far side on the line from the sensor: only the upper body shows above the car, as for most
# well-seen pedestrians of the real samples. 0 in the shipped world: a detector phase and refiner trained
# with 0.3 did not do better (docs/model-card.md, the pedestrians' diagnosis)
BEHIND = 0.0
GROUP_SQUEEZE = 0.8  # a pedestrian's free space (on the ground) is its box's footprint shrunk by this, so
# that a group can stand GROUP_SPACING_M apart; the label box itself keeps clear of the scenery


@dataclass(frozen=True)
class Candidates:
    boxes: np.ndarray  # (K, 7) label boxes
    large: np.ndarray  # (K,) bool: a truck, bus or trailer (vehicles only)
    kind: np.ndarray | None = None  # (K,) int64 body type (stats.SEDAN ..), what a pedestrian carries
    # (people.PLAIN ..) or a cyclist's vehicle (people.BICYCLE ..); None: drawn when the solids are built
    space: np.ndarray | None = None  # (K, 7) boxes that must stay free for them (None: the label boxes),
    # larger where an object has something unlabelled with it (a stroller)
    group: np.ndarray | None = None  # (K,) int64: candidates that are placed together (a group walking)

    def take(self, idx: np.ndarray) -> Candidates:
        pick = [None if a is None else a[idx] for a in (self.kind, self.space, self.group)]
        return Candidates(self.boxes[idx], self.large[idx], *pick)

    @staticmethod
    def join(parts: list[Candidates]) -> Candidates:
        """Candidates that all carry kinds, as one."""
        cat = [np.concatenate(a) for a in zip(*((c.boxes, c.large, c.kind) for c in parts), strict=True)]
        space = [c.boxes if c.space is None else c.space for c in parts]
        return Candidates(*cat, np.concatenate(space))


def _lanes(road: Road) -> list[tuple[float, float, bool]]:
    """(lateral offset, heading, parked) of every lane of a road."""
    lanes = []
    for k in range(road.lanes):
        lanes.append((-(k + 0.5) * road.lane_width, road.yaw, False))
        lanes.append(((k + 0.5) * road.lane_width, road.yaw + math.pi, False))
    for side, parked in zip((-1, 1), road.parking, strict=True):
        if parked:
            lateral = side * (road.lanes * road.lane_width + road.parking_width / 2)
            lanes.append((lateral, road.yaw + (0.0 if side < 0 else math.pi), True))
    return lanes


def vehicle_candidates(
    rng: np.random.Generator, roads: list[Road], ground: Ground, reach: float
) -> Candidates:
    """Queues of vehicles filling every lane of every road (parked queues tight, moving ones looser)."""
    boxes, large, kinds = [], [], []
    for i, road in enumerate(roads):
        others = [r for j, r in enumerate(roads) if j != i]
        for lateral, heading, parked in _lanes(road):
            n = int(2 * reach / 3.5) + 1
            big = rng.random(n) < stats.LARGE_VEHICLE_FRACTION
            kind = vehicles.body_kinds(rng, big, trailers=parked)  # semi-trailers stand parked
            size = body_sizes(rng, kind)  # (n, 3)
            room = road.parking_width + 0.3 if parked else road.lane_width - 0.3
            size[:, 1] = np.minimum(size[:, 1], room)
            gap = rng.uniform(*(stats.PARKED_GAP_M if parked else stats.MOVING_GAP_M), n)
            if parked:  # rows with breaks; the gaps within a row stay the measured ones
                gap += (rng.random(n) < ROW_BREAK) * rng.uniform(*ROW_BREAK_M, n)
            s = -reach + rng.uniform(0, 5) + np.cumsum(size[:, 0] + gap) - size[:, 0] / 2  # (n,) centres
            xy = road.point(s, np.full(n, lateral))  # (n, 2)
            yaw = heading + rng.normal(0, 0.05 if parked else 0.03, n)
            if not parked:
                turn = (rng.random(n) < TURNING) * rng.uniform(*TURN_RAD, n) * rng.choice([-1.0, 1.0], n)
                yaw += turn
            corners = footprint(xy, size[:, 0], size[:, 1], yaw)  # (n, 4, 2)
            margin = 5.0 if parked else 0.0  # no parking near a crossing; cross traffic waits outside it
            keep = (s < reach) & ~np.any(
                [o.overlaps(corners, margin) for o in others] or [np.zeros(n, bool)], 0
            )
            z = ground.height_at(xy[:, 0], xy[:, 1]) + size[:, 2] / 2
            boxes.append(np.column_stack([xy, z, size, yaw])[keep])
            large.append(big[keep])
            kinds.append(kind[keep])
    return Candidates(np.concatenate(boxes), np.concatenate(large), np.concatenate(kinds))


def parked_trailers(
    rng: np.random.Generator,
    roads: list[Road],
    ground: Ground,
    occ: Occupancy,
    reach: float,
    obstacles: Obstacles,
) -> np.ndarray:
    """Small trailers parked in parking lanes (hard negatives, not labelled) -> their boxes (K, 7), placed."""
    if rng.random() >= TRAILERS[0]:
        return np.zeros((0, 7))
    lanes = [(road, lat, yaw) for road in roads for lat, yaw, parked in _lanes(road) if parked]
    if not lanes:
        return np.zeros((0, 7))
    n = 10
    pick = rng.integers(len(lanes), size=n)
    size = rng.uniform(*TRAILER_SIZE, (n, 3))
    boxes = []
    for i in range(n):
        road, lateral, yaw = lanes[pick[i]]
        xy = road.point(np.array([rng.uniform(-reach, reach)]), np.array([lateral]))[0]
        z = float(ground.height_at(xy[None, 0], xy[None, 1])[0]) + size[i, 2] / 2
        boxes.append([*xy, z, *size[i], yaw + rng.choice([0.0, math.pi])])
    cands = Candidates(np.asarray(boxes), np.zeros(n, bool))
    count = int(rng.integers(1, TRAILERS[1] + 1))
    return select(rng, cands, occ, count, 0, reach, reach, obstacles).boxes


def body_sizes(rng: np.random.Generator, kind: np.ndarray) -> np.ndarray:
    """(K,) body types -> (K, 3) label sizes drawn from their `stats.BODY_SIZES`."""
    every = np.stack([s.draw(rng, len(kind)) for s in stats.BODY_SIZES])  # (types, K, 3)
    return every[kind, np.arange(len(kind))]


def driveway_candidates(rng: np.random.Generator, slots: np.ndarray) -> Candidates:
    """Cars parked in driveways: slots (K, 5) x, y, ground z, heading, room -> one car per slot that fits,
    facing the house or the street."""
    kind = vehicles.body_kinds(rng, np.zeros(len(slots), bool))
    size = body_sizes(rng, kind)  # (K, 3)
    fits = size[:, 0] <= slots[:, 4]
    yaw = slots[:, 3] + np.where(rng.random(len(slots)) < 0.5, 0.0, math.pi)
    boxes = np.column_stack([slots[:, :2], slots[:, 2] + size[:, 2] / 2, size, yaw])[fits]
    return Candidates(boxes, np.zeros(len(boxes), bool), kind[fits])


def _crossing(
    rng: np.random.Generator, roads: list[Road], ground: Ground, reach: float
) -> tuple[np.ndarray, float, float, float]:
    """A pedestrian crossing a road: at the crosswalk by the other road if there is one, else anywhere.
    Returns position (2,), ground z, heading, and the direction in which a group lines up."""
    i = int(rng.integers(len(roads)))
    road = roads[i]
    s = rng.uniform(-reach, reach)
    if len(roads) > 1:  # crosswalks just outside the crossing
        gap = crossing_span(road, roads[1 - i], 2.5)
        s = gap[int(rng.integers(2))] + rng.uniform(-1.5, 1.5)
    xy = road.point(np.array([s]), np.array([rng.uniform(road.edge(-1), road.edge(1))]))
    heading = road.yaw + math.pi / 2 + (math.pi if rng.random() < 0.5 else 0.0)
    return xy[0], float(ground.height_at(xy[:, 0], xy[:, 1])[0]), heading, road.yaw


def _beside(rng: np.random.Generator, beside: np.ndarray) -> tuple[np.ndarray, float, float]:
    """A spot next to one piece of furniture of `beside` (A, 5), along the road from it. Returns position
    (2,), sidewalk z and the road's heading."""
    x, y, z, r, yaw = beside[int(rng.integers(len(beside)))]
    along = (r + 0.45 + rng.uniform(0.0, 0.45)) * (1.0 if rng.random() < 0.5 else -1.0)
    across = rng.uniform(-0.3, 0.3)
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([x + along * c - across * s, y + along * s + across * c]), float(z), float(yaw)


def _behind(
    rng: np.random.Generator, vehicles: np.ndarray, ground: Ground
) -> tuple[np.ndarray, float, float]:
    """A spot behind one of `vehicles` (V, 7) as the sensor sees it: on the line from the sensor through the
    vehicle's centre, 0.4-2.4 m beyond its far side. Returns position (2,), ground z and the vehicle's
    heading (along which a group lines up)."""
    x, y, _, length, width, _, yaw = vehicles[int(rng.integers(len(vehicles)))]
    dist = math.hypot(x, y)
    ux, uy = x / dist, y / dist
    c, s = math.cos(yaw), math.sin(yaw)
    half = abs(length / 2 * (ux * c + uy * s)) + abs(width / 2 * (uy * c - ux * s))  # the car's depth / 2
    d = dist + half + rng.uniform(0.4, 2.4)
    xy = np.array([ux * d, uy * d]) + rng.uniform(-0.5, 0.5) * np.array([-uy, ux])
    return xy, float(ground.height_at(xy[None, 0], xy[None, 1])[0]), float(yaw)


def pedestrian_candidates(
    rng: np.random.Generator,
    roads: list[Road],
    ground: Ground,
    reach: float,
    n: int,
    beside: np.ndarray | None = None,
    vehicles: np.ndarray | None = None,
) -> Candidates:
    """`n` tries: walkers and standing groups of 1-4 on the sidewalks, about one in ten crossing a road, a
    share (BESIDE) next to a piece of street furniture of `beside` (A, 5) (clutter.clutter) and a share
    (BEHIND) behind one of the placed `vehicles` (V, 7) as the sensor sees it."""
    boxes, carries, groups = [], [], []
    for g in range(n):
        size, carry = people.pedestrian_sizes(rng, 4)  # (4, 3), (4,)
        draw = rng.random()
        if draw < 0.1:
            xy, base, heading, line_up = _crossing(rng, roads, ground, reach)
        else:
            if draw < 0.1 + BESIDE and beside is not None and len(beside):
                xy, base, line_up = _beside(rng, beside)
            elif draw < 0.1 + BESIDE + BEHIND and vehicles is not None and len(vehicles):
                xy, base, line_up = _behind(rng, vehicles, ground)
            else:
                spot = sidewalk_spot(rng, roads, ground, reach, (0.1, 0.9))
                if spot is None:
                    continue
                xy, base, line_up = spot.xy, spot.z, spot.yaw
            heading = line_up + (math.pi if rng.random() < 0.5 else 0.0)
            heading = heading if rng.random() < 0.8 else rng.uniform(-math.pi, math.pi)  # standing
        members = int(rng.choice([1, 2, 3, 4], p=[0.55, 0.3, 0.1, 0.05]))
        side = line_up + (math.pi / 2 if rng.random() < 0.5 else -math.pi / 2)  # side by side, or in a line
        along = side if rng.random() < 0.6 else line_up + (0.0 if rng.random() < 0.5 else math.pi)
        step = stats.GROUP_SPACING_M * np.array([math.cos(along), math.sin(along)])
        for m in range(members):
            c = xy + step * m
            yaw = heading + rng.normal(0, 0.15)
            boxes.append([c[0], c[1], base + size[m, 2] / 2, *size[m], yaw])
            carries.append(carry[m])
            groups.append(g)
    boxes_arr = np.asarray(boxes, np.float64).reshape(-1, 7)
    carry_arr = np.asarray(carries, np.int64)
    space = boxes_arr.copy()  # a stroller goes ahead of its pedestrian's box
    space[:, 3:5] *= GROUP_SQUEEZE
    pushing = carry_arr == people.STROLLER
    grow = 1.0
    space[pushing, :2] += grow / 2 * np.column_stack([np.cos(space[pushing, 6]), np.sin(space[pushing, 6])])
    space[pushing, 3] += grow
    group = np.asarray(groups, np.int64)
    return Candidates(boxes_arr, np.zeros(len(boxes_arr), bool), carry_arr, space, group)


def cyclist_candidates(
    rng: np.random.Generator, roads: list[Road], ground: Ground, reach: float, n: int
) -> Candidates:
    """`n` tries: riders near the right edge of the outer lanes, one in four on a sidewalk."""
    boxes, kinds = [], []
    for _ in range(n):
        sizes, kind = people.cyclist_sizes(rng, 1)
        size = sizes[0]  # (3,)
        if rng.random() < 0.25:
            spot = sidewalk_spot(rng, roads, ground, reach, (0.2, 0.8))
            if spot is None:
                continue
            xy, base, heading = spot.xy, spot.z, spot.yaw + (math.pi if rng.random() < 0.5 else 0.0)
        else:
            road = roads[int(rng.integers(len(roads)))]
            side = int(rng.choice([-1, 1]))  # forward lanes on the right, oncoming on the left
            lateral = side * (road.lanes * road.lane_width - rng.uniform(0.6, 1.0))
            xy = road.point(np.array([rng.uniform(-reach, reach)]), np.array([lateral]))[0]
            base = float(ground.height_at(xy[None, 0], xy[None, 1])[0])
            heading = road.yaw + (0.0 if side < 0 else math.pi)
        boxes.append([xy[0], xy[1], base + size[2] / 2, *size, heading + rng.normal(0, 0.05)])
        kinds.append(kind[0])
    boxes_arr = np.asarray(boxes, np.float64).reshape(-1, 7)
    return Candidates(boxes_arr, np.zeros(len(boxes_arr), bool), np.asarray(kinds, np.int64))


def discs(box: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One box (7,) -> its footprint as 1-3 discs along the heading: centres (D, 2), radii (D,)."""
    length, w, yaw = box[3], box[4], box[6]
    k = 1 if length < 1.3 * w else 3
    along = np.linspace(-(length - w) / 2, (length - w) / 2, k) if k > 1 else np.zeros(1)
    centres = box[:2] + along[:, None] * np.array([math.cos(yaw), math.sin(yaw)])
    r = np.full(k, math.hypot(w / 2, (length - w) / (2 * (k - 1)) if k > 1 else length / 2) + 0.05)
    return centres, r


def select(
    rng: np.random.Generator,
    cands: Candidates,
    occ: Occupancy,
    inside: int,
    outside: int,
    radius: float,
    reach: float,
    obstacles: Obstacles | None = None,
) -> Candidates:
    """Keep up to `inside` candidates within `radius` of the sensor and `outside` between it and `reach`,
    in random order (a group's members one after another), skipping those that overlap anything taken or any
    of the `obstacles` (scenery); the kept ones take their place."""
    if cands.group is None:
        order = rng.permutation(len(cands.boxes))
    else:  # groups in random order, each group's members together
        rank = rng.permutation(int(cands.group.max()) + 1 if len(cands.group) else 0)
        order = np.argsort(rank[cands.group], kind="stable")
    dist = np.hypot(cands.boxes[:, 0], cands.boxes[:, 1])
    space = cands.boxes if cands.space is None else cands.space
    keep, room = [], {True: inside, False: outside}
    for i in order:
        near = bool(dist[i] <= radius)
        if room[near] == 0 or dist[i] > reach:
            continue
        xy, r = discs(space[i])
        clear = obstacles is None or (obstacles.clear(cands.boxes[i]) and obstacles.clear(space[i]))
        if occ.free(xy, r) and clear:
            occ.take(xy, r)
            keep.append(i)
            room[near] -= 1
    return cands.take(np.asarray(keep, np.int64))


def vehicle_solids(solids: SolidList, rng: np.random.Generator, cands: Candidates) -> None:
    """Every vehicle of `cands` as its body type (drawn when not given: cars, box trucks or buses)."""
    kind = vehicles.body_kinds(rng, cands.large, trailers=False) if cands.kind is None else cands.kind
    vehicles.vehicle_solids(solids, rng, cands.boxes, kind)


def pedestrian_solids(
    solids: SolidList, rng: np.random.Generator, boxes: np.ndarray, carry: np.ndarray | None = None
) -> None:
    """Every pedestrian (people.pedestrian_solids)."""
    people.pedestrian_solids(solids, rng, boxes, carry)


def cyclist_solids(
    solids: SolidList, rng: np.random.Generator, boxes: np.ndarray, kind: np.ndarray | None = None
) -> None:
    """Every cyclist (people.cyclist_solids)."""
    people.cyclist_solids(solids, rng, boxes, kind)
