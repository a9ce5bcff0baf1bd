"""The simulator's sensor side (lidar/sim): presets, per-seed variation, ego motion and roof returns,
intensity per sensor, and the sim-vs-real comparison."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import SHARED_DATA

from lidar.sim import SceneConfig, Sensor, SimConfig, sensor_spec, simulate
from lidar.sim.compare import (
    HEIGHT_EDGES,
    RANGE_EDGES,
    Cloud,
    RealSet,
    above_ground,
    cloud_stats,
    compare,
    format_tables,
    legs_hidden_counts,
)
from lidar.sim.ego import sweep_origins
from lidar.sim.ground import Ground
from lidar.sim.raycast import SolidList
from lidar.sim.scene import Scene
from lidar.sim.sensors import PAIR_RANGE, PAIR_SPACING, Unit
from lidar.sim.simulate import Source, cast_unit, draw_setup, simulate_sources
from lidar.types import points_in_boxes


def _elevation(points: np.ndarray, z0: float = 0.0) -> np.ndarray:
    return np.degrees(np.arctan2(points[:, 2] - z0, np.hypot(points[:, 0], points[:, 1])))


@pytest.mark.parametrize(
    ("sensor", "beams", "top", "bottom", "finest"),
    [
        (Sensor.HDL64E, 64, 2.0, -24.61, 1 / 3),
        (Sensor.WAYMO_TOP, 64, 2.563, -17.498, 0.154),
        (Sensor.HDL32E, 32, 10.67, -30.67, 1.33),
        (Sensor.VLP32C, 32, 15.0, -25.0, 1 / 3),
        (Sensor.VLS128, 128, 15.0, -25.0, 0.11),
        (Sensor.VLP32C_PAIR, 64, 25.0, -25.0, 0.0),
    ],
)
def test_presets_have_their_beam_counts_and_spans(sensor, beams, top, bottom, finest):
    e = sensor_spec(sensor).elevations_deg
    assert len(e) == beams and np.all(np.diff(e) <= 0)
    assert abs(e[0] - top) < 0.06 and abs(e[-1] - bottom) < 0.06, (e[0], e[-1])
    assert abs((-np.diff(e)).min() - finest) < 0.01


def test_vlp32c_is_the_datasheet_table_dense_near_the_horizon():
    e = sensor_spec(Sensor.VLP32C).elevations_deg
    assert {15.0, 10.333, 7.0, -11.31, -15.639, -25.0} <= set(np.round(e, 3).tolist())
    assert ((e > -4.1) & (e < 1.7)).sum() == 18  # the 1/3 deg core
    assert np.allclose(-np.diff(e)[6:23], 1 / 3, atol=0.002)


def test_the_pair_is_two_vlp32c_one_upside_down():
    spec = sensor_spec(Sensor.VLP32C_PAIR)
    upper, lower = spec.heads
    assert np.allclose(upper.elevations_deg, sensor_spec(Sensor.VLP32C).elevations_deg)
    assert np.allclose(lower.elevations_deg, -upper.elevations_deg[::-1])
    assert math.isclose(upper.z_offset - lower.z_offset, PAIR_SPACING)
    assert spec.max_range == PAIR_RANGE


def test_pair_points_come_from_both_units_out_to_its_range_and_labels_stay_within_range_max():
    scan = simulate(2, SimConfig(sensor=Sensor.VLP32C_PAIR))
    upper, lower = sensor_spec(Sensor.VLP32C_PAIR).heads
    p = scan.points
    for unit in (upper, lower):
        off = np.abs(_elevation(p, unit.z_offset)[:, None] - unit.elevations_deg[None]).min(axis=1)
        assert (off < 1e-3).mean() > 0.3  # about half the points are this unit's
    r = np.linalg.norm(p[:, :3], axis=1)
    assert r.max() > 80 and r.max() <= PAIR_RANGE
    assert np.hypot(scan.gt.boxes[:, 0], scan.gt.boxes[:, 1]).max() <= 75.0
    assert (_elevation(p) > 16).sum() > 100  # the upside-down unit looks up to +25 deg
    assert np.all(np.diff(scan.time) >= 0)


def test_varied_setups_draw_heights_in_range_and_jitter_deterministically_per_seed():
    cfg = SimConfig.varied()
    setups = [draw_setup(np.random.default_rng(seed), cfg) for seed in range(40)]
    assert {s.sensor for s in setups} == set(Sensor)
    heights = np.array([s.spec.height for s in setups])
    assert heights.min() >= 1.6 and heights.max() <= 2.3 and heights.std() > 0.1
    again = draw_setup(np.random.default_rng(7), cfg)
    assert np.array_equal(again.spec.elevations_deg, setups[7].spec.elevations_deg)
    for s in setups:
        preset = np.sort(sensor_spec(s.sensor).elevations_deg)
        error = np.sort(s.spec.elevations_deg) - preset
        assert 0.005 < np.abs(error).max() < 1.0, s.sensor  # jittered, by fractions of a degree
        offsets = np.concatenate([u.azimuth_offset_deg for u in s.spec.heads])
        assert 0 < np.abs(offsets).max() < 0.6
    assert len({round(s.speed, 3) for s in setups}) > 20 and max(s.speed for s in setups) <= 15
    assert len({s.intensity.gain for s in setups if s.sensor == Sensor.HDL32E}) > 1


def test_varied_scans_are_deterministic_and_vary():
    cfg = replace(SimConfig.varied(sensors=(Sensor.HDL32E, Sensor.VLP32C)), firings=600)
    a, b = simulate(3, cfg), simulate(3, cfg)
    assert np.array_equal(a.points, b.points) and np.array_equal(a.gt.boxes, b.gt.boxes)
    assert not np.array_equal(simulate(4, cfg).points[:100], a.points[:100])


def _flat_scene(with_box: bool) -> Scene:
    ground = Ground(1.73, np.zeros(2), np.zeros(0), np.zeros((0, 2)), np.zeros(0), 0.15, np.zeros((0, 8)))
    solids = SolidList()
    box = np.array([[-12.0, 0.0, -1.73 + 0.8, 4.5, 1.9, 1.6, 0.0]])
    if with_box:
        solids.boxes(box[:, :2], -1.73, -1.73 + 1.6, 4.5, 1.9, 0.0, 0.5)
    return Scene((), ground, solids.build(), box if with_box else np.zeros((0, 7)), np.zeros(1, np.int64))


def _cast_moving(scene: Scene, speed: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 4) and beams (N,) of firings 0..19 and 1980..1999 (both look backwards, along -x) of a
    still HDL-64E or one driving along +x at `speed`."""
    cfg = SimConfig(dropout=0.0, range_noise=0.0, speed=speed)
    rng = np.random.default_rng(0)
    setup = draw_setup(rng, cfg)
    origins = sweep_origins(scene.ground, 0.0, speed, cfg.firings, cfg.rate_hz)
    ret = cast_unit(rng, scene, Unit(setup.spec.elevations_deg), origins, setup, cfg)
    keep = (ret.firing < 20) | (ret.firing >= 1980)
    return ret.points[keep], ret.ray[keep] % 64 + np.where(ret.firing[keep] < 20, 0, 100)


def test_motion_during_the_sweep_skews_the_rings_and_keeps_static_objects_in_their_boxes():
    """Points are in the end-of-sweep frame: the first firings' rays started speed / rate metres behind."""
    for speed, shift in ((0.0, 0.0), (15.0, 1.5)):
        points, beam = _cast_moving(_flat_scene(False), speed)
        start, end = beam == 63, beam == 163  # the lowest beam: a ring 3.8 m across
        gap = np.median(points[end, 0]) - np.median(points[start, 0])
        assert abs(gap - shift) < 0.1, (speed, gap)
    scene = _flat_scene(True)
    points, _ = _cast_moving(scene, 15.0)
    grown = scene.boxes.astype(np.float32) + np.array([0, 0, 0, 0.04, 0.04, 0.04, 0], np.float32)
    inside = points_in_boxes(points[:, :3], grown)[:, 0]  # within 2 cm of the box
    near = (np.abs(points[:, 0] + 12) < 2.6) & (np.abs(points[:, 1]) < 1.3) & (points[:, 2] > -1.6)
    assert inside.sum() > 300 and inside[near].all()  # no smear: every point near the box is on it


def test_ego_roof_returns_for_the_sensors_that_have_them():
    counts = {}
    for sensor in (Sensor.HDL32E, Sensor.HDL64E, Sensor.VLP32C):
        scan, source = simulate_sources(1, SimConfig(sensor=sensor))
        r = np.linalg.norm(scan.points[:, :3], axis=1)
        counts[sensor] = int((r < 1.0).sum())
        assert np.all(r[source == Source.EGO] < 1.2)
        assert not np.any(points_in_boxes(scan.points[source == Source.EGO, :3], scan.gt.boxes))
    assert 3000 < counts[Sensor.HDL32E] < 12000  # nuScenes: about 4,000 roof points per 1,085 firings
    assert counts[Sensor.HDL64E] == 0 and counts[Sensor.VLP32C] == 0
    _, source = simulate_sources(1, SimConfig(sensor=Sensor.HDL32E, ego_returns=False))
    assert not np.any(source == Source.EGO)


def test_intensity_scale_differs_per_sensor_and_retroreflectors_saturate():
    medians = {}
    for sensor in (Sensor.HDL64E, Sensor.HDL32E, Sensor.WAYMO_TOP):
        p = simulate(0, SimConfig(sensor=sensor, firings=800)).points
        medians[sensor] = float(np.median(p[:, 3]))
        assert (p[:, 3] >= 0.99).any() and p[:, 3].max() <= 1.0
    assert 0.2 < medians[Sensor.HDL64E] < 0.4  # KITTI: 0.29
    assert 0.02 < medians[Sensor.HDL32E] < 0.09  # nuScenes: 0.047
    assert medians[Sensor.HDL64E] > 3 * medians[Sensor.HDL32E]


def test_above_ground_and_stats_on_a_known_cloud():
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(-20, 20, (2000, 2)), np.full(2000, -1.8), np.full(2000, 0.1)]
    pole = np.c_[np.full((50, 2), 5.0), np.linspace(-1.8, 1.0, 50), np.full(50, 0.5)]
    points = np.concatenate([ground, pole]).astype(np.float32)
    up = above_ground(points)
    assert not up[:2000].any() and up[2000:].sum() == int((pole[:, 2] > -1.5).sum())
    cloud = Cloud(points, 1.8, np.zeros((0, 7), np.float32), None, None)
    stats = cloud_stats("x", [cloud])
    assert math.isclose(stats.range_share.sum(), 1.0) and len(stats.range_share) == len(RANGE_EDGES) - 1
    assert (
        math.isclose(stats.height_share[0], 2001 / 2050, rel_tol=0.02)
        and len(stats.height_share) == len(HEIGHT_EDGES) - 1
    )
    assert 0 < stats.clutter_est < 0.05 and stats.clutter_true is None


def test_legs_hidden_counts_the_pedestrians_seen_only_above_their_legs():
    """Three pedestrians (boxes 1.8 m tall, bottoms at z -1.8): one seen head to foot, one seen from 0.6 m
    up (over a car), one with too few points to count; a cyclist seen from 0.6 m up is not a pedestrian."""
    boxes = np.array([[10.0, y, -0.9, 0.6, 0.6, 1.8, 0.0] for y in (0.0, 3.0, 6.0, 9.0)], np.float32)
    column = [
        np.c_[np.full(n, 10.0), np.full(n, y), np.linspace(lo, -0.1, n), np.zeros(n)]
        for y, lo, n in ((0.0, -1.75, 30), (3.0, -1.2, 30), (6.0, -1.75, 10), (9.0, -1.2, 30))
    ]
    points = np.concatenate(column).astype(np.float32)
    labels = np.array([1, 1, 1, 2])  # PEDESTRIAN x 3, CYCLIST
    cloud = Cloud(points, 1.8, boxes, None, None, labels=labels)
    assert legs_hidden_counts(cloud) == (2, 1)
    stats = cloud_stats("x", [cloud])
    assert stats.pedestrians == 2 and stats.legs_hidden == 0.5
    assert legs_hidden_counts(replace(cloud, labels=None)) == (0, 0)  # no classes: nothing counted


def test_compare_without_samples_gives_simulated_rows(tmp_path):
    rows = compare((Sensor.HDL32E, Sensor.VLS128), 1, tmp_path)
    assert [r.name for r in rows] == ["sim hdl32e", "sim vls128"]
    assert rows[0].clutter_true is not None and 0.05 < rows[0].clutter_true < 0.9
    text = format_tables(rows)
    assert text.count("| sim hdl32e |") == 3 and "points/scan" in text and "clutter est." in text


@pytest.mark.samples
def test_compare_against_the_real_samples():
    rows = {r.name: r for r in compare((Sensor.HDL64E, Sensor.VLP32C_PAIR), 2, SHARED_DATA)}
    assert set(rows) == {
        "sim hdl64e",
        f"real {RealSet.KITTI}",
        "sim vlp32c-pair",
        f"real {RealSet.ARGOVERSE}",
    }
    sim, real = rows["sim hdl64e"], rows["real kitti"]
    assert real.scans == 6 and abs(real.intensity_median - 0.29) < 0.02
    assert abs(sim.intensity_median - real.intensity_median) < 0.08
    assert abs(sim.points - real.points) < 0.2 * real.points
    assert np.abs(sim.range_share - real.range_share).max() < 0.1
    assert rows["real argoverse"].intensity_median is None  # the conversion dropped intensities
    assert 0.1 < real.clutter_est < 0.6 and sim.clutter_true is not None


def test_cli_compare_and_varied(tmp_path):
    from phim.cli import main as app

    result = CliRunner().invoke(
        app, ["sim", "compare", "--seeds", "1", "--sensor", "vlp32c", "--samples", str(tmp_path)]
    )
    assert result.exit_code == 0, result.output
    assert "| sim vlp32c |" in result.output
    result = CliRunner().invoke(app, ["sim", "--seed", "2", "--varied"])
    assert result.exit_code == 0 and result.output.startswith("sim/"), result.output
    scene = SceneConfig(vehicles=(2, 2), pedestrians=(0, 0), cyclists=(0, 0), far_fraction=0.0)
    assert len(simulate(0, SimConfig.varied(scene=scene)).gt) == 2
