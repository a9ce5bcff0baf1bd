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


@dataclass(frozen=True)
class SensorSpec:
    name: str
    elevations_deg: np.ndarray  # (B,) float64 beam elevations, descending (top beam first)
    height: float  # metres above the ground under the sensor

    @property
    def beams(self) -> int:
        return int(self.elevations_deg.shape[0])


# Waymo TOP: elevation (deg) = polyval(coefficients, i / 63) for beam i = 0 (lowest) .. 63 (highest).
_WAYMO_TOP_POLY_DEG = (16.03190, -20.65970, -13.51010, 38.19870, -17.49810)

SENSOR_HEIGHTS = {  # metres above the ground
    Sensor.HDL64E: 1.73,  # KITTI setup
    Sensor.WAYMO_TOP: 2.184,  # TOP extrinsic z above the vehicle origin (near ground level)
    Sensor.HDL32E: 1.84,  # nuScenes LIDAR_TOP
}


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


_PRESETS = {
    Sensor.HDL64E: hdl64e_elevations,
    Sensor.WAYMO_TOP: waymo_top_elevations,
    Sensor.HDL32E: hdl32e_elevations,
}


def sensor_spec(
    sensor: Sensor, height: float | None = None, elevation_file: Path | None = None
) -> SensorSpec:
    """The preset of `sensor`, optionally with its mounting height or beam table replaced."""
    elevations = _PRESETS[sensor]() if elevation_file is None else load_elevations(elevation_file)
    return SensorSpec(str(sensor), elevations, SENSOR_HEIGHTS[sensor] if height is None else height)


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
