"""Where a checkout finds the real LiDAR samples it may use for tests and evaluation (never shipped): the
folder $PHIM_SAMPLES_DIR, else `shared/data` beside the repository. Commands fall back to other input when
the samples are not there; tests skip (or, in CI, fail) naming the missing path."""

from __future__ import annotations

import os
from pathlib import Path

from lidar.labels import FileFrame

SAMPLES_DIR = Path(
    os.environ.get("PHIM_SAMPLES_DIR") or Path(__file__).resolve().parents[1].parent / "shared" / "data"
)
KITTI_VELODYNE = SAMPLES_DIR / "kitti_object" / "velodyne"  # KITTI object scans 000000.bin ...
KITTI_000000 = KITTI_VELODYNE / "000000.bin"

# Samples that depart from their format's conventions: subfolder -> FileFrame. The Argoverse-1 conversion is
# in Argoverse's egovehicle frame (origin at the rear axle, ~0.33 m above the road); its two VLP-32s sit at
# (1.35, 0, 1.64) and (1.355, 0, 1.565) there (Argoverse-1 vehicle calibration): the sensor is taken as their
# middle. Its label_2 location is the box's centre, not KITTI's bottom centre: read by KITTI's rule its boxes
# float half their height too high (the median point of a labelled car at 13 % of its box's height, a fifth
# of the points within 1 m below the box under its bottom; as centres: 63 % and none; KITTI's own cars: 40 %).
SAMPLE_FRAMES: dict[str, FileFrame] = {
    "argoverse_kitti_format": FileFrame(origin=(1.35, 0.0, 1.60), label_z_is_centre=True),
}
