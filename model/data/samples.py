"""Where a checkout finds the real LiDAR samples it may use for tests and evaluation (never shipped): the
folder $PHIM_SAMPLES_DIR, else `shared/data` beside the repository. Commands fall back to other input when
the samples are not there; tests skip (or, in CI, fail) naming the missing path."""

from __future__ import annotations

import os
from pathlib import Path

SAMPLES_DIR = Path(
    os.environ.get("PHIM_SAMPLES_DIR") or Path(__file__).resolve().parents[2].parent / "shared" / "data"
)
KITTI_VELODYNE = SAMPLES_DIR / "kitti_object" / "velodyne"  # KITTI object scans 000000.bin ...
KITTI_000000 = KITTI_VELODYNE / "000000.bin"

# Samples whose points and labels are not in the sensor's frame: subfolder -> the sensor's position (x, y, z)
# in their frame, metres. The Argoverse-1 conversion is in Argoverse's egovehicle frame (origin at the rear
# axle, ~0.33 m above the road); its two VLP-32s sit at (1.35, 0, 1.64) and (1.355, 0, 1.565) there
# (Argoverse-1 vehicle calibration): the sensor is taken as their middle.
SENSOR_ORIGINS: dict[str, tuple[float, float, float]] = {"argoverse_kitti_format": (1.35, 0.0, 1.60)}

# KITTI-layout samples whose label_2 location is the box's centre, not its bottom centre (KITTI's rule): the
# Argoverse conversion. Read by KITTI's rule its boxes float half their height too high: the median point of
# a labelled car sits at 13 % of its box's height and a fifth of the points within 1 m below the box lie
# under its bottom; lowered by half the height, 63 % and none (KITTI's own cars: 40 %).
LABEL_Z_IS_CENTRE: frozenset[str] = frozenset({"argoverse_kitti_format"})
