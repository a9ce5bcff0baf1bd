"""Targets: VEHICLE (sedans, hatchbacks/SUVs, pickups, trucks and buses, with rear lights), PEDESTRIAN
(legs and feet, a torso leaning forward, head, sometimes a backpack), CYCLIST (bicycle with a handlebar +
a rider leaning to it). Candidates are drawn densely along lanes and sidewalks, then a configured number is
kept inside the placement radius (and a few beyond it), skipping any that would overlap what is placed.

A label box is (x, y, z, l, w, h, yaw) with z the box centre; the solids of an object lie inside its box.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from model.data.sim import stats
from model.data.sim.clutter import sidewalk_spot
from model.data.sim.ground import Ground
from model.data.sim.layout import Occupancy, Road, crossing_span, footprint
from model.data.sim.parts import Obstacles
from model.data.sim.raycast import Num, SolidList

PAINT = np.array([0.06, 0.12, 0.25, 0.35, 0.5, 0.7])  # car paint reflectivities: black .. white
SEDAN, HATCHBACK, PICKUP = 0, 1, 2  # car body shapes (hatchback stands for SUVs and vans too)
CAR_SHAPES = (0.35, 0.5, 0.15)  # their shares of cars
CABIN_BEHIND = ((0.17, 0.25), (0.02, 0.06), (0.3, 0.4))  # what follows the cabin (boot, hatch, bed) / length
TRUCK_SHARE = 0.6  # of large vehicles; the rest are buses
LIGHT_DEPTH = 0.02  # metres: the rear lights fill the back of the label box, the body ends in front of them
BACKPACK_SHARE = 0.35  # of pedestrians
ROW_BREAK = 0.12  # chance that a parked row breaks after a car (a driveway, a hydrant, an empty stretch)
ROW_BREAK_M = (4.0, 20.0)  # length of such a break


@dataclass(frozen=True)
class Candidates:
    boxes: np.ndarray  # (K, 7) label boxes
    large: np.ndarray  # (K,) bool: a truck or bus (vehicles only)


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
    boxes, large = [], []
    for i, road in enumerate(roads):
        others = [r for j, r in enumerate(roads) if j != i]
        for lateral, heading, parked in _lanes(road):
            n = int(2 * reach / 3.5) + 1
            big = rng.random(n) < stats.LARGE_VEHICLE_FRACTION
            size = np.where(big[:, None], stats.LARGE_VEHICLE.draw(rng, n), stats.CAR.draw(rng, n))  # (n, 3)
            room = road.parking_width + 0.3 if parked else road.lane_width - 0.3
            size[:, 1] = np.minimum(size[:, 1], room)
            gap = rng.uniform(*(stats.PARKED_GAP_M if parked else stats.MOVING_GAP_M), n)
            if parked:  # rows with breaks; the gaps within a row stay the measured ones
                gap += (rng.random(n) < ROW_BREAK) * rng.uniform(*ROW_BREAK_M, n)
            s = -reach + rng.uniform(0, 5) + np.cumsum(size[:, 0] + gap) - size[:, 0] / 2  # (n,) centres
            xy = road.point(s, np.full(n, lateral))  # (n, 2)
            yaw = heading + rng.normal(0, 0.05 if parked else 0.03, n)
            corners = footprint(xy, size[:, 0], size[:, 1], yaw)  # (n, 4, 2)
            margin = 5.0 if parked else 0.0  # no parking near a crossing; cross traffic waits outside it
            keep = (s < reach) & ~np.any(
                [o.overlaps(corners, margin) for o in others] or [np.zeros(n, bool)], 0
            )
            z = ground.height_at(xy[:, 0], xy[:, 1]) + size[:, 2] / 2
            boxes.append(np.column_stack([xy, z, size, yaw])[keep])
            large.append(big[keep])
    return Candidates(np.concatenate(boxes), np.concatenate(large))


def driveway_candidates(rng: np.random.Generator, slots: np.ndarray) -> Candidates:
    """Cars parked in driveways: slots (K, 5) x, y, ground z, heading, room -> one car per slot that fits,
    facing the house or the street."""
    size = stats.CAR.draw(rng, len(slots))  # (K, 3)
    fits = size[:, 0] <= slots[:, 4]
    yaw = slots[:, 3] + np.where(rng.random(len(slots)) < 0.5, 0.0, math.pi)
    boxes = np.column_stack([slots[:, :2], slots[:, 2] + size[:, 2] / 2, size, yaw])[fits]
    return Candidates(boxes, np.zeros(len(boxes), bool))


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


def pedestrian_candidates(
    rng: np.random.Generator, roads: list[Road], ground: Ground, reach: float, n: int
) -> Candidates:
    """`n` tries: walkers and standing groups of 1-3 on the sidewalks, about one in ten crossing a road."""
    boxes = []
    for _ in range(n):
        size = stats.PEDESTRIAN.draw(rng, 3)  # (3, 3)
        if rng.random() < 0.1:
            xy, base, heading, line_up = _crossing(rng, roads, ground, reach)
        else:
            spot = sidewalk_spot(rng, roads, ground, reach, (0.1, 0.9))
            if spot is None:
                continue
            xy, base, line_up = spot.xy, spot.z, spot.yaw
            heading = spot.yaw + (math.pi if rng.random() < 0.5 else 0.0)
            heading = heading if rng.random() < 0.8 else rng.uniform(-math.pi, math.pi)  # standing
        members = int(rng.choice([1, 2, 3], p=[0.6, 0.3, 0.1]))
        step = stats.GROUP_SPACING_M * np.array([math.cos(line_up), math.sin(line_up)])
        for m in range(members):
            c = xy + step * m
            yaw = heading + rng.normal(0, 0.15)
            boxes.append([c[0], c[1], base + size[m, 2] / 2, *size[m], yaw])
    boxes_arr = np.asarray(boxes, np.float64).reshape(-1, 7)
    return Candidates(boxes_arr, np.zeros(len(boxes_arr), bool))


def cyclist_candidates(
    rng: np.random.Generator, roads: list[Road], ground: Ground, reach: float, n: int
) -> Candidates:
    """`n` tries: riders near the right edge of the outer lanes, one in four on a sidewalk."""
    boxes = []
    for _ in range(n):
        size = stats.CYCLIST.draw(rng, 1)[0]  # (3,)
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
    boxes_arr = np.asarray(boxes, np.float64).reshape(-1, 7)
    return Candidates(boxes_arr, np.zeros(len(boxes_arr), bool))


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
    in random order, skipping those that overlap anything taken or any of the `obstacles` (scenery); the kept
    ones take their place."""
    order = rng.permutation(len(cands.boxes))
    dist = np.hypot(cands.boxes[:, 0], cands.boxes[:, 1])
    keep, room = [], {True: inside, False: outside}
    for i in order:
        near = bool(dist[i] <= radius)
        if room[near] == 0 or dist[i] > reach:
            continue
        xy, r = discs(cands.boxes[i])
        if occ.free(xy, r) and (obstacles is None or obstacles.clear(cands.boxes[i])):
            occ.take(xy, r)
            keep.append(i)
            room[near] -= 1
    idx = np.asarray(keep, np.int64)
    return Candidates(cands.boxes[idx], cands.large[idx])


def _offset(boxes: np.ndarray, along: Num, across: Num = 0.0) -> np.ndarray:
    """(K, 7) boxes, metres along each heading and to its left (scalars or (K,)) -> (K, 2) points."""
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    return boxes[:, :2] + np.stack([along * c - across * s, along * s + across * c], 1)


def _segment(
    solids: SolidList,
    boxes: np.ndarray,
    span: tuple[Num, Num],
    z: tuple[Num, Num],
    width: Num,
    refl: Num,
    porosity: float = 0.0,
    across: Num = 0.0,
) -> None:
    """One solid per object, from span[1] to span[0] metres along its heading (front > rear)."""
    front, rear = span
    centre = _offset(boxes, (np.asarray(front) + rear) / 2, across)
    solids.boxes(centre, z[0], z[1], np.asarray(front) - rear, width, boxes[:, 6], refl, porosity)


def vehicle_solids(solids: SolidList, rng: np.random.Generator, cands: Candidates) -> None:
    """Every vehicle: axles with wheels under the body and retroreflective rear lights; cars as sedans,
    hatchbacks/SUVs or pickups, large vehicles as trucks (cab + cargo box) or buses (docs/simulator.md)."""
    b, k = cands.boxes, len(cands.boxes)
    base, length, w, _, _ = _parts(b)
    clear = np.where(cands.large, rng.uniform(0.4, 0.6, k), rng.uniform(0.18, 0.3, k))
    paint = rng.choice(PAINT, k) * rng.uniform(0.8, 1.2, k)
    for sign in (-1.0, 1.0):  # axles with their wheels, seen through the gap under the body
        axle = _offset(b, sign * (length / 2 - np.minimum(0.9, length * 0.2)))
        solids.boxes(axle, base, base + clear + 0.05, 0.65, w * 0.96, b[:, 6], rng.uniform(0.03, 0.08, k))
    light_z = base + clear + np.where(cands.large, 0.5, rng.uniform(0.35, 0.55, k))
    lights = (-length / 2 + LIGHT_DEPTH, -length / 2)
    for side in (-1.0, 1.0):  # tail lights with their retroreflectors, at the back corners: saturated returns
        height = (light_z - 0.08, light_z + 0.08)
        _segment(solids, b, lights, height, 0.3, 1.0, across=side * (w / 2 - 0.2))
    car = ~cands.large
    _car_solids(solids, rng, b[car], clear[car], paint[car])
    _large_solids(solids, rng, b[cands.large], clear[cands.large], paint[cands.large])


def _car_solids(
    solids: SolidList, rng: np.random.Generator, b: np.ndarray, clear: np.ndarray, paint: np.ndarray
) -> None:
    """A bonnet lower than the rest of the body, a glass cabin with a raked windscreen that ends above a
    boot (sedan), near the back (hatchback, SUV, van) or before an open bed (pickup)."""
    k = len(b)
    base, length, w, h, _ = _parts(b)
    half, back = length / 2, -length / 2 + LIGHT_DEPTH
    shape = rng.choice(len(CAR_SHAPES), k, p=CAR_SHAPES)
    body_top = base + h * rng.uniform(0.5, 0.6, k)
    windscreen = half - length * rng.uniform(0.24, 0.32, k)  # where the bonnet ends
    boot = length * np.choose(shape, [rng.uniform(*CABIN_BEHIND[s], k) for s in range(len(CAR_SHAPES))])
    pickup = shape == PICKUP
    _segment(solids, b, (half, windscreen), (base + clear, body_top - rng.uniform(0.03, 0.12, k)), w, paint)
    body_end = np.where(pickup, -half + boot, back)
    _segment(solids, b, (windscreen, body_end), (base + clear, body_top), w, paint)
    sill = (body_top + base + h) / 2  # the windscreen leans back from the bonnet to the roof
    glass = rng.uniform(0.05, 0.15, k)
    cabin_end = -half + np.where(pickup, boot + 0.1, boot)
    _segment(solids, b, (windscreen, cabin_end), (body_top, sill), w * 0.88, glass, 0.25)
    roof = (windscreen - rng.uniform(0.3, 0.6, k), cabin_end)
    _segment(solids, b, roof, (sill, base + h), w * 0.88, glass, 0.25)
    _bed(solids, b[pickup], (-half + boot)[pickup], clear[pickup], body_top[pickup], paint[pickup])


def _bed(
    solids: SolidList, b: np.ndarray, front: np.ndarray, clear: np.ndarray, top: np.ndarray, paint: np.ndarray
) -> None:
    """A pickup's open bed from `front` to the back: a floor well below the sides, two side walls and a
    tailgate."""
    base, length, w, _, _ = _parts(b)
    back = -length / 2 + LIGHT_DEPTH
    floor = np.maximum(base + clear + 0.1, top - 0.45)
    _segment(solids, b, (front, back), (base + clear, floor), w, paint)
    for side in (-1.0, 1.0):
        _segment(solids, b, (front, back), (floor, top), 0.08, paint, across=side * (w / 2 - 0.04))
    _segment(solids, b, (back + 0.06, back), (floor, top), w, paint)


def _large_solids(
    solids: SolidList, rng: np.random.Generator, b: np.ndarray, clear: np.ndarray, paint: np.ndarray
) -> None:
    """Trucks: a cab lower than the cargo box behind it; buses: one box."""
    k = len(b)
    base, length, w, h, _ = _parts(b)
    half, back = length / 2, -length / 2 + LIGHT_DEPTH
    t = rng.random(k) < TRUCK_SHARE  # trucks; the rest are buses
    cab_end = half - np.minimum(2.4, 0.3 * length)
    cab_top = base + h * rng.uniform(0.7, 0.85, k)
    _segment(solids, b[t], (half[t], cab_end[t]), (base[t] + clear[t], cab_top[t]), w[t] * 0.96, paint[t])
    cargo_front = np.where(t, cab_end - 0.2, half)
    _segment(solids, b, (cargo_front, back), (base + clear, base + h), w, paint)


def _parts(boxes: np.ndarray) -> tuple[np.ndarray, ...]:
    """(K, 7) boxes -> (K,) each: bottom z, length, width, height, yaw."""
    return boxes[:, 2] - boxes[:, 5] / 2, boxes[:, 3], boxes[:, 4], boxes[:, 5], boxes[:, 6]


def pedestrian_solids(solids: SolidList, rng: np.random.Generator, boxes: np.ndarray) -> None:
    """Legs (one cylinder) with the feet pointing ahead, a torso across the heading whose chest leans
    forward over the hips, the head ahead of the shoulders; 35 % carry a backpack."""
    k = len(boxes)
    base, length, w, h, _ = _parts(boxes)
    half = length / 2
    clothes = rng.uniform(0.05, 0.5, k)
    legs = np.minimum(rng.uniform(0.13, 0.18, k), np.minimum(length, w) / 2)
    solids.cylinders(boxes[:, :2], base, base + 0.47 * h, legs, clothes * rng.uniform(0.7, 1.0, k))
    toes = np.minimum(legs + rng.uniform(0.08, 0.14, k), half)
    _segment(solids, boxes, (toes, -0.08), (base, base + 0.09), np.minimum(0.3, w), rng.uniform(0.05, 0.3, k))
    torso_l, torso_w = np.minimum(rng.uniform(0.22, 0.3, k), length), np.minimum(rng.uniform(0.4, 0.5, k), w)
    lean = np.minimum(rng.uniform(0.04, 0.1, k), half - torso_l / 2)  # of the chest over the hips
    waist, shoulders = base + 0.62 * h, base + 0.84 * h
    _segment(solids, boxes, (torso_l / 2, -torso_l / 2), (base + 0.47 * h, waist), torso_w, clothes)
    _segment(solids, boxes, (lean + torso_l / 2, lean - torso_l / 2), (waist, shoulders), torso_w, clothes)
    head = _offset(boxes, np.minimum(lean + 0.05, half - 0.1))
    solids.cylinders(head, shoulders, base + h, 0.1, rng.uniform(0.2, 0.4, k))
    bag = rng.random(k) < BACKPACK_SHARE
    rear = (lean - torso_l / 2)[bag]  # the backpack hangs on the back of the chest
    depth = np.minimum(rng.uniform(0.12, 0.2, bag.sum()), rear + half[bag])
    height = (waist[bag] - 0.05, shoulders[bag] - 0.05)
    _segment(solids, boxes[bag], (rear, rear - depth), height, 0.3, rng.uniform(0.1, 0.5, bag.sum()))


def cyclist_solids(solids: SolidList, rng: np.random.Generator, boxes: np.ndarray) -> None:
    """A bicycle (thin, mostly see-through plate up to 1 m) with a handlebar across its front, and a rider
    leaning forward: legs, hips over the saddle behind the middle, chest ahead of them, arms reaching to the
    handlebar, the head ahead of the chest."""
    k = len(boxes)
    base, length, w, h, yaw = _parts(boxes)
    solids.boxes(boxes[:, :2], base, base + 1.0, length * 0.95, 0.12, yaw, rng.uniform(0.3, 0.6, k), 0.5)
    bar, grip = 0.3 * length, base + rng.uniform(0.95, 1.1, k)
    _segment(solids, boxes, (bar + 0.04, bar - 0.04), (grip - 0.04, grip), np.minimum(0.6, w), 0.4)
    clothes = rng.uniform(0.05, 0.5, k)
    solids.cylinders(boxes[:, :2], base + 0.45, base + 1.0, 0.12, clothes)
    torso_w = np.minimum(rng.uniform(0.4, 0.5, k), w)
    waist, shoulders = base + 1.2, base + h - 0.27
    _segment(solids, boxes, (-0.02 * length, -0.2 * length), (base + 1.0, waist), torso_w, clothes)
    _segment(solids, boxes, (0.08 * length, -0.1 * length), (waist, shoulders), torso_w, clothes)
    _segment(solids, boxes, (bar, 0.08 * length), (grip, shoulders - 0.1), torso_w, clothes, 0.6)  # arms
    head = _offset(boxes, 0.1 * length)
    solids.cylinders(head, shoulders, base + h, 0.1, rng.uniform(0.2, 0.4, k))
