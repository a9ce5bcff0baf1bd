from __future__ import annotations

import gc
import os
from pathlib import Path

import pytest
import torch

from lidar.samples import KITTI_VELODYNE
from lidar.samples import SAMPLES_DIR as SHARED_DATA

REPO = Path(__file__).resolve().parents[1]
# CI sets this (.ci/run): a test that needs the real samples fails where they are missing instead of skipping
REQUIRE_SAMPLES = os.environ.get("PHIM_REQUIRE_SAMPLES") == "1"


def require_samples(path: Path = SHARED_DATA) -> Path:
    """`path` (a file or folder of the real LiDAR samples), or skip the test naming it (fail in CI)."""
    if not path.exists():
        why = (
            f"needs the real LiDAR samples: {path} is missing (put shared/data beside the repository or set "
            "PHIM_SAMPLES_DIR: README.md, Quick start)"
        )
        if REQUIRE_SAMPLES:
            pytest.fail(why)
        pytest.skip(why)
    return path


def pytest_runtest_setup(item: pytest.Item) -> None:
    """Tests marked `samples` read files of the real LiDAR samples (shared/data)."""
    if item.get_closest_marker("samples") is not None:
        require_samples()


@pytest.fixture(scope="module", autouse=True)
def _frozen_heap():
    """Each module runs with what earlier modules left on the heap frozen (gc.freeze), so that Python's full
    collections walk only the module's own objects. Without it, by the load-test modules a full collection
    walked ~800k objects for 0.5-0.6 s: a stall of every thread of the process (the in-process servers and
    clients) that failed their timing checks at random."""
    gc.collect()
    gc.freeze()
    yield
    gc.unfreeze()


@pytest.fixture(autouse=True)
def _seed_and_threads():
    """One torch thread: the tests' models are small, and on a busy machine two OpenMP threads spin-wait on
    each other (tests ran 6-10x slower with two under load, docs/benchmarks.md). Tests of a multi-threaded
    path set their own."""
    torch.manual_seed(0)
    torch.set_num_threads(1)


def kitti_scan(index: int = 0) -> torch.Tensor:
    """A real KITTI HDL-64E scan (N, 4) of the samples (skips, or fails in CI, where they are missing)."""
    from model.sectors import load_kitti_bin

    return load_kitti_bin(str(require_samples(KITTI_VELODYNE / f"{index:06d}.bin")))


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


def rss_bytes() -> int:
    """This process's resident memory (Linux /proc)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmRSS in /proc/self/status")
