"""The sensor side of one simulated scan: which sensor, its beams and mount, how it reports returns, and how
the ego moves. Fixed by `SimConfig` (a preset as it is), or drawn per seed from a `Variation` for training.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from lidar.sim.ego import EGO_BODY, EgoBody
from lidar.sim.response import INTENSITY, Intensity
from lidar.sim.sensors import Sensor, SensorSpec, Unit


@dataclass(frozen=True)
class Variation:
    """Per-seed randomization of the sensor side (ranges are drawn uniformly unless said otherwise)."""

    height: tuple[float, float] = (1.6, 2.3)  # metres, mounting height above the ground
    elevation_jitter_deg: tuple[float, float] = (0.05, 0.2)  # per unit: sigma of each beam's elevation error
    azimuth_jitter_deg: float = 0.1  # sigma of each beam's azimuth offset
    range_noise: tuple[float, float] = (0.01, 0.04)  # metres, 1 sigma
    dropout: tuple[float, float] = (0.0, 0.08)  # flat loss rate
    weak_signal: tuple[float, float] = (3e-5, 3e-4)  # drawn log-uniformly
    intensity_gain: tuple[float, float] = (0.7, 1.4)  # times the sensor's curve, drawn log-uniformly
    intensity_gamma: tuple[float, float] = (0.8, 1.25)  # times the sensor's exponents, log-uniformly
    speed: tuple[float, float] = (0.0, 15.0)  # m/s during the sweep
    standing: float = 0.25  # chance the ego stands still
    body_scale: tuple[float, float] = (0.85, 1.15)  # size of the roof under the sensor, where it has one
    intensity_noise: float = 0.05  # relative, 1 sigma


@dataclass(frozen=True)
class Setup:
    sensor: Sensor
    spec: SensorSpec  # beams (possibly jittered) per unit, mounting height, range
    intensity: Intensity
    body: EgoBody | None  # the roof under the sensor
    speed: float  # m/s along the ego's lane during the sweep
    range_noise: float  # metres, 1 sigma
    dropout: float
    weak_signal: float
    intensity_noise: float  # relative, 1 sigma


@dataclass(frozen=True)
class Fixed:
    """The sensor-side fields of a fixed `SimConfig` (one preset as it is)."""

    height: float | None
    speed: float
    ego_returns: bool
    range_noise: float
    dropout: float
    weak_signal: float
    intensity_noise: float


def fixed_setup(sensor: Sensor, spec: SensorSpec, fixed: Fixed) -> Setup:
    body = EGO_BODY[sensor] if fixed.ego_returns else None
    return Setup(
        sensor, spec, INTENSITY[sensor], body, fixed.speed, fixed.range_noise, fixed.dropout,
        fixed.weak_signal, fixed.intensity_noise,
    )  # fmt: skip


def _log_uniform(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    return float(np.exp(rng.uniform(np.log(lo_hi[0]), np.log(lo_hi[1]))))


def jittered_unit(rng: np.random.Generator, unit: Unit, v: Variation) -> Unit:
    """A unit with each beam's elevation off by N(0, sigma) (sigma drawn per unit) and a small azimuth
    offset per beam; beams are re-sorted top to bottom."""
    sigma = rng.uniform(*v.elevation_jitter_deg)
    beams = len(unit.elevations_deg)
    elevations = unit.elevations_deg + rng.normal(0.0, sigma, beams)
    offsets = rng.normal(0.0, v.azimuth_jitter_deg, beams)
    order = np.argsort(-elevations, kind="stable")
    return Unit(elevations[order], unit.z_offset, offsets[order])


def varied_setup(rng: np.random.Generator, sensor: Sensor, spec: SensorSpec, v: Variation) -> Setup:
    """Draw every sensor-side parameter of one scan around the preset `spec` of `sensor`."""
    units = tuple(jittered_unit(rng, unit, v) for unit in spec.heads)
    every = np.sort(np.concatenate([u.elevations_deg for u in units]))[::-1].copy()
    spec = replace(spec, elevations_deg=every, height=float(rng.uniform(*v.height)), units=units)
    base = INTENSITY[sensor]
    gamma = _log_uniform(rng, v.intensity_gamma)
    curve = replace(
        base,
        gain=base.gain * _log_uniform(rng, v.intensity_gain),
        gamma=base.gamma * gamma,
        beta=base.beta * gamma,
    )
    body = EGO_BODY[sensor]
    body = None if body is None else body.scaled(float(rng.uniform(*v.body_scale)))
    speed = 0.0 if rng.random() < v.standing else float(rng.uniform(*v.speed))
    return Setup(
        sensor, spec, curve, body, speed, float(rng.uniform(*v.range_noise)), float(rng.uniform(*v.dropout)),
        _log_uniform(rng, v.weak_signal), v.intensity_noise,
    )  # fmt: skip
