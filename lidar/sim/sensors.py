"""Spinning multi-beam LiDAR presets: beam elevations as parametric descriptions, mounting height, range.

No calibration table ships with the code. The presets are closed-form descriptions whose parameters were
chosen against real tables, which the tests (tests/test_sim.py) compare them to:
- HDL-64E: the datasheet layout, an upper block of 32 beams from +2.0 deg down in 1/3 deg steps and a lower
  block of 32 beams from -8.8 deg down in 0.51 deg steps. Max error against the S3 (xiesc) and nominal
  (utexas) tables of ros-drivers/velodyne: 0.28 / 0.19 deg. (The S2.1 sztaki unit spans +5..-24.9 deg, a
  different layout, and is not what this preset describes.)
- Waymo TOP: a quartic in the normalised beam index fitted (least squares) to the 64 inclinations of the
  TOP LiDAR in one Waymo Open Dataset frame's calibration; max error 0.06 deg.
- HDL-32E: 32 beams evenly spaced from -30.67 to +10.67 deg (datasheet); within 0.32 deg of the per-ring
  medians of the nuScenes sample scan.
- VLP-32C: the datasheet's non-uniform table, -25..+15 deg: a core of 18 beams from +1.667 down to -4.0 deg
  in 1/3 deg steps, six beams above it and eight below it, spreading out to the ends.
- VLP-32C pair (Argoverse-1 style): two VLP-32C units stacked 0.075 m apart (Argoverse-1's vehicle
  calibration), the upper one upright, the lower one upside down (its beams -15..+25 deg: the Argoverse
  samples have returns up to +25 deg), both spinning in step; the points of both make one scan, out to 200 m.
- VLS-128-like: 128 beams, -25..+15 deg, elevation = -1 - 2.5533 sinh(5.4713 (i - 58.835) / 127) for beam
  i = 0 (top) .. 127: 0.11 deg apart at -1 deg (the datasheet's finest step), about 1 deg at the ends.
"""

from __future__ import annotations

import enum
import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np


class Sensor(enum.StrEnum):
    HDL64E = "hdl64e"  # Velodyne HDL-64E as mounted on KITTI's car
    WAYMO_TOP = "waymo-top"  # Waymo Open Dataset TOP LiDAR
    HDL32E = "hdl32e"  # Velodyne HDL-32E as mounted on nuScenes' cars
    VLP32C = "vlp32c"  # Velodyne VLP-32C (Ultra Puck)
    VLP32C_PAIR = "vlp32c-pair"  # two stacked VLP-32C, as on Argoverse-1's cars
    VLS128 = "vls128"  # a 128-beam layout like Velodyne's VLS-128


@dataclass(frozen=True)
class Unit:
    """One spinning head of a sensor: its beams and where it sits relative to the scan's origin."""

    elevations_deg: np.ndarray  # (B,) float64, descending (top beam first)
    z_offset: float = 0.0  # metres above the scan's origin
    azimuth_offset_deg: np.ndarray | None = None  # (B,) per-beam azimuth offsets; None: all zero


@dataclass(frozen=True)
class SensorSpec:
    name: str
    elevations_deg: np.ndarray  # (B,) float64 beam elevations of all units, descending (top beam first)
    height: float  # metres above the ground under the sensor (the scan's origin)
    units: tuple[Unit, ...] = ()  # () : one unit with `elevations_deg` at the origin
    max_range: float | None = None  # metres, the points' range (None: SimConfig.range_max)

    @property
    def beams(self) -> int:
        return int(self.elevations_deg.shape[0])

    @property
    def heads(self) -> tuple[Unit, ...]:
        return self.units or (Unit(self.elevations_deg),)


# Waymo TOP: elevation (deg) = polyval(coefficients, i / 63) for beam i = 0 (lowest) .. 63 (highest).
_WAYMO_TOP_POLY_DEG = (16.03190, -20.65970, -13.51010, 38.19870, -17.49810)

SENSOR_HEIGHTS = {  # metres above the ground
    Sensor.HDL64E: 1.73,  # KITTI setup
    Sensor.WAYMO_TOP: 2.184,  # TOP extrinsic z above the vehicle origin (near ground level)
    Sensor.HDL32E: 1.84,  # nuScenes LIDAR_TOP
    Sensor.VLP32C: 1.9,  # a typical roof mount (no real sample to take it from)
    Sensor.VLP32C_PAIR: 1.95,  # between the units: 1.60 m over Argoverse's vehicle origin, ~0.35 m up
    Sensor.VLS128: 2.0,  # a typical roof mount
}
PAIR_SPACING = 0.075  # metres between the two units of a VLP-32C pair (1.64 and 1.565 m on Argoverse-1)
PAIR_RANGE = 200.0  # metres: Argoverse-1's stacked VLP-32C reach about 200 m (its samples: 219 m)
_VLP32C_CORE = (1.667, -4.0, 18)  # deg: first, last, count of the 1/3 deg core
_VLP32C_ABOVE = (15.0, 10.333, 7.0, 4.667, 3.333, 2.333)
_VLP32C_BELOW = (-4.667, -5.333, -6.148, -7.254, -8.843, -11.31, -15.639, -25.0)
_VLS128_SINH = (-1.0, 2.5533, 5.4713, 58.835)  # deg: centre c, scale a; rate b, centre beam i0


def hdl64e_elevations() -> np.ndarray:
    """(64,) degrees, descending: upper block +2.0 deg in 1/3 deg steps, lower block -8.8 deg in 0.51."""
    i = np.arange(32, dtype=np.float64)
    return np.concatenate([2.0 - i / 3.0, -8.8 - 0.51 * i])


def waymo_top_elevations() -> np.ndarray:
    """(64,) degrees, descending: the fitted quartic, -17.5 .. +2.5 deg, denser near the horizon."""
    u = np.arange(64, dtype=np.float64) / 63.0
    return np.polyval(_WAYMO_TOP_POLY_DEG, u)[::-1].copy()


def hdl32e_elevations() -> np.ndarray:
    """(32,) degrees, descending: evenly spaced -30.67 .. +10.67 deg."""
    return np.linspace(10.67, -30.67, 32)


def vlp32c_elevations() -> np.ndarray:
    """(32,) degrees, descending: the VLP-32C datasheet table, -25 .. +15 deg, 1/3 deg steps near 0."""
    first, last, count = _VLP32C_CORE
    return np.concatenate([_VLP32C_ABOVE, np.linspace(first, last, count), _VLP32C_BELOW])


def vls128_elevations() -> np.ndarray:
    """(128,) degrees, descending: c - a sinh(b (i - i0) / 127), +15 .. -25 deg, 0.11 deg apart at -1 deg."""
    c, a, b, i0 = _VLS128_SINH
    return c - a * np.sinh(b * (np.arange(128, dtype=np.float64) - i0) / 127)


def _pair_units() -> tuple[Unit, ...]:
    """The upper unit upright, the lower one upside down (elevations mirrored), PAIR_SPACING apart."""
    upright = vlp32c_elevations()
    return Unit(upright, PAIR_SPACING / 2), Unit(-upright[::-1].copy(), -PAIR_SPACING / 2)


_PRESETS = {
    Sensor.HDL64E: hdl64e_elevations,
    Sensor.WAYMO_TOP: waymo_top_elevations,
    Sensor.HDL32E: hdl32e_elevations,
    Sensor.VLP32C: vlp32c_elevations,
    Sensor.VLS128: vls128_elevations,
}


def sensor_spec(
    sensor: Sensor, height: float | None = None, elevation_file: Path | None = None
) -> SensorSpec:
    """The preset of `sensor`, optionally with its mounting height or beam table replaced (a table replaces
    the pair's two units by one)."""
    mount = SENSOR_HEIGHTS[sensor] if height is None else height
    if sensor == Sensor.VLP32C_PAIR and elevation_file is None:
        units = _pair_units()
        every = np.sort(np.concatenate([u.elevations_deg for u in units]))[::-1].copy()
        return SensorSpec(str(sensor), every, mount, units, PAIR_RANGE)
    if elevation_file is not None:
        return SensorSpec(str(sensor), load_elevations(elevation_file), mount)
    return SensorSpec(str(sensor), _PRESETS[sensor](), mount)


def load_elevations(path: Path) -> np.ndarray:
    """A beam table file -> (B,) degrees, descending.

    Formats: a Velodyne driver YAML (`vert_correction:` entries in radians, read without a YAML parser);
    a JSON list of degrees; any other text file with one elevation in degrees per line (`#` comments).
    """
    text = Path(path).read_text()
    if "vert_correction" in text:
        values = np.degrees([float(v) for v in re.findall(r"vert_correction:\s*([-+0-9.eE]+)", text)])
    elif Path(path).suffix == ".json":
        values = np.asarray(json.loads(text), np.float64)
    else:
        lines = (line.split("#")[0].strip() for line in text.splitlines())
        values = np.asarray([float(line) for line in lines if line], np.float64)
    values = np.sort(np.asarray(values, np.float64).reshape(-1))[::-1].copy()
    if len(values) == 0 or not np.all(np.abs(values) < 90):
        raise ValueError(f"{path}: expected beam elevations in degrees within (-90, 90)")
    return values
