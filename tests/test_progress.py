"""Long commands say what they are doing on stderr (stdout stays the result), and none degrades silently:
without the real samples (PHIM_SAMPLES_DIR pointing at an empty folder, as in a clone without ../shared)
each command that falls back to other input says so on stderr, and one asked for what is missing fails.
Every command runs for real, as `phim ...` in a subprocess."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

NOTE = "note: the real samples"


def phim(
    args: list[str], samples: Path | None = None, timeout: float = 900
) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, **({"PHIM_SAMPLES_DIR": str(samples)} if samples is not None else {})}
    cmd = [sys.executable, "-m", "phim", *args]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.fixture
def no_samples(tmp_path: Path) -> Path:
    (tmp_path / "no-samples").mkdir()
    return tmp_path / "no-samples"


def test_model_info_says_what_it_is_doing(no_samples: Path) -> None:
    r = phim(["model", "info", "--config", "tiny", "--json"], no_samples)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["config"] == "tiny"  # stdout: the JSON alone
    stages = [line for line in r.stderr.splitlines() if line.startswith("[model info")]
    assert any("counting the FLOPs of the whole turn" in line for line in stages), r.stderr
    assert len(stages) >= 4 and NOTE not in r.stderr  # its default input is a synthetic turn: no fallback


def test_bench_refiner_without_the_samples_times_real_boxes_and_says_so(no_samples: Path) -> None:
    r = phim(["bench", "refiner", "--repeats", "1", "--json"], no_samples)
    assert r.returncode == 0, r.stderr
    result = json.loads(r.stdout)
    assert result["input"] == "simulate(seed=3)" and result["boxes"] > 0, result  # not zero boxes timed
    assert NOTE in r.stderr and str(no_samples) in r.stderr, r.stderr
    assert "[bench refiner" in r.stderr and "timing lookup, PointNet and refine" in r.stderr


def test_bench_refiner_fails_when_there_is_nothing_to_refine(tmp_path: Path) -> None:
    empty_scan = tmp_path / "far.bin"
    np.full((64, 4), 500.0, "<f4").tofile(empty_scan)  # points far out of range: no boxes
    r = phim(["bench", "refiner", "--repeats", "1", "--points", str(empty_scan)])
    assert r.returncode == 1 and "no boxes" in r.stderr and str(empty_scan) in r.stderr, r.stderr


def test_sim_compare_says_its_real_rows_are_missing_or_fails_when_asked_for_them(no_samples: Path) -> None:
    r = phim(["sim", "compare", "--seeds", "1", "--sensor", "hdl64e", "--samples", str(no_samples)])
    assert r.returncode == 2 and "--samples" in r.stderr and "kitti_object/velodyne" in r.stderr, r.stderr
    r = phim(["sim", "compare", "--seeds", "1", "--sensor", "hdl64e"], no_samples)
    assert r.returncode == 0, r.stderr
    assert NOTE in r.stderr and "simulated rows only" in r.stderr, r.stderr
    assert "sim hdl64e" in r.stdout and "real" not in r.stdout.replace("real samples", ""), r.stdout


@pytest.mark.parametrize(
    "args",
    [
        ["loadtest", "--url", "http://127.0.0.1:9", "--duration", "0.1", "--timeout", "1", "--no-progress"],
        ["bench", "server", "--url", "http://127.0.0.1:9", "--no-floor", "--turns", "1"],
    ],
    ids=["loadtest", "bench-server"],
)
def test_the_clients_say_they_send_synthetic_scans(args: list[str], no_samples: Path) -> None:
    """No server answers at that address: the commands fail, but only after saying what they would send."""
    r = phim(args, no_samples, timeout=300)
    assert NOTE in r.stderr and "synthetic" in r.stderr, r.stderr
    r = phim([*args, "--synthetic"] if args[0] == "loadtest" else args, no_samples, timeout=300)
    assert (NOTE not in r.stderr) == (args[0] == "loadtest"), r.stderr  # --synthetic asked for it: quiet
