"""What a sensor reports for a return: intensity by material, incidence and range with a per-sensor curve, and
which returns it loses (dropout by material and incidence).

Intensity. Real sensors scale intensity differently: KITTI's HDL-64E reflectance (0..1) has a median of
0.28 (0.25-0.30 over frames 000000-000005) and stays flat out to about 30 m, then fades (0.16 at 30-45 m, 0
beyond 45 m); nuScenes' HDL-32E intensity / 255 has a median of 0.047, about the same at every range, because
Velodyne's calibrated reflectivity maps diffuse targets to 0..100 of 255 and keeps 101..255 for
retroreflectors. So per sensor:

    diffuse = gain * reflectivity^gamma * |cos incidence|^beta / (1 + (range / half_range)^falloff)

times (1 + noise), clipped to [0, diffuse_max]; a retroreflector (reflectivity >= RETRO) saturates at 1
when it faces the sensor within 60 deg (retroreflective sheeting works up to 40-60 deg of entrance angle),
else it reads as a bright diffuse target. `gamma` < 1 and `beta` < 1 compress the spread as KITTI's values
are compressed (asphalt at grazing incidence reads 0.29 there, not the 0.02 a Lambertian model gives).

Dropout. A return is kept with chance (1 - dropout) * (1 - exp(-s / weak_signal)), where the signal
s = reflectivity * |cos incidence| * (10 m / range)^2: dark materials, grazing incidence and long range
lose more returns (grazing asphalt far away, black cars, glass).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lidar.sim.sensors import Sensor

RETRO = 0.95  # reflectivity at and above which a material is a retroreflector (plates, tail lights)
RETRO_COS = math.cos(math.radians(60))  # beyond 60 deg of incidence a retroreflector no longer saturates
SIGNAL_RANGE = 10.0  # metres: a return's signal is reflectivity * cos * (SIGNAL_RANGE / range)^2
VELODYNE_DIFFUSE_MAX = 100 / 255  # calibrated reflectivity: diffuse targets 0..100 of 255


@dataclass(frozen=True)
class Intensity:
    """A sensor's intensity curve (see the module docstring)."""

    gain: float
    gamma: float  # exponent of the reflectivity
    beta: float  # exponent of |cos incidence|
    half_range: float  # metres where the range roll-off halves the value (inf: none)
    falloff: float  # steepness of the roll-off
    diffuse_max: float  # the largest value a diffuse (not retroreflective) return reads


# Fitted on a small grid so that the intensity histogram and median of simulated scans (seeds 0-3, scenes
# of 2026-11-25) match the real ones (`phim sim compare`): KITTI 000000-000005 for the HDL-64E (sim median
# 0.28, real 0.29), the nuScenes sweep for the HDL-32E (0.045 and 0.047). The VLP-32C, its pair and the
# VLS-128 use the HDL-32E's Velodyne calibrated-reflectivity curve (Argoverse dropped its intensities);
# Waymo's curve is a guess (the sample frame has no points).
_VELODYNE = Intensity(0.6, 1.0, 1.1, math.inf, 1.0, VELODYNE_DIFFUSE_MAX)
INTENSITY: dict[Sensor, Intensity] = {
    Sensor.HDL64E: Intensity(0.78, 0.35, 0.3, 32.0, 4.0, 0.9),
    Sensor.WAYMO_TOP: Intensity(0.3, 1.0, 0.8, math.inf, 1.0, 0.6),
    Sensor.HDL32E: _VELODYNE,
    Sensor.VLP32C: _VELODYNE,
    Sensor.VLP32C_PAIR: _VELODYNE,
    Sensor.VLS128: _VELODYNE,
}


def intensity(
    curve: Intensity, refl: np.ndarray, cos: np.ndarray, t: np.ndarray, noise: np.ndarray
) -> np.ndarray:
    """(R,) reflectivity, |cos incidence|, range (m), relative noise -> (R,) float32 intensity in [0, 1]."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        roll_off = 1 / (1 + (t / curve.half_range) ** curve.falloff)
        diffuse = curve.gain * refl**curve.gamma * np.abs(cos) ** curve.beta * roll_off * (1 + noise)
    diffuse = np.clip(np.nan_to_num(diffuse, nan=0.0), 0.0, curve.diffuse_max)
    return np.where((refl >= RETRO) & (np.abs(cos) >= RETRO_COS), 1.0, diffuse).astype(np.float32)


def keep_chance(refl: np.ndarray, cos: np.ndarray, t: np.ndarray, dropout: float, weak: float) -> np.ndarray:
    """(R,) reflectivity, |cos incidence|, range (m) -> (R,) chance that the sensor reports the return."""
    with np.errstate(divide="ignore", invalid="ignore"):
        signal = refl * np.abs(cos) * (SIGNAL_RANGE / t) ** 2
    return (1 - dropout) * -np.expm1(-np.nan_to_num(signal, nan=0.0) / weak)
