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


# 132 of the 138 vehicles (KITTI 12, Argoverse 77, nuScenes 12, Waymo 37) are shorter than 6.5 m. Vehicles
# are drawn per body type (BODY_SIZES below); CAR is a reference the car mix is held to (tests).
CAR = SizeStats((4.43, 1.99, 1.77), (0.57, 0.29, 0.29), (3.0, 1.5, 1.35), (6.2, 2.6, 2.6))
# 6 vehicles of 6.5 m or longer (trucks, buses, a construction vehicle): 6 of 138 vehicles = 4.3 % (the share
# of large vehicles; their sizes come from BODY_SIZES).
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

# Vehicle body types (vehicles.py). The data sets label one VEHICLE class, so the per-type sizes come from
# public class means where a data set has the type, and typical dimensions of the segment otherwise. Widths
# are label widths, which leave the side mirrors out (nuScenes' annotator instructions: "Do not include
# vehicle side view mirrors"): the body fills the label box (short of an annotation margin that keeps its
# noisy returns inside), the mirrors stand out of it (vehicles.py):
# - nuScenes class means (the anchor sizes of the public nuScenes detection configs, computed from the
#   train split): car 4.63 x 1.97 x 1.74, truck 6.93 x 2.51 x 2.84, bus 10.5 x 2.94 x 3.47, trailer
#   12.29 x 2.90 x 3.87, bicycle 1.70 x 0.60 x 1.28, motorcycle 2.11 x 0.77 x 1.47, pedestrian 0.73 x 0.67 x
#   1.77; Waymo class means (the same configs): vehicle 4.73 x 2.08 x 1.77, pedestrian 0.91 x 0.84 x 1.74,
#   cyclist 1.81 x 0.84 x 1.77; KITTI Van 5.03 x 1.87 x 2.21.
# - sedan, hatchback, SUV and pickup: typical European / US dimensions of the segment (bodies 4.7-4.9,
#   3.9-4.3, 4.4-4.9 and 5.3-5.9 m long), widths held to the public label means; the mix below gives a car
#   mean of 4.71 x 2.00 x 1.68, between nuScenes' and Waymo's.
SEDAN, HATCHBACK, SUV, PICKUP, VAN, BOX_TRUCK, BUS, TRAILER = range(8)
BODY_NAMES = ("sedan", "hatchback", "suv", "pickup", "van", "box_truck", "bus", "trailer")
BODY_SIZES = (
    SizeStats((4.75, 1.96, 1.47), (0.22, 0.07, 0.05), (4.3, 1.8, 1.35), (5.3, 2.15, 1.6)),
    SizeStats((4.15, 1.90, 1.50), (0.22, 0.07, 0.06), (3.5, 1.7, 1.38), (4.6, 2.05, 1.65)),
    SizeStats((4.70, 2.05, 1.74), (0.28, 0.08, 0.08), (4.1, 1.85, 1.55), (5.2, 2.25, 1.95)),
    SizeStats((5.55, 2.15, 1.88), (0.30, 0.08, 0.08), (4.9, 1.95, 1.7), (6.2, 2.35, 2.05)),
    SizeStats((5.05, 2.05, 2.15), (0.40, 0.09, 0.18), (4.4, 1.85, 1.8), (6.2, 2.3, 2.7)),
    SizeStats((6.93, 2.51, 2.84), (1.20, 0.15, 0.35), (5.5, 2.2, 2.3), (10.0, 2.7, 3.8)),
    SizeStats((10.5, 2.94, 3.47), (1.50, 0.10, 0.20), (8.0, 2.6, 3.0), (13.0, 3.1, 4.0)),
    SizeStats((12.29, 2.90, 3.87), (1.60, 0.12, 0.25), (8.0, 2.5, 3.2), (14.5, 3.1, 4.2)),
)
CAR_BODIES = (0.30, 0.22, 0.28, 0.08, 0.12)  # shares of sedans .. vans among cars
LARGE_BODIES = (0.5, 0.3, 0.2)  # shares of box trucks, buses and (semi-)trailers among large vehicles
# Cyclists (people.py): a bicycle or, with this chance, a motorcycle, with their riders.
MOTORCYCLE_SHARE = 0.2
# a motorcycle with its rider: nuScenes' motorcycle mean length and width, the rider's helmet on top
MOTORCYCLE = SizeStats((2.11, 0.85, 1.65), (0.15, 0.06, 0.07), (1.8, 0.7, 1.5), (2.5, 1.0, 1.8))
