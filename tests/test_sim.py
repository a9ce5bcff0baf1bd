"""The LiDAR simulator (lidar/sim): determinism, sweep order, beams vs real tables, labels, occlusion."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest
import torch
import yaml
from click.testing import CliRunner
from conftest import SHARED_DATA

from lidar.sim import SceneConfig, Sensor, SimConfig, actors, load_elevations, sensor_spec, simulate
from lidar.sim.ground import Ground
from lidar.sim.raycast import Rays, SolidList
from lidar.sim.scene import Scene
from lidar.sim.simulate import cast_scene
from lidar.types import LEVEL_1, LEVEL_2, LEVEL_2_MAX_POINTS, points_in_boxes
from model.sectors import sector_of_points

HDL64E_TABLES = SHARED_DATA / "velodyne_hdl64e_calibration"
WAYMO_CALIBRATION = SHARED_DATA / "waymo_frame_labels" / "lidar_calibration.json"
NUSCENES_SCAN = (
    SHARED_DATA / "nuscenes_sample" / "n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin"
)


@pytest.fixture(scope="module")
def scans() -> list:
    return [simulate(seed) for seed in range(3)]


def _dense_points_in_boxes(xyz: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """The plain O(N*M) definition: (N, M) point inside box, borders included."""
    d = xyz[:, None, :].astype(np.float64) - boxes[None, :, :3]
    cos, sin = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    u = d[..., 0] * cos + d[..., 1] * sin
    v = -d[..., 0] * sin + d[..., 1] * cos
    return (
        (np.abs(u) <= boxes[:, 3] / 2)
        & (np.abs(v) <= boxes[:, 4] / 2)
        & (np.abs(d[..., 2]) <= boxes[:, 5] / 2)
    )


def test_same_seed_same_scan_other_seed_other_scan(scans):
    again = simulate(1)
    assert np.array_equal(again.points, scans[1].points)
    assert np.array_equal(again.time, scans[1].time)
    assert np.array_equal(again.gt.boxes, scans[1].gt.boxes)
    assert np.array_equal(again.gt.num_points, scans[1].gt.num_points)
    assert len(scans[0].points) != len(scans[1].points) or not np.array_equal(
        scans[0].points, scans[1].points
    )


def test_scan_layout(scans):
    for scan in scans:
        n = len(scan.points)
        assert 80_000 < n < 2000 * 64
        assert scan.points.dtype == np.float32 and scan.points.shape == (n, 4)
        assert scan.fields == ("x", "y", "z", "intensity")
        assert scan.time.shape == (n,) and scan.sector.shape == (n,) and scan.sector.dtype == np.int64
        assert scan.points[:, 3].min() >= 0 and scan.points[:, 3].max() <= 1
        assert scan.points[:, 3].std() > 0.05  # materials and incidence vary
        assert scan.label_fov is None


def test_sweep_starts_at_minus_pi_turns_counter_clockwise_and_sectors_come_in_order(scans):
    for scan in scans:
        x, y = scan.points[:, 0], scan.points[:, 1]
        assert np.all(np.diff(scan.time) >= 0) and scan.time[0] >= 0 and scan.time[-1] < 0.1
        az = np.arctan2(y, x)
        expected = -math.pi + 2 * math.pi * scan.time / 0.1  # the firing's azimuth at 10 Hz
        assert np.abs(az - expected).max() < 2 * math.pi / 2000 * 1.01  # within one firing step
        assert np.all(np.diff(scan.sector) >= 0)  # sectors 0, 1, 2, 3 in time order
        assert set(np.unique(scan.sector).tolist()) == {0, 1, 2, 3}
        ref = sector_of_points(torch.from_numpy(x.copy()), torch.from_numpy(y.copy()), 4).numpy()
        assert np.array_equal(scan.sector, ref)


def _velodyne_table(name: str) -> np.ndarray:
    lasers = yaml.safe_load((HDL64E_TABLES / name).read_text())["lasers"]
    return np.sort(np.degrees([laser["vert_correction"] for laser in lasers]))[::-1]


@pytest.mark.samples
@pytest.mark.parametrize("table", ["64e_s3-xiesc.yaml", "64e_utexas.yaml"])
def test_hdl64e_preset_matches_real_tables(table):
    error = np.abs(sensor_spec(Sensor.HDL64E).elevations_deg - _velodyne_table(table)).max()
    assert error < 0.3, f"{table}: max error {error:.3f} deg"


@pytest.mark.samples
def test_waymo_top_preset_matches_the_calibration():
    top = json.loads(WAYMO_CALIBRATION.read_text())["lasers"]["TOP"]
    real = np.degrees(top["beam_inclinations_rad_ascending"])[::-1]
    error = np.abs(sensor_spec(Sensor.WAYMO_TOP).elevations_deg - real).max()
    assert len(real) == 64 and error < 0.1, f"max error {error:.3f} deg"


@pytest.mark.samples
def test_hdl32e_preset_matches_the_nuscenes_rings():
    p = np.fromfile(NUSCENES_SCAN, dtype=np.float32).reshape(-1, 5)
    r = np.hypot(p[:, 0], p[:, 1])
    elevation = np.degrees(np.arctan2(p[:, 2], r))
    far = r > 3  # not the ego vehicle
    real = np.array([np.median(elevation[far & (p[:, 4] == ring)]) for ring in range(32)])[::-1]
    assert np.abs(sensor_spec(Sensor.HDL32E).elevations_deg - real).max() < 0.4


@pytest.mark.samples
def test_elevation_tables_load_from_files(tmp_path):
    yaml_table = load_elevations(HDL64E_TABLES / "64e_s3-xiesc.yaml")
    assert np.allclose(yaml_table, _velodyne_table("64e_s3-xiesc.yaml"))
    (tmp_path / "beams.txt").write_text("# degrees\n2.0\n-10.5\n-24.0\n")
    (tmp_path / "beams.json").write_text("[-1.0, 1.0]")
    assert np.array_equal(load_elevations(tmp_path / "beams.txt"), [2.0, -10.5, -24.0])
    assert np.array_equal(load_elevations(tmp_path / "beams.json"), [1.0, -1.0])
    scan = simulate(0, SimConfig(elevation_file=tmp_path / "beams.txt", firings=400))
    elevation = np.degrees(np.arctan2(scan.points[:, 2], np.hypot(scan.points[:, 0], scan.points[:, 1])))
    assert np.abs(elevation[:, None] - np.array([2.0, -10.5, -24.0])).min(axis=1).max() < 1e-3


def test_points_lie_on_the_beams_of_the_drawn_sensor():
    cfg = SimConfig(sensors=(Sensor.HDL64E, Sensor.WAYMO_TOP, Sensor.HDL32E), firings=500)
    seen = set()
    for seed in range(6):
        scan = simulate(seed, cfg)
        sensor = Sensor(scan.name.split("/")[1])
        seen.add(sensor)
        beams = sensor_spec(sensor).elevations_deg
        p = scan.points
        elevation = np.degrees(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])))
        assert np.abs(elevation[:, None] - beams[None]).min(axis=1).max() < 1e-3
    assert len(seen) >= 2


def test_points_in_boxes_is_the_dense_definition():
    rng = np.random.default_rng(0)
    boxes = np.concatenate(
        [rng.uniform(-20, 20, (30, 3)), rng.uniform(0.5, 5, (30, 3)), rng.uniform(-3, 3, (30, 1))], 1
    )
    boxes = boxes.astype(np.float32)
    xyz = rng.uniform(-25, 25, (20_000, 3)).astype(np.float32)
    xyz[:30] = boxes[:, :3]
    xyz[30:60, 0] = boxes[:, 0] + boxes[:, 3] / 2  # on a face of an axis-aligned box: inside
    xyz[30:60, 1:] = boxes[:, 1:3]
    boxes[:, 6] = np.where(np.arange(30) % 2 == 0, 0.0, boxes[:, 6])
    xyz[60] = np.nan
    assert np.array_equal(points_in_boxes(xyz, boxes), _dense_points_in_boxes(xyz, boxes))


def test_box_counts_and_difficulty(scans):
    for scan in scans:
        gt = scan.gt
        dense = _dense_points_in_boxes(scan.points[:, :3], gt.boxes).sum(axis=0)
        assert np.array_equal(gt.num_points, dense)
        assert np.array_equal(gt.difficulty == LEVEL_2, gt.num_points <= LEVEL_2_MAX_POINTS)
        assert set(np.unique(gt.difficulty).tolist()) <= {LEVEL_1, LEVEL_2}
    all_counts = np.concatenate([s.gt.num_points for s in scans])
    assert (all_counts > LEVEL_2_MAX_POINTS).mean() > 0.6 and (all_counts <= LEVEL_2_MAX_POINTS).any()


def test_class_counts_follow_the_config(scans):
    for scan in scans:
        near = np.hypot(scan.gt.boxes[:, 0], scan.gt.boxes[:, 1]) <= 50
        counts = np.bincount(scan.gt.labels[near], minlength=3)
        assert 10 <= counts[0] <= 40 and counts[1] <= 20 and counts[2] <= 6
    scene = SceneConfig(vehicles=(12, 12), pedestrians=(7, 7), cyclists=(3, 3), far_fraction=0.0)
    scan = simulate(5, SimConfig(scene=scene))
    assert np.bincount(scan.gt.labels, minlength=3).tolist() == [12, 7, 3]
    assert np.hypot(scan.gt.boxes[:, 0], scan.gt.boxes[:, 1]).max() <= 50


def test_range_limit():
    cfg = SimConfig(range_max=30.0, firings=800)
    scan = simulate(2, cfg)
    r = np.linalg.norm(scan.points[:, :3], axis=1)
    assert r.max() <= 30.0 and r.min() >= cfg.range_min
    assert np.hypot(scan.gt.boxes[:, 0], scan.gt.boxes[:, 1]).max() <= 30.0
    assert len(scan.gt) > 0


def _flat_street() -> Ground:
    """Level ground 1.73 m below the sensor, no roads or curbs."""
    return Ground(1.73, np.zeros(2), np.zeros(0), np.zeros((0, 2)), np.zeros(0), 0.15, np.zeros((0, 8)))


def _two_box_scene(front_height: float | None) -> Scene:
    """A flat empty street, a car 20 m ahead and optionally a box of the given height 10 m ahead."""
    ground = _flat_street()
    solids = SolidList()
    car = np.array([20.0, 0.0, -1.73 + 0.8, 4.5, 1.9, 1.6, 0.0])
    solids.boxes(car[None, :2], -1.73, -1.73 + 1.6, 4.5, 1.9, 0.0, 0.5)
    if front_height is not None:
        solids.boxes(np.array([[10.0, 0.0]]), -1.73, -1.73 + front_height, 4.5, 1.9, 0.0, 0.5)
    return Scene((), ground, solids.build(), car[None], np.zeros(1, np.int64))


def test_a_box_behind_another_gets_fewer_points():
    cfg = replace(SimConfig(), dropout=0.0)
    rays = Rays.spinning(cfg.firings, sensor_spec(Sensor.HDL64E).elevations_deg)
    counts = {}
    for front in (None, 1.6, 3.5):
        points, _ = cast_scene(np.random.default_rng(0), _two_box_scene(front), rays, cfg)
        counts[front] = int(
            points_in_boxes(points[:, :3], _two_box_scene(None).boxes.astype(np.float32)).sum()
        )
    assert counts[None] > 100
    assert counts[1.6] < counts[None] / 2  # only its top shows over the car in front
    assert counts[3.5] == 0  # fully hidden behind a taller box


def _one_actor(
    box: np.ndarray, draw: Callable[[SolidList, np.random.Generator], None], seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """One object (label box (7,), its solids drawn by `draw`) on a flat empty street -> its points (N, 4),
    and u: where each point lies along the heading, as a fraction of the length (+0.5 the front)."""
    solids = SolidList()
    rng = np.random.default_rng(seed)
    draw(solids, rng)
    scene = Scene((), _flat_street(), solids.build(), box[None], np.zeros(1, np.int64))
    cfg = replace(SimConfig(), dropout=0.0)
    points, _ = cast_scene(
        rng, scene, Rays.spinning(cfg.firings, sensor_spec(Sensor.HDL64E).elevations_deg), cfg
    )
    points = points[points_in_boxes(points[:, :3], box[None].astype(np.float32))[:, 0]]
    u = (points[:, 0] - box[0]) * math.cos(box[6]) + (points[:, 1] - box[1]) * math.sin(box[6])
    return points, u / box[3]


def _one_vehicle(box: np.ndarray, large: bool, seed: int) -> tuple[np.ndarray, np.ndarray]:
    cands = actors.Candidates(box[None], np.array([large]))
    return _one_actor(box, lambda solids, rng: actors.vehicle_solids(solids, rng, cands), seed)


def test_a_vehicle_shows_its_front_and_back():
    """Front and back differ as on real vehicles: a car's bonnet is lower than its cabin and boot (a
    sedan's only a little), and retroreflective lights saturate a vehicle's back, never its front."""
    car, truck = (4.5, 1.9, 1.6), (9.0, 2.6, 3.6)
    higher_back = 0
    for seed in range(12):
        side_on = np.array([0.0, 10.0, -1.73 + car[2] / 2, *car, 0.0])
        points, u = _one_vehicle(side_on, False, seed)
        assert len(points) > 200
        front, back = points[u > 0.3, 2], points[u < -0.3, 2]
        higher_back += np.percentile(back, 90) > np.percentile(front, 90) + 0.05
        for large, size in ((False, car), (True, truck)):
            saturated = []  # returns at full intensity: only retroreflectors give them
            for yaw in (0.0, math.pi):  # the back, then the front turned to the sensor
                facing = np.array([12.0, 0.0, -1.73 + size[2] / 2, *size, yaw])
                saturated.append(int((_one_vehicle(facing, large, seed)[0][:, 3] >= 0.99).sum()))
            assert saturated[0] >= 5 and saturated[1] == 0, (seed, large, saturated)
    assert higher_back >= 10


def test_pedestrians_and_cyclists_show_their_front():
    """Seen side-on, a pedestrian's feet point ahead and the chest and head lean ahead of the hips; a
    cyclist's arms, handlebar and head lie ahead of the middle, the hips behind it."""
    ped, cyclist = (0.78, 0.72, 1.81), (1.86, 0.68, 1.79)
    feet_ahead = leaning = rider_ahead = 0
    for seed in range(12):
        box = np.array([0.0, 6.0, -1.73 + ped[2] / 2, *ped, 0.0])
        points, u = _one_actor(box, lambda s, r, b=box: actors.pedestrian_solids(s, r, b[None]), seed)
        up = points[:, 2] + 1.73  # height above the street
        assert len(points) > 100
        feet_ahead += np.mean(u[(up > 0.02) & (up < 0.1)]) > 0.05  # the street below them left out
        leaning += np.mean(u[up > 1.2]) > np.mean(u[(up > 0.9) & (up < 1.1)]) + 0.02
        box = np.array([0.0, 6.0, -1.73 + cyclist[2] / 2, *cyclist, 0.0])
        points, u = _one_actor(box, lambda s, r, b=box: actors.cyclist_solids(s, r, b[None]), seed)
        up = points[:, 2] + 1.73
        assert len(points) > 100
        rider_ahead += np.mean(u[up > 1.25]) > 0.03
    assert feet_ahead >= 10 and leaning >= 10 and rider_ahead >= 10, (feet_ahead, leaning, rider_ahead)


def test_cli_writes_a_png_and_bench_reports(tmp_path):
    from phim.cli import main as app

    out = tmp_path / "scan.png"
    result = CliRunner().invoke(app, ["sim", "--seed", "3", "--sensor", "waymo-top", "--png", str(out)])
    assert result.exit_code == 0, result.output
    assert "points" in result.output and "VEHICLE" in result.output and "LEVEL_2" in result.output
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    result = CliRunner().invoke(app, ["bench", "sim", "--seeds", "2", "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.output.strip().splitlines()[-1])["scans_per_s"] > 0
