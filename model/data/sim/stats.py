"""Object size and spacing statistics of the simulator, derived once from real labels (numbers only).

Source: the labelled samples in ../shared/data (KITTI label_2 frames 000000-000005 and 000008, three
Argoverse-1 frames in KITTI format, one nuScenes v1.0-mini key frame, one Waymo Open Dataset frame), read
with a throw-away script; none of that data ships. Sizes are (length, width, height) in metres, length
along the heading. Class mapping: VEHICLE = KITTI Car/Van/Truck, nuScenes car/truck/bus/construction_vehicle,
Argoverse Car, Waymo VEHICLE; PEDESTRIAN = Pedestrian/pedestrian/PEDESTRIAN; CYCLIST = KITTI Cyclist,
nuScenes bicycle, Waymo CYCLIST.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SizeStats:
    mean: tuple[float, float, float]  # (l, w, h) metres
    std: tuple[float, float, float]
    low: tuple[float, float, float]  # clip limits of a drawn size
    high: tuple[float, float, float]

    def draw(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """(n, 3) sizes: independent normals, clipped."""
        size = rng.normal(self.mean, self.std, size=(n, 3))  # (n, 3)
        return np.clip(size, self.low, self.high)


# 132 of the 138 vehicles (KITTI 12, Argoverse 77, nuScenes 12, Waymo 37) are shorter than 6.5 m.
CAR = SizeStats((4.43, 1.99, 1.77), (0.57, 0.29, 0.29), (3.0, 1.5, 1.35), (6.2, 2.6, 2.6))
# 6 vehicles of 6.5 m or longer (trucks, buses, a construction vehicle): 6 of 138 vehicles = 4.3 %.
LARGE_VEHICLE = SizeStats((9.03, 2.95, 3.63), (1.91, 0.71, 0.48), (6.5, 2.3, 2.8), (13.0, 3.2, 4.3))
LARGE_VEHICLE_FRACTION = 0.043
# 188 pedestrians (Argoverse 144, nuScenes 30, Waymo 12, KITTI 2).
PEDESTRIAN = SizeStats((0.78, 0.72, 1.81), (0.17, 0.14, 0.13), (0.45, 0.45, 1.45), (1.3, 1.05, 2.05))
# Only 3 cyclists in the samples (KITTI, nuScenes, Waymo); their spread is small, the clip keeps it sane.
CYCLIST = SizeStats((1.86, 0.68, 1.79), (0.11, 0.06, 0.06), (1.6, 0.55, 1.6), (2.1, 0.85, 1.95))

# Spacing (Waymo frame, same-heading vehicles within 1.5 m laterally): bumper-to-bumper gaps of parked
# queues 0.1-3.3 m, then 5.5-14 m between moving or sparsely parked cars.
PARKED_GAP_M = (0.3, 3.3)
MOVING_GAP_M = (5.0, 20.0)
# Pedestrians walk in groups: the nearest-neighbour centre distance of 6 of 12 Waymo and 10 of 30 nuScenes
# pedestrians is 0.8-0.9 m.
GROUP_SPACING_M = 0.85
# Counts within 50 m: Waymo frame 27 vehicles, 9 pedestrians, 1 cyclist; nuScenes frame 4 cars and trucks,
# 20 pedestrians. The default count ranges (SceneConfig) bracket these.
