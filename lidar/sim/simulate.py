"""`simulate(seed, cfg)`: one labelled LiDAR turn ray-cast through a random street scene.

The sweep starts at azimuth -pi and turns counter-clockwise, so points come in firing order with time and
azimuth increasing together, and the model's sectors (`lidar.readers.sector_of_xy`) arrive in index
order 0, 1, 2, 3. With ego motion (`speed` > 0) points and labels are in the sensor's frame at the end of
the turn (lidar/sim/ego.py).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from contract import REQUIRED_FIELDS
from lidar.readers import sector_of_xy
from lidar.sim.ego import EGO_MIN_RANGE, roof_range, sweep_origins
from lidar.sim.ground import Ground
from lidar.sim.raycast import Rays, Solids, cast_solids
from lidar.sim.response import intensity, keep_chance
from lidar.sim.scene import Scene, SceneConfig, make_scene
from lidar.sim.sensors import Sensor, Unit, sensor_spec
from lidar.sim.setup import Fixed, Setup, Variation, fixed_setup, varied_setup
from lidar.types import GroundTruth, LabeledScan

SECTORS = 4


class Source(enum.IntEnum):
    """What a simulated point lies on."""

    GROUND = 0
    SOLID = 1  # scenery, clutter or a target
    EGO = 2  # the ego vehicle's roof


@dataclass(frozen=True)
class SimConfig:
    sensor: Sensor = Sensor.HDL64E
    sensors: tuple[Sensor, ...] = ()  # when given: one of them is drawn per seed (overrides `sensor`)
    height: float | None = None  # sensor height above the ground (m); None: the sensor preset's
    elevation_file: Path | None = None  # a beam table instead of the preset's (sensors.load_elevations)
    firings: int = 2000  # per turn
    rate_hz: float = 10.0  # turns per second
    range_min: float = 1.0  # metres
    range_max: float = 75.0  # metres; the label range (box centre distance), and the points' unless the
    # preset has its own (the VLP-32C pair: 200 m)
    range_noise: float = 0.02  # metres, 1 sigma
    dropout: float = 0.03  # chance that a return is lost at random
    weak_signal: float = 1e-4  # a return of signal s is kept with chance 1 - exp(-s / weak_signal)
    intensity_noise: float = 0.05  # relative, 1 sigma
    speed: float = 0.0  # m/s, the ego's speed along its lane during the turn
    ego_returns: bool = True  # returns from the roof under the sensor, for the presets that have them
    vary: Variation | None = None  # when given: every sensor-side value above is drawn per seed from it
    scene: SceneConfig = field(default_factory=SceneConfig)

    @classmethod
    def varied(cls, **overrides: object) -> SimConfig:
        """For training: every preset, mounting height, beam errors, noise, intensity curve, dropout and ego
        speed drawn per seed (`Variation`)."""
        return cls(**{"sensors": tuple(Sensor), "vary": Variation(), **overrides})  # type: ignore[arg-type]


DEFAULT = SimConfig()


@dataclass(frozen=True)
class Returns:
    """The reported returns of some rays, in firing order."""

    points: np.ndarray  # (N, 4) float32 x, y, z, intensity
    ray: np.ndarray  # (N,) int64 ray index f * B + b of its unit
    firing: np.ndarray  # (N,) int64
    source: np.ndarray  # (N,) int8 Source


_RETURN_FIELDS = tuple(f.name for f in fields(Returns))


def draw_setup(rng: np.random.Generator, cfg: SimConfig) -> Setup:
    """The sensor side of one scan: the preset drawn from `cfg.sensors`, varied when `cfg.vary` is given."""
    sensor = cfg.sensors[int(rng.integers(len(cfg.sensors)))] if cfg.sensors else cfg.sensor
    spec = sensor_spec(sensor, cfg.height, cfg.elevation_file)
    if cfg.vary is not None:
        return varied_setup(rng, sensor, spec, cfg.vary)
    fixed = Fixed(
        cfg.height, cfg.speed, cfg.ego_returns, cfg.range_noise, cfg.dropout, cfg.weak_signal,
        cfg.intensity_noise,
    )  # fmt: skip
    return fixed_setup(sensor, spec, fixed)


def simulate(seed: int, cfg: SimConfig = DEFAULT) -> LabeledScan:
    """One labelled turn: points (N, 4) x, y, z, intensity in firing order, their time and sector, and the
    labels of every object within range (boxes hit by no ray included: evaluation drops them)."""
    return simulate_sources(seed, cfg)[0]


def simulate_sources(seed: int, cfg: SimConfig = DEFAULT) -> tuple[LabeledScan, np.ndarray]:
    """`simulate`, and what each point lies on: (N,) int8 `Source`."""
    rng = np.random.default_rng(seed)
    setup = draw_setup(rng, cfg)
    scene = make_scene(rng, cfg.scene, setup.spec.height, cfg.range_max)
    heading = scene.roads[0].yaw if scene.roads else 0.0
    origins = sweep_origins(scene.ground, heading, setup.speed, cfg.firings, cfg.rate_hz)
    parts = [cast_unit(rng, scene, unit, origins, setup, cfg) for unit in setup.spec.heads]
    ret = _merge(parts)
    time = (ret.firing / (cfg.firings * cfg.rate_hz)).astype(np.float32)
    sector = sector_of_xy(ret.points[:, 0], ret.points[:, 1], SECTORS)  # (N,)
    gt = GroundTruth.from_boxes(scene.boxes.astype(np.float32), scene.labels, ret.points)
    name = f"sim/{setup.sensor}/{seed}"
    return LabeledScan(name, ret.points, REQUIRED_FIELDS, gt, time, sector), ret.source


def _merge(parts: list[Returns]) -> Returns:
    if len(parts) == 1:
        return parts[0]
    firing = np.concatenate([p.firing for p in parts])
    order = np.argsort(firing, kind="stable")  # firing by firing; within one, unit by unit
    return Returns(*(np.concatenate([getattr(p, k) for p in parts])[order] for k in _RETURN_FIELDS))


def cast_unit(
    rng: np.random.Generator,
    scene: Scene,
    unit: Unit,
    origins: np.ndarray | None,
    setup: Setup,
    cfg: SimConfig,
) -> Returns:
    """The returns of one unit of the sensor, which sits `unit.z_offset` above the scan's origin."""
    lift = unit.z_offset
    if lift and origins is None:
        origins = np.zeros((cfg.firings, 3))
    start = None if origins is None else origins + np.array([0.0, 0.0, lift])
    rays = Rays.spinning(cfg.firings, unit.elevations_deg, unit.azimuth_offset_deg, start)
    ground = replace(scene.ground, height=scene.ground.height + lift) if lift else scene.ground
    max_range = setup.spec.max_range or cfg.range_max
    return _cast(rng, ground, scene.solids, rays, setup, cfg.range_min, max_range, lift)


def cast_scene(
    rng: np.random.Generator, scene: Scene, rays: Rays, cfg: SimConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Cast every ray with a fixed `cfg`'s sensor -> points (N, 4) float32 and their ray indices (N,), in
    firing order."""
    setup = draw_setup(np.random.default_rng(0), replace(cfg, sensors=(), vary=None))
    ret = _cast(rng, scene.ground, scene.solids, rays, setup, cfg.range_min, cfg.range_max, 0.0)
    return ret.points, ret.ray


def _nearest(
    rng: np.random.Generator, ground: Ground, solids: Solids, rays: Rays, range_min: float, max_range: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every ray's nearest return among the solids and the ground -> range (R,) (inf: none), reflectivity
    (R,), |cos incidence| (R,), Source (R,)."""
    hits = cast_solids(solids, rays, range_min, rng)
    nearest_solid = np.full(rays.count, np.inf, np.float32)
    nearest_solid[hits.ray] = hits.t
    t = ground.cast(rays, max_range, nearest_solid)  # (R,) inf: no ground return before a solid
    closer = hits.t < t[hits.ray]
    solid_ray = hits.ray[closer]  # rays whose nearest return is a solid
    t[solid_ray] = hits.t[closer]
    f, b = np.divmod(np.arange(rays.count), len(rays.elevation))
    dx, dy, dz = rays.directions(f, b)  # (R,) each
    refl = np.zeros(rays.count, np.float32)
    cos = np.abs(dz)  # ground: near enough to level
    refl[solid_ray] = solids.reflectivity[hits.solid[closer]]
    cos[solid_ray] = hits.cos[closer]
    source = np.full(rays.count, Source.GROUND, np.int8)
    source[solid_ray] = Source.SOLID
    g = np.flatnonzero(np.isfinite(t) & (source == Source.GROUND))
    ox, oy, _ = rays.starts(f[g])
    refl[g] = ground.reflectivity(ox + t[g] * dx[g], oy + t[g] * dy[g])
    return t, refl, cos, source


def _cast(
    rng: np.random.Generator,
    ground: Ground,
    solids: Solids,
    rays: Rays,
    setup: Setup,
    range_min: float,
    max_range: float,
    lift: float,
) -> Returns:
    """Cast every ray -> the returns the sensor reports, in firing order."""
    t, refl, cos, source = _nearest(rng, ground, solids, rays, range_min, max_range)
    f, b = np.divmod(np.arange(rays.count), len(rays.elevation))
    dx, dy, dz = rays.directions(f, b)  # (R,) each
    if setup.body is not None:
        roof = roof_range(setup.body, dx, dy, dz, lift)
        on_roof = roof < t
        t[on_roof], refl[on_roof], cos[on_roof] = roof[on_roof], setup.body.reflectivity, np.abs(dz[on_roof])
        source[on_roof] = Source.EGO
    t = t + rng.normal(0.0, setup.range_noise, rays.count).astype(np.float32)
    noise = setup.intensity_noise * rng.standard_normal(rays.count)
    value = intensity(setup.intensity, refl, cos, t, noise)
    kept = rng.random(rays.count) < keep_chance(refl, cos, t, setup.dropout, setup.weak_signal)
    near_enough = np.where(source == Source.EGO, t >= EGO_MIN_RANGE, t >= range_min)
    ray = np.flatnonzero(kept & near_enough & (t <= max_range))  # (N,)
    tr, fr = t[ray], f[ray]
    ox, oy, oz = rays.starts(fr)
    xyz = np.stack([ox + tr * dx[ray], oy + tr * dy[ray], oz + tr * dz[ray]], 1)
    points = np.concatenate([xyz, value[ray, None]], 1).astype(np.float32)
    return Returns(points, ray, fr, source[ray])
