"""A random street scene around the sensor: a layout (urban, suburban, open), roads, ground, sidewalks, what
stands beside the roads (frontage.py), clutter and targets."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from lidar.sim import actors, vehicles
from lidar.sim.clutter import clutter
from lidar.sim.frontage import frontage
from lidar.sim.ground import Ground
from lidar.sim.layout import OPEN, SUBURBAN, URBAN, Occupancy, Road, make_ground, sidewalks
from lidar.sim.parts import FURNITURE, SLAB, TARGET, Obstacles, TaggedSolidList
from lidar.sim.raycast import Solids
from lidar.types import CLASS_NAMES

VEHICLE, PEDESTRIAN, CYCLIST = (CLASS_NAMES.index(n) for n in ("VEHICLE", "PEDESTRIAN", "CYCLIST"))
EGO_LENGTH, EGO_WIDTH = 4.8, 2.0  # the ego car around the sensor (nothing may overlap it)
PLACEMENT_ROUNDS = 3


@dataclass(frozen=True)
class SceneConfig:
    """Scene randomization. Counts are (min, max) inclusive, of objects within `place_radius` metres."""

    vehicles: tuple[int, int] = (10, 40)
    pedestrians: tuple[int, int] = (0, 20)
    cyclists: tuple[int, int] = (0, 6)
    place_radius: float = 50.0  # metres
    far_fraction: float = 0.25  # plus this many (relative to the count) between place_radius and the range
    clutter: tuple[int, int] = (30, 80)  # tries at placing street furniture and vegetation
    intersection_prob: float = 0.4  # a crossing road
    aligned_prob: float = 0.5  # road along the sensor's x axis (+-10 deg); else any orientation
    lanes: tuple[int, int] = (1, 3)  # driving lanes per direction
    lane_width: tuple[float, float] = (3.0, 3.8)
    parking_prob: float = 0.6  # a parking lane, per side
    parking_width: tuple[float, float] = (2.0, 2.6)
    sidewalk_width: tuple[float, float] = (2.0, 5.0)
    curb_height: tuple[float, float] = (0.1, 0.2)
    max_slope: float = 0.04  # road grade
    bump: float = 0.1  # metres, amplitude of each of three long ground waves
    crossfall: tuple[float, float] = (0.01, 0.03)  # camber of the sensor's road: drop per metre to the curbs
    layouts: tuple[float, float, float] = (0.45, 0.3, 0.25)  # chances of urban, suburban, open scenes


@dataclass(frozen=True)
class LayoutStyle:
    """How a layout changes the roads: sidewalk (a grass verge in the open), curb, lot depth, and factors on
    the parking chance and the clutter count. None: the SceneConfig's range."""

    sidewalk: tuple[float, float] | None
    curb: tuple[float, float] | None
    lot: float  # raised ground behind the sidewalk (m)
    parking: float
    clutter: float


STYLES = {
    URBAN: LayoutStyle(None, None, 12.0, 1.3, 1.0),
    SUBURBAN: LayoutStyle((1.5, 3.0), (0.1, 0.15), 25.0, 0.8, 0.5),
    OPEN: LayoutStyle((1.0, 3.0), (0.0, 0.05), 4.0, 0.3, 0.25),
}


@dataclass(frozen=True)
class Scene:
    roads: tuple[Road, ...]
    ground: Ground
    solids: Solids
    boxes: np.ndarray  # (M, 7) float64 label boxes, sensor frame, z the box centre
    labels: np.ndarray  # (M,) int64 index into CLASS_NAMES
    layout: int = URBAN
    tags: np.ndarray | None = None  # (P,) int8 what each solid is (parts.TAG_NAMES)


def _layout(rng: np.random.Generator, cfg: SceneConfig) -> int:
    p = np.asarray(cfg.layouts, np.float64)
    return int(rng.choice(len(p), p=p / p.sum()))


def _road(rng: np.random.Generator, cfg: SceneConfig, origin: np.ndarray, yaw: float, layout: int) -> Road:
    style = STYLES[layout]
    park = min(1.0, cfg.parking_prob * style.parking)
    return Road(
        origin=origin,
        yaw=yaw,
        lanes=int(rng.integers(cfg.lanes[0], cfg.lanes[1] + 1)),
        lane_width=float(rng.uniform(*cfg.lane_width)),
        parking=(bool(rng.random() < park), bool(rng.random() < park)),
        parking_width=float(rng.uniform(*cfg.parking_width)),
        sidewalk=float(rng.uniform(*(style.sidewalk or cfg.sidewalk_width))),
        curb=float(rng.uniform(*(style.curb or cfg.curb_height))),
        layout=layout,
        lot=style.lot,
    )


def make_roads(rng: np.random.Generator, cfg: SceneConfig, layout: int = URBAN) -> list[Road]:
    """Road 0 carries the sensor in one of its forward lanes; maybe a second road crosses it."""
    aligned = rng.random() < cfg.aligned_prob
    yaw = rng.uniform(-math.radians(10), math.radians(10)) if aligned else rng.uniform(-math.pi, math.pi)
    main = _road(rng, cfg, np.zeros(2), yaw, layout)
    lane = int(rng.integers(main.lanes))
    ego_lateral = -(lane + 0.5) * main.lane_width + rng.normal(0, 0.2)
    main = replace(main, origin=-ego_lateral * main.n)  # the sensor sits at lateral ego_lateral
    roads = [main]
    if rng.random() < cfg.intersection_prob:
        s = rng.uniform(-40, 40)
        cross = yaw + math.pi / 2 + rng.uniform(-math.radians(15), math.radians(15))
        roads.append(_road(rng, cfg, main.point(np.array(s), np.array(0.0)), cross, layout))
    return roads


def make_scene(rng: np.random.Generator, cfg: SceneConfig, height: float, reach: float) -> Scene:
    """A scene whose objects lie within `reach` metres of the sensor (label boxes by centre distance)."""
    layout = _layout(rng, cfg)
    roads = make_roads(rng, cfg, layout)
    ground = make_ground(rng, height, cfg.max_slope, cfg.bump, roads, cfg.crossfall)
    solids, occ = TaggedSolidList(), Occupancy()
    extent = reach + 10  # static scenery reaches a little beyond the range
    solids.tag = SLAB
    sidewalks(solids, rng, roads, ground, extent)
    ego = np.array([0.0, 0.0, 0.0, EGO_LENGTH, EGO_WIDTH, 1.5, roads[0].yaw])
    occ.take(*actors.discs(ego))
    slots = frontage(solids, occ, rng, roads, ground, extent)
    tries = round(int(rng.integers(cfg.clutter[0], cfg.clutter[1] + 1)) * STYLES[layout].clutter)
    beside = clutter(solids, occ, rng, roads, ground, tries, extent)
    obstacles = Obstacles.of(solids.build(), solids.tags())
    solids.tag = FURNITURE
    trailers = actors.parked_trailers(rng, roads, ground, occ, reach, obstacles)
    vehicles.utility_trailer_solids(solids, rng, trailers)
    solids.tag = TARGET
    boxes, labels = [], []
    for label, counts in ((VEHICLE, cfg.vehicles), (CYCLIST, cfg.cyclists), (PEDESTRIAN, cfg.pedestrians)):
        inside = int(rng.integers(counts[0], counts[1] + 1))
        outside = round(cfg.far_fraction * inside)
        for _ in range(PLACEMENT_ROUNDS):  # a new round of candidates fills what the last one could not
            tries = 3 * (inside + outside) + 5
            cars = np.concatenate(boxes)[np.concatenate(labels) == VEHICLE] if boxes else np.zeros((0, 7))
            cands = _candidates(rng, label, roads, ground, reach, tries, slots, beside, cars)
            chosen = actors.select(rng, cands, occ, inside, outside, cfg.place_radius, reach, obstacles)
            _build(solids, rng, label, chosen)
            boxes.append(chosen.boxes)
            labels.append(np.full(len(chosen.boxes), label, np.int64))
            near = int((np.hypot(chosen.boxes[:, 0], chosen.boxes[:, 1]) <= cfg.place_radius).sum())
            inside, outside = inside - near, outside - (len(chosen.boxes) - near)
            if inside == 0:
                break
    box_arr, label_arr = np.concatenate(boxes), np.concatenate(labels)
    return Scene(tuple(roads), ground, solids.build(), box_arr, label_arr, layout, solids.tags())


def _candidates(
    rng: np.random.Generator,
    label: int,
    roads: list[Road],
    ground: Ground,
    reach: float,
    tries: int,
    slots: np.ndarray,
    beside: np.ndarray,
    vehicles: np.ndarray,
) -> actors.Candidates:
    if label == VEHICLE:
        lanes = actors.vehicle_candidates(rng, roads, ground, reach)
        return actors.Candidates.join([lanes, actors.driveway_candidates(rng, slots)])
    if label == PEDESTRIAN:
        return actors.pedestrian_candidates(rng, roads, ground, reach, tries, beside, vehicles)
    return actors.cyclist_candidates(rng, roads, ground, reach, tries)


def _build(solids: TaggedSolidList, rng: np.random.Generator, label: int, chosen: actors.Candidates) -> None:
    if label == VEHICLE:
        actors.vehicle_solids(solids, rng, chosen)
    elif label == PEDESTRIAN:
        actors.pedestrian_solids(solids, rng, chosen.boxes, chosen.kind)
    else:
        actors.cyclist_solids(solids, rng, chosen.boxes, chosen.kind)
