from __future__ import annotations

from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
KITTI_VELODYNE = SHARED_DATA / "kitti_object" / "velodyne"


@pytest.fixture(autouse=True)
def _seed_and_threads():
    torch.manual_seed(0)
    torch.set_num_threads(2)


def kitti_scan(index: int = 0) -> torch.Tensor:
    """A real KITTI HDL-64E scan (N, 4); the tests need ../shared/data beside the repository."""
    from model.sectors import load_kitti_bin

    path = KITTI_VELODYNE / f"{index:06d}.bin"
    if not path.is_file():
        pytest.fail(f"test data missing: {path} (shared/data must sit beside the repository)")
    return load_kitti_bin(str(path))


# Server-side tests: two real KITTI scans in 4 sectors (every 4th point, for speed) and what the module's own
# `det` fixture (a StreamingDetector) gives for them run directly.


@pytest.fixture(scope="module")
def scan_a() -> list:
    from server_helpers import kitti_sectors

    return kitti_sectors(0, every=4)


@pytest.fixture(scope="module")
def scan_b() -> list:
    from server_helpers import kitti_sectors

    return kitti_sectors(1, every=4)


@pytest.fixture(scope="module")
def ref_a(det, scan_a) -> list:
    from server_helpers import run_direct

    return run_direct(det, scan_a)


@pytest.fixture(scope="module")
def ref_b(det, scan_b) -> list:
    from server_helpers import run_direct

    return run_direct(det, scan_b)
