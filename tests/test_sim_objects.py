"""The simulator's objects (lidar/sim/vehicles.py, people.py): tight label boxes around every part, body
types, glass that lets most rays through, wheels, articulated legs, strollers and parked trailers."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from lidar.sim import (
    SceneConfig,
    Sensor,
    SimConfig,
    actors,
    people,
    sensor_spec,
    simulate,
    stats,
    vehicles,
)
from lidar.sim.ground import Ground
from lidar.sim.layout import Occupancy, make_ground
from lidar.sim.parts import FURNITURE, TARGET, Obstacles, TaggedSolidList
from lidar.sim.raycast import BOX, OPAQUE, SURFACE, VOLUME, Rays, SolidList, Solids, cast_solids
from lidar.sim.scene import Scene, make_roads, make_scene
from lidar.sim.simulate import cast_scene
from lidar.types import points_in_boxes

HEIGHT = 1.73
CFG = replace(SimConfig(), dropout=0.0, range_noise=0.0)
RAYS = Rays.spinning(CFG.firings, sensor_spec(Sensor.HDL64E).elevations_deg)


def _flat_street() -> Ground:
    return Ground(HEIGHT, np.zeros(2), np.zeros(0), np.zeros((0, 2)), np.zeros(0), 0.15, np.zeros((0, 8)))


def _box(x: float, y: float, size: tuple[float, float, float], yaw: float) -> np.ndarray:
    return np.array([x, y, -HEIGHT + size[2] / 2, *size, yaw])


def _extent(s: Solids, box: np.ndarray) -> np.ndarray:
    """Every solid's reach in the box frame -> (P, 6) along min/max, across min/max, z min/max."""
    c, sn = math.cos(box[6]), math.sin(box[6])
    rel = s.centre - box[:2]
    u, v = rel[:, 0] * c + rel[:, 1] * sn, -rel[:, 0] * sn + rel[:, 1] * c
    d = s.yaw - box[6]
    box_kind = s.kind == BOX
    hu = np.where(box_kind, np.abs(np.cos(d)) * s.half[:, 0] + np.abs(np.sin(d)) * s.half[:, 1], s.half[:, 0])
    hv = np.where(box_kind, np.abs(np.sin(d)) * s.half[:, 0] + np.abs(np.cos(d)) * s.half[:, 1], s.half[:, 0])
    return np.stack([u - hu, u + hu, v - hv, v + hv, s.z[:, 0], s.z[:, 1]], 1)


def _assert_tight(s: Solids, box: np.ndarray, what: str) -> None:
    """Every solid inside the label box, and the solids reach each of its six faces (within 3 cm)."""
    e = _extent(s, box)
    half = np.array([box[3], box[4]]) / 2
    bottom, top = box[2] - box[5] / 2, box[2] + box[5] / 2
    eps = 1e-6
    assert e[:, 0].min() >= -half[0] - eps and e[:, 1].max() <= half[0] + eps, what
    assert e[:, 2].min() >= -half[1] - eps and e[:, 3].max() <= half[1] + eps, what
    assert e[:, 4].min() >= bottom - eps and e[:, 5].max() <= top + eps, what
    reach = [-e[:, 0].min(), e[:, 1].max(), -e[:, 2].min(), e[:, 3].max()]
    assert np.allclose(reach, [half[0], half[0], half[1], half[1]], atol=0.03), (what, reach, half)
    assert abs(e[:, 5].max() - top) < 0.03 and abs(e[:, 4].min() - bottom) < 0.03, what


def _mirrors(s: Solids, box: np.ndarray) -> np.ndarray:
    """(P,) bool: the solids that stand out of the label box's sides."""
    e = _extent(s, box)
    return (e[:, 2] < -box[4] / 2 - 1e-6) | (e[:, 3] > box[4] / 2 + 1e-6)


@pytest.mark.parametrize("kind", range(len(stats.BODY_NAMES)))
def test_every_body_type_fills_a_tight_label_box(kind):
    rng = np.random.default_rng(kind)
    for i in range(10):
        size = tuple(stats.BODY_SIZES[kind].draw(rng, 1)[0])
        box = _box(rng.uniform(-30, 30), rng.uniform(-30, 30), size, rng.uniform(-math.pi, math.pi))
        solids = SolidList()
        vehicles.vehicle_solids(solids, rng, box[None], np.array([kind]))
        s = solids.build()
        mirrors = _mirrors(s, box)
        # the body fills the label box short of the annotation margin (on every face but the bottom)
        body = vehicles.body_boxes(box[None])[0]
        assert (
            np.allclose(body[3:6], box[3:6] - [0.08, 0.08, 0.04])
            and body[2] - body[5] / 2 == box[2] - box[5] / 2
        )
        _assert_tight(s.select(~mirrors), body, f"{stats.BODY_NAMES[kind]} {i}")
        # the side mirrors, and nothing else, stand out of the label box's sides, as annotators leave them out
        e = _extent(s.select(mirrors), box)
        trailer = kind == stats.TRAILER
        assert mirrors.sum() == (0 if trailer else 2), (stats.BODY_NAMES[kind], mirrors.sum())
        if not trailer:
            out = np.maximum(-e[:, 2], e[:, 3]) - box[4] / 2  # (2,) how far each stands out
            assert np.all((out > 0.03) & (out < 0.17)) and e[:, 2].min() < 0 < e[:, 3].max()
            assert e[:, 0].min() > 0 and e[:, 4].min() > box[2] - box[5] / 2 + 0.5  # ahead, above the sill


@pytest.mark.parametrize("carry", [people.PLAIN, people.BACKPACK, people.HANDBAG, people.STROLLER])
def test_pedestrians_fill_tight_boxes_and_a_stroller_stays_out_of_it(carry):
    rng = np.random.default_rng(carry)
    sizes, _ = people.pedestrian_sizes(rng, 20)
    for size in sizes:
        box = _box(rng.uniform(-20, 20), rng.uniform(-20, 20), tuple(size), rng.uniform(-math.pi, math.pi))
        solids = TaggedSolidList()
        solids.tag = TARGET
        people.pedestrian_solids(solids, rng, box[None], np.array([carry]))
        s, tags = solids.build(), solids.tags()
        _assert_tight(s.select(tags == TARGET), box, f"carry {carry}")
        stroller = s.select(tags == FURNITURE)
        assert (len(stroller) > 0) == (carry == people.STROLLER)
        if len(stroller):  # ahead of the pedestrian, clear of the box
            assert _extent(stroller, box)[:, 0].min() > box[3] / 2


@pytest.mark.parametrize("kind", [people.BICYCLE, people.MOTORCYCLE])
def test_cyclists_fill_tight_boxes(kind):
    rng = np.random.default_rng(kind)
    sizes, kinds = people.cyclist_sizes(rng, 2000)
    assert 0.15 < (kinds == people.MOTORCYCLE).mean() < 0.25
    assert np.all(sizes[kinds == people.MOTORCYCLE, 0] >= stats.MOTORCYCLE.low[0])
    for _ in range(10):
        size = tuple((stats.MOTORCYCLE if kind else stats.CYCLIST).draw(rng, 1)[0])
        box = _box(rng.uniform(-20, 20), rng.uniform(-20, 20), size, rng.uniform(-math.pi, math.pi))
        solids = SolidList()
        people.cyclist_solids(solids, rng, box[None], np.array([kind]))
        s = solids.build()
        e = _extent(s, box)
        assert e[:, 0].min() >= -box[3] / 2 - 1e-6 and e[:, 1].max() <= box[3] / 2 + 1e-6
        assert e[:, 2].min() >= -box[4] / 2 - 1e-6 and e[:, 3].max() <= box[4] / 2 + 1e-6
        assert abs(e[:, 5].max() - (box[2] + box[5] / 2)) < 1e-6 and abs(e[:, 1].max() - box[3] / 2) < 0.01


def _cast(solids: SolidList, box: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One object on a flat street, no noise -> its points above the street (N, 4), u (along the heading,
    metres from the box centre) and their height above the street."""
    scene = Scene((), _flat_street(), solids.build(), box[None], np.zeros(1, np.int64))
    points, _ = cast_scene(np.random.default_rng(seed), scene, RAYS, CFG)
    up = points[:, 2] + HEIGHT
    near = (up > 0.03) & (np.hypot(points[:, 0] - box[0], points[:, 1] - box[1]) < 8)
    p = points[near]
    u = (p[:, 0] - box[0]) * math.cos(box[6]) + (p[:, 1] - box[1]) * math.sin(box[6])
    return p, u, up[near]


def test_labels_enclose_every_point_of_their_object():
    rng = np.random.default_rng(3)
    for kind in range(len(stats.BODY_NAMES)):
        size = tuple(stats.BODY_SIZES[kind].mean)
        box = _box(10.0, 4.0, size, rng.uniform(-math.pi, math.pi))
        solids = SolidList()
        vehicles.vehicle_solids(solids, rng, box[None], np.array([kind]))
        points, _, _ = _cast(solids, box)
        assert len(points) > 50
        inside = points_in_boxes(points[:, :3], box[None].astype(np.float32))[:, 0]  # (N,)
        assert inside.mean() > 0.95, stats.BODY_NAMES[kind]
        grown = box.copy()
        grown[4] += 0.4  # the rest are on the mirrors, out of the sides
        assert points_in_boxes(points[:, :3], grown[None].astype(np.float32)).all(), stats.BODY_NAMES[kind]


def test_labels_enclose_the_noisy_returns_of_the_body_as_annotators_draw_them():
    rng = np.random.default_rng(4)
    for kind in (stats.SEDAN, stats.SUV, stats.BOX_TRUCK):
        for yaw in (0.0, math.pi / 2, 2.5):  # seen end-on, side-on, obliquely
            box = _box(12.0, 0.0, tuple(stats.BODY_SIZES[kind].mean), yaw)
            solids = SolidList()
            vehicles.vehicle_solids(solids, rng, box[None], np.array([kind]))
            scene = Scene((), _flat_street(), solids.build(), box[None], np.zeros(1, np.int64))
            noisy = replace(CFG, range_noise=0.02)
            points, _ = cast_scene(np.random.default_rng(0), scene, RAYS, noisy)
            p = points[(points[:, 2] + HEIGHT > 0.1) & (np.hypot(points[:, 0] - 12.0, points[:, 1]) < 8)]
            beside = box.copy()
            beside[3:6] += [0.2, 0.4, 0.2]  # the body's returns and its mirrors'
            body = points_in_boxes(p[:, :3], beside[None].astype(np.float32))[:, 0]  # (N,)
            across = -(p[:, 0] - box[0]) * math.sin(yaw) + (p[:, 1] - box[1]) * math.cos(yaw)  # (N,)
            within = body & (np.abs(across) <= box[4] / 2)  # not the mirrors out of the sides
            inside = points_in_boxes(p[within, :3], box[None].astype(np.float32))[:, 0]
            what = (stats.BODY_NAMES[kind], yaw)
            # a body whose faces were the label's leaves 8-16 % of them out (end-on and oblique views)
            assert within.sum() > 1000 and inside.mean() > 0.99, (*what, inside.mean())
            assert (body & ~within).sum() < 0.05 * body.sum(), what


def test_a_sedan_at_10_m_shows_its_wheels_under_the_body_and_little_glass(monkeypatch):
    box = _box(0.0, 10.0, (4.75, 1.96, 1.47), 0.0)  # side-on
    counts = {}
    for porosity in (vehicles.GLASS_POROSITY, 0.0):
        monkeypatch.setattr(vehicles, "GLASS_POROSITY", porosity)
        solids = SolidList()
        vehicles.vehicle_solids(solids, np.random.default_rng(0), box[None], np.array([stats.SEDAN]))
        p, u, up = _cast(solids, box)
        v = p[:, 1] - box[1]
        # the near side's glass face (at 0.46 w; the seat backs behind it reach 0.4 w)
        side_windows = (up > 1.05) & (up < 1.37) & (np.abs(v) > 0.42 * box[4])
        counts[porosity] = int(side_windows.sum())
        if porosity:
            low = np.abs(u[up < 0.12])  # below the body: only the wheels
            assert len(low) > 10
            assert np.all((low > 0.2 * 4.75) & (low < 0.45 * 4.75)), low  # none between the axles
    opaque = counts[0.0]
    glass = next(c for k, c in counts.items() if k > 0)
    assert opaque > 80 and glass < 0.5 * opaque, counts  # pillars and the glass returns that remain


def test_glass_lets_most_rays_through_and_returns_from_its_face():
    solids = SolidList()
    solids.boxes(np.array([[10.0, 0.0]]), -1.0, 1.0, 0.2, 6.0, 0.0, 0.1, 0.85, SURFACE)
    solids.boxes(np.array([[-10.0, 0.0]]), -1.0, 1.0, 0.2, 6.0, 0.0, 0.1, 0.0)  # the same, behind
    s = solids.build()
    assert s.material.tolist() == [SURFACE, OPAQUE]
    hits = cast_solids(s, RAYS, 1.0, np.random.default_rng(0))
    glass, wall = (hits.solid == 0), (hits.solid == 1)
    assert 0.08 < glass.sum() / wall.sum() < 0.25
    x = hits.t[glass] * np.cos(RAYS.elevation[hits.ray[glass] % len(RAYS.elevation)])
    assert np.abs(np.abs(x * np.cos(RAYS.azimuth[hits.ray[glass] // 64])) - 9.9).max() < 0.02  # on the face
    leaves = SolidList()
    leaves.cylinders(np.array([[10.0, 0.0]]), -1.0, 1.0, 1.0, 0.4, 0.5)
    assert leaves.build().material.tolist() == [VOLUME]


def test_a_walker_s_legs_split_and_a_standing_person_s_do_not():
    gaps = {}
    for name, length in (("walking", 0.95), ("standing", 0.36)):
        box = _box(0.0, 7.0, (length, 0.6, 1.75), 0.0)
        solids = SolidList()
        people.pedestrian_solids(solids, np.random.default_rng(1), box[None], np.array([people.PLAIN]))
        _, u, up = _cast(solids, box)
        knee = np.sort(u[(up > 0.25) & (up < 0.45)])
        assert len(knee) > 10, name
        gaps[name] = float(np.diff(knee).max())
    assert gaps["walking"] > 0.2 and gaps["standing"] < 0.1, gaps


def test_candidates_draw_every_body_type_and_turning_traffic():
    rng = np.random.default_rng(0)
    large = rng.random(4000) < 0.3
    kinds = vehicles.body_kinds(rng, large)
    assert set(np.unique(kinds).tolist()) == set(range(len(stats.BODY_NAMES)))
    assert np.all((kinds >= stats.BOX_TRUCK) == large)
    assert not np.isin(vehicles.body_kinds(rng, large, trailers=False), [stats.TRAILER]).any()
    cfg = SceneConfig(parking_prob=0.0, lanes=(3, 3), intersection_prob=0.0)
    roads = make_roads(rng, cfg)
    ground = make_ground(rng, HEIGHT, 0.0, 0.0, roads, (0.0, 0.0))
    cands = actors.vehicle_candidates(rng, roads, ground, 75.0)
    off = np.abs(np.angle(np.exp(1j * (cands.boxes[:, 6] - roads[0].yaw))))
    off = np.minimum(off, math.pi - off)  # oncoming lanes head the other way
    turning = (off > 0.15).mean()
    assert 0.04 < turning < 0.2, turning  # TURNING of them, by TURN_RAD
    assert np.array_equal(cands.kind >= stats.BOX_TRUCK, cands.large) and len(np.unique(cands.kind)) >= 5


def test_parked_trailers_stand_in_parking_lanes_unlabelled(monkeypatch):
    monkeypatch.setattr(actors, "TRAILERS", (1.0, 2))
    cfg = SceneConfig(parking_prob=1.0)
    placed = 0
    for seed in range(6):
        rng = np.random.default_rng(seed)
        roads = make_roads(rng, cfg)
        ground = make_ground(rng, HEIGHT, 0.0, 0.0, roads, (0.0, 0.0))
        occ = Occupancy()
        empty = TaggedSolidList()
        trailers = actors.parked_trailers(
            rng, roads, ground, occ, 40.0, Obstacles.of(empty.build(), empty.tags())
        )
        placed += len(trailers)
        for box in trailers:
            lateral = [abs(float(np.dot(box[:2] - r.origin, r.n))) for r in roads]
            lanes = [r.lanes * r.lane_width + r.parking_width / 2 for r in roads]
            assert min(abs(a - b) for a, b in zip(lateral, lanes, strict=True)) < 0.05
            solids = SolidList()
            vehicles.utility_trailer_solids(solids, rng, box[None])
            _assert_tight(solids.build(), box, "trailer")
    assert placed >= 6
    scene = make_scene(np.random.default_rng(0), cfg, HEIGHT, 75.0)
    trailer_like = (scene.tags == FURNITURE) & (scene.solids.kind == BOX)
    assert trailer_like.any() and len(scene.labels) == len(scene.boxes)


def test_same_seed_same_objects_other_seed_other_objects():
    a, b, c = simulate(11), simulate(11), simulate(12)
    assert np.array_equal(a.points, b.points) and np.array_equal(a.gt.boxes, b.gt.boxes)
    assert not np.array_equal(a.gt.boxes[: len(c.gt.boxes)], c.gt.boxes[: len(a.gt.boxes)])


def test_the_car_mix_matches_the_public_and_the_samples_class_means():
    mix = sum(p * np.array(stats.BODY_SIZES[k].mean) for k, p in enumerate(stats.CAR_BODIES))
    assert math.isclose(sum(stats.CAR_BODIES), 1.0) and math.isclose(sum(stats.LARGE_BODIES), 1.0)
    for reference in ((4.63, 1.97, 1.74), (4.73, 2.08, 1.77), stats.CAR.mean):  # nuScenes, Waymo, samples
        assert np.all(np.abs(mix - np.array(reference)) < (0.3, 0.1, 0.12)), (mix, reference)
