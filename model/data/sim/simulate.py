"""`simulate(seed, cfg)`: one labelled LiDAR turn ray-cast through a random street scene.

The sweep starts at azimuth -pi and turns counter-clockwise, so points come in firing order with time and
azimuth increasing together, and the model's sectors (`model.data.readers.sector_of_xy`) arrive in index
order 0, 1, 2, 3.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from contract import REQUIRED_FIELDS
from model.data.readers import sector_of_xy
from model.data.sim.raycast import Rays, cast_solids
from model.data.sim.scene import Scene, SceneConfig, make_scene
from model.data.sim.sensors import Sensor, sensor_spec
from model.data.types import GroundTruth, LabeledScan

SECTORS = 4
SIGNAL_RANGE = 10.0  # metres: a return's signal is intensity * (SIGNAL_RANGE / range)^2


@dataclass(frozen=True)
class SimConfig:
    sensor: Sensor = Sensor.HDL64E
    sensors: tuple[Sensor, ...] = ()  # when given: one of them is drawn per seed (overrides `sensor`)
    height: float | None = None  # sensor height above the ground (m); None: the sensor preset's
    elevation_file: Path | None = None  # a beam table instead of the preset's (sensors.load_elevations)
    firings: int = 2000  # per turn
    rate_hz: float = 10.0  # turns per second
    range_min: float = 1.0  # metres
    range_max: float = 75.0  # metres; also the label range (box centre distance)
    range_noise: float = 0.02  # metres, 1 sigma
    dropout: float = 0.03  # chance that a return is lost at random
    weak_signal: float = 1e-4  # a return of signal s is kept with chance 1 - exp(-s / weak_signal)
    intensity_noise: float = 0.05  # relative, 1 sigma
    scene: SceneConfig = field(default_factory=SceneConfig)


DEFAULT = SimConfig()


def simulate(seed: int, cfg: SimConfig = DEFAULT) -> LabeledScan:
    """One labelled turn: points (N, 4) x, y, z, intensity in firing order, their time and sector, and the
    labels of every object within range (boxes hit by no ray included: evaluation drops them)."""
    rng = np.random.default_rng(seed)
    sensor = cfg.sensors[int(rng.integers(len(cfg.sensors)))] if cfg.sensors else cfg.sensor
    spec = sensor_spec(sensor, cfg.height, cfg.elevation_file)
    scene = make_scene(rng, cfg.scene, spec.height, cfg.range_max)
    rays = Rays.spinning(cfg.firings, spec.elevations_deg)
    points, ray = cast_scene(rng, scene, rays, cfg)
    firing = ray // len(rays.elevation)  # (N,)
    time = (firing / (cfg.firings * cfg.rate_hz)).astype(np.float32)
    sector = sector_of_xy(points[:, 0], points[:, 1], SECTORS)  # (N,)
    gt = GroundTruth.from_boxes(scene.boxes.astype(np.float32), scene.labels, points)
    return LabeledScan(f"sim/{sensor}/{seed}", points, REQUIRED_FIELDS, gt, time, sector)


def cast_scene(
    rng: np.random.Generator, scene: Scene, rays: Rays, cfg: SimConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Cast every ray -> points (N, 4) float32 and their ray indices (N,), in firing order."""
    hits = cast_solids(scene.solids, rays, cfg.range_min, rng)
    nearest_solid = np.full(rays.count, np.inf, np.float32)
    nearest_solid[hits.ray] = hits.t
    t = scene.ground.cast(rays, cfg.range_max, nearest_solid)  # (R,) inf: no ground return before a solid
    closer = hits.t < t[hits.ray]
    solid_ray = hits.ray[closer]  # rays whose nearest return is a solid
    t[solid_ray] = hits.t[closer]
    f, b = np.divmod(np.arange(rays.count), len(rays.elevation))
    dx, dy, dz = rays.directions(f, b)  # (R,) each
    refl = np.zeros(rays.count, np.float32)
    cos = np.abs(dz)  # ground: near enough to level
    refl[solid_ray] = scene.solids.reflectivity[hits.solid[closer]]
    cos[solid_ray] = hits.cos[closer]
    on_ground = np.isfinite(t)
    on_ground[solid_ray] = False
    g = np.flatnonzero(on_ground)
    refl[g] = scene.ground.reflectivity(t[g] * dx[g], t[g] * dy[g])
    t = t + rng.normal(0.0, cfg.range_noise, rays.count).astype(np.float32)
    intensity = np.clip(refl * cos * (1 + cfg.intensity_noise * rng.standard_normal(rays.count)), 0, 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        signal = intensity * (SIGNAL_RANGE / t) ** 2
    kept = rng.random(rays.count) >= cfg.dropout
    kept &= rng.random(rays.count) < -np.expm1(-signal / cfg.weak_signal)
    ray = np.flatnonzero(kept & (t >= cfg.range_min) & (t <= cfg.range_max))  # (N,)
    tr = t[ray]
    points = np.stack([tr * dx[ray], tr * dy[ray], tr * dz[ray], intensity[ray]], 1).astype(np.float32)
    return points, ray
