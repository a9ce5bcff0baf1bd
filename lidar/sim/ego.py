"""The ego vehicle as the sensor sees it: its roof under the sensor (returns within about 1 m), and its motion
during the sweep.

Roof returns. nuScenes' LIDAR_TOP sits about 0.34 m above the roof: in the sample sweep its lowest rings hit
the roof 0.26-0.44 m below the sensor, from 1.1 m behind to 0.6 m ahead of it (ring 0 on 69 % of the firings,
ring 4 on 47 %, ring 7 on 15 %, ring 8 on 4 %), about 4,000 points; most of the other 4,400 of its 8,029
points within 1 m lie on one line behind the sensor (y = 0, z = 0), a driver artefact that is not modelled.
KITTI's HDL-64E and Argoverse's VLP-32C pair report next to nothing within 2.5 m (no body here). The roof
is a level rectangle in the sensor's frame; it moves with the sensor.

Motion. The ego drives straight along its lane (the heading of the scene's first road) at `speed` m/s during
the turn. Firing f happens at time f / (F * rate); its rays start where the sensor is then. Points and labels
are in the sensor's frame at the END of the turn (motion-compensated, as nuScenes and Waymo publish their
sweeps): a static object's points line up with its box wherever in the turn they were taken, while the rays
of early firings started up to speed / rate metres behind (1.5 m at 15 m/s, 10 Hz). The sensor keeps its
height above the ground under it. KITTI's scans are not compensated (a seam of up to speed / rate metres
behind the car); that is not modelled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lidar.sim.ground import Ground
from lidar.sim.sensors import Sensor

EGO_MIN_RANGE = 0.05  # metres: nearer roof returns are not reported


@dataclass(frozen=True)
class EgoBody:
    """The roof under the sensor: a level rectangle `drop` metres below it (sensor frame, x forward)."""

    drop: float  # metres below the sensor
    front: float  # metres ahead of the sensor
    back: float  # metres behind it
    half_width: float  # metres to each side
    reflectivity: float = 0.3

    def scaled(self, factor: float) -> EgoBody:
        return EgoBody(
            self.drop * factor, self.front * factor, self.back * factor, self.half_width * factor,
            self.reflectivity,
        )  # fmt: skip


# Fitted (least squares over a grid) to the share of firings per ring that hit the roof in the nuScenes
# sample: 0.68, 0.62, 0.57, 0.53, 0.42, 0.32, 0.25, 0.13, 0.04 for rings 0-8 (real 0.69 ... 0.04, above).
EGO_BODY: dict[Sensor, EgoBody | None] = {
    Sensor.HDL64E: None,
    Sensor.WAYMO_TOP: None,
    Sensor.HDL32E: EgoBody(0.34, 0.7, 0.85, 0.5),
    Sensor.VLP32C: None,
    Sensor.VLP32C_PAIR: None,
    Sensor.VLS128: None,
}


def roof_range(body: EgoBody, dx: np.ndarray, dy: np.ndarray, dz: np.ndarray, lift: float) -> np.ndarray:
    """(R,) unit directions in the sensor frame -> (R,) float32 range to the roof, inf where a ray misses it;
    `lift` raises the ray's start above the sensor (a unit of a stack)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(dz < -1e-3, (body.drop + lift) / -dz, np.inf).astype(np.float32)
        x, y = t * dx, t * dy  # inf * 0: nan, outside
    inside = (x <= body.front) & (x >= -body.back) & (np.abs(y) <= body.half_width) & (t >= EGO_MIN_RANGE)
    return np.where(inside, t, np.inf).astype(np.float32)


def sweep_origins(
    ground: Ground, heading: float, speed: float, firings: int, rate_hz: float
) -> np.ndarray | None:
    """(F, 3) float64: where the sensor is at each firing, in its frame at the end of the turn (None when it
    stands still). Firing f is at time f / (F * rate); the turn ends at 1 / rate."""
    if speed <= 0:
        return None
    back = speed * (1 / rate_hz - np.arange(firings) / (firings * rate_hz))  # (F,) metres behind the end
    x, y = -back * math.cos(heading), -back * math.sin(heading)
    z = ground.height_at(x, y) + ground.height  # keeps its height above the ground under it
    return np.stack([x, y, z], 1)
