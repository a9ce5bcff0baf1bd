"""The simulator's scenes (lidar/sim): layouts and their structure, vegetation, facades, crossfall,
and labels that keep clear of the scenery."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from lidar.sim import SceneConfig, Sensor, actors, sensor_spec
from lidar.sim.clutter import Spot, _jersey
from lidar.sim.facades import URBAN_FACADE, Front, building
from lidar.sim.ground import Ground
from lidar.sim.layout import OPEN, SUBURBAN, URBAN, Road, make_ground
from lidar.sim.parts import (
    BUILDING,
    FURNITURE,
    INTERIOR,
    SLAB,
    TARGET,
    VEGETATION,
    Obstacles,
    TaggedSolidList,
)
from lidar.sim.raycast import Rays, SolidList, cast_solids
from lidar.sim.scene import PEDESTRIAN, VEHICLE, make_scene
from lidar.sim.vegetation import hedge
from lidar.types import points_in_boxes

HEIGHT = 1.73
RAYS = Rays.spinning(1000, sensor_spec(Sensor.HDL64E).elevations_deg)


DEFAULT = SceneConfig()


def _scene(seed: int, cfg: SceneConfig = DEFAULT):
    return make_scene(np.random.default_rng(seed), cfg, HEIGHT, 75.0)


@pytest.fixture(scope="module")
def scenes() -> dict[int, list]:
    """Four scenes of each layout."""
    out: dict[int, list] = {URBAN: [], SUBURBAN: [], OPEN: []}
    for layout in out:
        probs = tuple(float(k == layout) for k in range(3))
        out[layout] = [_scene(seed, SceneConfig(layouts=probs)) for seed in range(4)]
    return out


def _hit_shares(scene) -> np.ndarray:
    """Share of the solid hits within 40 m per tag (HDL-64E, 1,000 firings)."""
    hits = cast_solids(scene.solids, RAYS, 1.0, np.random.default_rng(0))
    tags = scene.tags[hits.solid[hits.t < 40]]
    return np.bincount(tags, minlength=8) / max(1, len(tags))


def test_all_layouts_are_drawn():
    layouts = {_scene(seed).layout for seed in range(30)}
    assert layouts == {URBAN, SUBURBAN, OPEN}


def test_each_layout_has_its_defining_structure(scenes):
    for scene in scenes[URBAN]:  # building fronts dominate, some rays enter through windows
        share = _hit_shares(scene)
        assert share[BUILDING] > share[VEGETATION] and share[BUILDING] > 0.1, share
        assert share[INTERIOR] > 0.005, share
    for scene in scenes[OPEN]:  # vegetation dominates what stands beside the road
        share = _hit_shares(scene)
        scenery = share[VEGETATION] / share[SLAB + 1 : TARGET].sum()  # of the returns off slabs and targets
        assert share[VEGETATION] > 0.05 and scenery > 0.7, share
    parked_in_drives = 0
    for scene in scenes[SUBURBAN]:  # houses set back, cars in driveways (across the road)
        share = _hit_shares(scene)
        assert share[BUILDING] > 0.02 and share[VEGETATION] > 0.02, share
        road, vehicles = scene.roads[0], scene.boxes[scene.labels == VEHICLE]
        _, lateral = road.local(vehicles[:, :2])
        off_road = np.abs(lateral) > min(-road.back(-1), road.back(1))  # beyond the sidewalks
        for other in scene.roads[1:]:
            off_road &= ~other.overlaps(vehicles[:, :2], margin=other.sidewalk)
        parked_in_drives += int(off_road.sum())
    assert parked_in_drives > 0


def test_same_seed_same_scene():
    a, b = _scene(11), _scene(11)
    assert a.layout == b.layout and np.array_equal(a.boxes, b.boxes) and np.array_equal(a.tags, b.tags)
    assert np.array_equal(a.solids.centre, b.solids.centre) and np.array_equal(a.solids.z, b.solids.z)


def test_targets_keep_clear_of_the_scenery_and_the_ego_car():
    for seed in range(8):
        scene = _scene(seed)
        assert len(scene.tags) == len(scene.solids)
        scenery = scene.tags != TARGET
        obstacles = Obstacles.of(scene.solids.select(scenery), scene.tags[scenery])
        for box in scene.boxes:
            assert obstacles.clear(box), (seed, box)
            assert math.hypot(box[0], box[1]) > 1.0  # not on the sensor


def _pedestrian_company(seeds: range) -> tuple[float, float]:
    """Share of pedestrians with another within 1.2 m, and with a piece of street furniture within 1.5 m."""
    grouped, beside, n = 0, 0, 0
    for seed in seeds:
        scene = _scene(seed, SceneConfig(pedestrians=(15, 15)))
        peds = scene.boxes[scene.labels == PEDESTRIAN]
        furniture = scene.solids.centre[scene.tags == FURNITURE]
        apart = np.hypot(*(peds[:, None, :2] - peds[None, :, :2]).transpose(2, 0, 1)) + 99 * np.eye(len(peds))
        to_furniture = np.hypot(*(peds[:, None, :2] - furniture[None, :, :2]).transpose(2, 0, 1))
        grouped += int((apart.min(1) < 1.2).sum())
        beside += int((to_furniture.min(1) < 1.5).sum())
        n += len(peds)
    return grouped / n, beside / n


def test_pedestrians_stand_in_groups_and_beside_street_furniture(monkeypatch):
    """Real pedestrians come in company: groups 0.8-0.9 m apart, people by poles, signs and trees (the
    model card's diagnosis). Without the groups and `actors.BESIDE` few would."""
    grouped, beside = _pedestrian_company(range(6))
    assert grouped > 0.35 and beside > 0.25, (grouped, beside)
    monkeypatch.setattr(actors, "BESIDE", 0.0)
    monkeypatch.setattr(actors, "GROUP_SQUEEZE", 1.0)  # members' free space overlaps: groups break up
    alone, away = _pedestrian_company(range(6))
    assert alone < grouped / 2 and away < beside * 0.6, (alone, away)


def _behind_vehicles(seeds: range) -> float:
    """Share of pedestrians whose line of sight from the sensor to their legs (0.3 m up) passes through a
    vehicle's label box."""
    behind, n = 0, 0
    for seed in seeds:
        scene = _scene(seed, SceneConfig(pedestrians=(15, 15)))
        cars = scene.boxes[scene.labels == VEHICLE]
        for ped in scene.boxes[scene.labels == PEDESTRIAN]:
            legs = np.array([ped[0], ped[1], ped[2] - ped[5] / 2 + 0.3])
            sight = np.linspace(0.05, 0.95, 40)[:, None] * legs  # (40, 3) points on the line
            behind += bool(points_in_boxes(sight, cars).any())
            n += 1
    return behind / n


def test_pedestrians_stand_behind_vehicles(monkeypatch):
    """Most well-seen real pedestrians show their upper body over a car (the model card's diagnosis):
    `actors.BEHIND` puts a share of them there (0 in the shipped world); without it fewer stand so."""
    monkeypatch.setattr(actors, "BEHIND", 0.3)
    behind = _behind_vehicles(range(8))
    monkeypatch.setattr(actors, "BEHIND", 0.0)
    alone = _behind_vehicles(range(8))
    assert behind > alone + 0.1, (behind, alone)


def test_concrete_barriers_stand_end_to_end_along_the_curb():
    solids = TaggedSolidList()
    spot = Spot(np.array([5.0, 3.0]), 0.15, 0.3, 0, 1)
    half = _jersey(solids, np.random.default_rng(3), spot)
    built = solids.build()
    along = (built.centre - spot.xy) @ np.array([math.cos(0.3), math.sin(0.3)])
    assert len(built) % 2 == 0 and 4 <= len(built) <= 8  # 2-4 segments, each a foot and a top
    assert np.allclose(np.unique(np.round(along, 3)).sum(), 0.0, atol=1e-6)  # centred on the spot
    reach = np.ptp(along) / 2 + built.half[0, 0]  # the run's half length
    assert reach - 0.15 <= half <= reach  # its footprint radius leaves out the gaps between segments
    assert 0.8 + 0.15 <= built.z[:, 1].max() <= 1.05 + 0.15


def test_obstacles_test_footprints_and_heights():
    solids = TaggedSolidList()
    solids.tag = VEGETATION
    solids.cylinders(np.array([[0.0, 0.0]]), 2.5, 6.0, 2.0, 0.5, 0.4)  # a crown from 2.5 m up
    solids.boxes(np.array([[10.0, 0.0]]), 0.0, 1.5, 4.0, 1.0, math.pi / 4, 0.5)  # a yawed hedge piece
    solids.tag = SLAB
    solids.boxes(np.array([[0.0, 0.0]]), -0.5, 0.0, 50.0, 50.0, 0.0, 0.3)  # ground: never an obstacle
    obstacles = Obstacles.of(solids.build(), solids.tags())
    car = np.array([0.5, 0.0, 0.8, 4.4, 1.9, 1.6, 0.0])
    assert obstacles.clear(car)  # under the crown
    assert not obstacles.clear(car + np.array([0, 0, 1.0, 0, 0, 0, 0]))  # up in the crown
    assert not obstacles.clear(np.array([12.0, 0.0, 0.8, 4.4, 1.9, 1.6, 0.0]))  # its end in the hedge
    assert obstacles.clear(np.array([10.0, -3.0, 0.8, 4.4, 1.9, 1.6, math.pi / 4]))  # parallel beside it


def _flat() -> Ground:
    return Ground(HEIGHT, np.zeros(2), np.zeros(0), np.zeros((0, 2)), np.zeros(0), 0.15, np.zeros((0, 8)))


def test_windows_let_rays_into_the_building():
    """A facade 10 m away: rays pass its window openings and return from the interior wall behind it."""
    road = Road(np.zeros(2), 0.0, 1, 3.5, (False, False), 2.0, 3.0, 0.0)  # back of the left sidewalk: y 6.5
    solids = TaggedSolidList()
    rng = np.random.default_rng(1)
    building(solids, rng, Front(road, 1, (-15.0, 15.0), 3.5, 15.0), _flat(), 4, URBAN_FACADE)
    scene_solids, tags = solids.build(), solids.tags()
    hits = cast_solids(scene_solids, RAYS, 1.0, rng)
    d = RAYS.directions(*np.divmod(hits.ray, len(RAYS.elevation)))
    y = hits.t * d[1]  # (H,) how far from the road each return lies
    inner = tags[hits.solid] == INTERIOR
    assert inner.sum() > 50 and (tags[hits.solid] == BUILDING).sum() > inner.sum()
    facade = tags[hits.solid] == BUILDING
    assert y[inner].min() > y[facade].min() + 2.0  # the facade layer and a cavity of 2 m or more
    assert np.ptp(y[facade]) > 0.3  # bays stepping back and forth, recessed doors: not one flat wall


@pytest.mark.parametrize("awnings", [True, False])
def test_shop_awnings_roof_part_of_the_sidewalk(awnings: bool):
    """Shopfront bays with awnings (`FacadeStyle.awning_prob`): returns over the sidewalk, 2.3-3.4 m above
    it, where a building without them has nothing (seen by a VLP-32C: beams up to 15 degrees)."""
    road = Road(np.zeros(2), 0.0, 1, 3.5, (False, False), 2.0, 3.0, 0.0)  # sidewalk: y 3.5 to 6.5
    style = dataclasses.replace(URBAN_FACADE, shopfront_prob=1.0, awning_prob=1.0 if awnings else 0.0)
    solids = TaggedSolidList()
    rng = np.random.default_rng(4)
    building(solids, rng, Front(road, 1, (-15.0, 15.0), 0.5, 15.0), _flat(), 3, style)
    rays = Rays.spinning(1000, sensor_spec(Sensor.VLP32C).elevations_deg)
    hits = cast_solids(solids.build(), rays, 1.0, rng)
    x, y, z = hits.t * rays.directions(*np.divmod(hits.ray, len(rays.elevation)))
    over = (y > 3.5) & (y < 6.5) & (np.abs(x) < 15) & (z > 2.0 - HEIGHT) & (z < 3.5 - HEIGHT)
    if awnings:
        assert over.sum() > 20 and z[over].min() > 1.9 - HEIGHT  # the valance hangs at most 0.4 m lower
    else:
        assert over.sum() == 0


def test_a_hedge_is_porous_and_irregular():
    solids = TaggedSolidList()
    rng = np.random.default_rng(2)
    hedge(solids, rng, np.array([-15.0, 6.0]), 0.0, 30.0, lambda xy: np.full(len(xy), -HEIGHT), (1.0, 1.6))
    hits = cast_solids(solids.build(), RAYS, 1.0, rng)
    f, b = np.divmod(hits.ray, len(RAYS.elevation))
    dx, dy, dz = RAYS.directions(f, b)
    y, z = hits.t * dy, hits.t * dz
    assert np.std(y) > 0.15  # returns from different depths
    seen = np.zeros(RAYS.count, bool)
    seen[hits.ray] = True
    ahead = np.abs(RAYS.azimuth - math.pi / 2) < 0.5  # firings towards the middle of the hedge
    low = (RAYS.elevation < math.atan2(0.6 - HEIGHT, 7.0)) & (RAYS.elevation > math.atan2(-HEIGHT, 5.5))
    through = ~seen.reshape(len(RAYS.azimuth), -1)[ahead][:, low]  # rays that would meet it below 0.6 m
    assert low.sum() >= 5 and 0.02 < through.mean() < 0.6, through.mean()  # some pass it entirely
    tops = [z[(np.abs(hits.t * dx - s) < 0.5)].max() for s in (-10.0, -5.0, 0.0, 5.0, 10.0)]
    assert np.ptp(tops) > 0.05  # its top is not one straight line


def test_crossfall_tilts_the_road_and_rays_land_on_it():
    road = Road(np.array([0.0, 1.75]), 0.0, 2, 3.5, (True, True), 2.2, 3.0, 0.15)  # sensor 1.75 m right
    rng = np.random.default_rng(3)
    ground = make_ground(rng, HEIGHT, 0.0, 0.0, [road], (0.02, 0.02))
    lateral = np.array([0.0, 3.0, 6.0, road.edge(1), road.edge(1) + 3.0])
    z = ground.height_at(np.zeros(5), road.origin[1] + lateral)
    drop = z[0] - z
    assert np.allclose(drop[1:4], 0.02 * (np.hypot(lateral[1:4], 0.5) - 0.5), atol=1e-6)
    assert drop[4] == pytest.approx(drop[3])  # flat beyond the curb
    assert z[0] > -HEIGHT  # the crown is higher than the ground under the sensor
    t = ground.cast(RAYS, 75.0, np.full(RAYS.count, np.inf, np.float32))
    ok = np.isfinite(t)
    dx, dy, dz = RAYS.directions(*np.divmod(np.arange(RAYS.count)[ok], len(RAYS.elevation)))
    hx, hy, hz = t[ok] * dx, t[ok] * dy, t[ok] * dz
    assert ok.mean() > 0.5 and np.abs(hz - ground.height_at(hx, hy)).max() < 0.025


def test_rays_of_a_moving_sensor_land_on_the_ground_from_where_they_start():
    """A sensor moving during the sweep casts each firing from its own start (lidar.sim.ego): the
    ground is met from there, not from the origin (a 4 % grade and 1.5 m of travel: 6 cm off otherwise)."""
    road = Road(np.array([0.0, 1.75]), 0.3, 2, 3.5, (True, True), 2.2, 3.0, 0.15)
    ground = make_ground(np.random.default_rng(5), HEIGHT, 0.04, 0.1, [road], (0.02, 0.02))
    firings = len(RAYS.azimuth)
    travel = np.linspace(-1.5, 0.0, firings)  # (F,) metres along x, ending at the origin
    starts = np.stack([travel, 0.2 * travel, ground.height_at(travel, 0.2 * travel) + HEIGHT], 1)
    rays = Rays(RAYS.azimuth, RAYS.elevation, RAYS.azimuth_offset, starts)
    t = ground.cast(rays, 75.0, np.full(rays.count, np.inf, np.float32))
    ok = np.isfinite(t)
    f, b = np.divmod(np.arange(rays.count)[ok], len(rays.elevation))
    (dx, dy, dz), (ox, oy, oz) = rays.directions(f, b), rays.starts(f)
    hx, hy, hz = ox + t[ok] * dx, oy + t[ok] * dy, oz + t[ok] * dz
    assert ok.mean() > 0.5 and np.abs(hz - ground.height_at(hx, hy)).max() < 0.025


def test_foliage_returns_a_volume_and_a_wall_its_surface():
    """A porous solid returns from leaves at random depths inside it (VOLUME_DEPTH), a wall from its face."""
    solids = SolidList()
    solids.boxes(np.array([[10.0, 0.0]]), -1.7, 1.0, 3.0, 3.0, 0.0, 0.3, 0.4)  # a hedge-like block ahead
    solids.boxes(np.array([[-10.0, 0.0]]), -1.7, 1.0, 3.0, 3.0, 0.0, 0.3, 0.0)  # a wall block behind
    hits = cast_solids(solids.build(), RAYS, 1.0, np.random.default_rng(0))
    f, b = np.divmod(hits.ray, len(RAYS.elevation))
    dx, _, _ = RAYS.directions(f, b)
    x = hits.t * dx  # (H,) the hits' x: 8.5 is either block's face
    front, back = x[x > 0], -x[x < 0]
    assert np.abs(back - 8.5).max() < 0.01
    assert 0.2 < (front - 8.5).mean() < 0.6 and (front - 8.5).max() < 3.01
