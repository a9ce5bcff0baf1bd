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
