"""`phim replay` on broken input (real files, the real CLI): a one-line error naming the file and exit code 2,
never a traceback; a KITTI .bin is never truncated, and one without a finite point says so."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from ros2_helpers import POINTCLOUD2, Recorded, recording, write_plain_mcap, write_rosbag2
from server_helpers import free_port

from lidar.readers import read_scan
from lidar.synthetic import synthetic_turn
from phim.cli import main as app


def replay_cli(source: Path, tmp_path: Path) -> tuple[int, str, BaseException | None]:
    url = f"http://127.0.0.1:{free_port()}"  # nothing there: the input fails first
    args = ["replay", str(source), "--url", url, "--out", str(tmp_path / "p.jsonl"), "--rate", "0"]
    result = CliRunner().invoke(app, args)
    return result.exit_code, result.output, result.exception


def assert_one_line_error(source: Path, tmp_path: Path, says: str) -> None:
    code, output, exception = replay_cli(source, tmp_path)
    assert code == 2 and isinstance(exception, SystemExit), output  # not an uncaught exception
    assert "Traceback" not in output and str(source.name) in output and says in output, output


def test_a_corrupt_npz(tmp_path: Path):
    bad = tmp_path / "000000.npz"
    bad.write_bytes(b"PK\x03\x04" + bytes(range(200)))
    assert_one_line_error(bad, tmp_path, "not a readable native scan")


def test_a_kitti_bin_is_never_truncated(tmp_path: Path):
    bad = tmp_path / "000000.bin"
    bad.write_bytes(np.ones((10, 4), "<f4").tobytes() + b"\x00\x00")  # 162 bytes: 40.5 floats
    with pytest.raises(ValueError, match="162 bytes is not a multiple of 16"):
        read_scan(bad)
    assert_one_line_error(bad, tmp_path, "is not a multiple of 16")


def test_a_kitti_bin_without_a_finite_point_says_so(tmp_path: Path):
    bad = tmp_path / "000000.bin"
    bad.write_bytes(np.full((100, 4), np.nan, "<f4").tobytes())
    assert_one_line_error(bad, tmp_path, "none of its 100 points has finite x, y, z")
    good = tmp_path / "good" / "000000.bin"
    good.parent.mkdir()
    good.write_bytes(synthetic_turn(seed=1).astype("<f4").tobytes())
    assert read_scan(good).points.shape[1] == 4


def test_a_corrupt_or_truncated_mcap(tmp_path: Path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 4)
    assert_one_line_error(junk, tmp_path, "not a readable MCAP file")
    whole = write_plain_mcap(tmp_path / "whole.mcap", recording([synthetic_turn(seed=2)[::8]] * 3))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size * 2 // 3])
    code, output, exception = replay_cli(cut, tmp_path)
    assert code == 2 and isinstance(exception, SystemExit) and "Traceback" not in output, output
    assert "cut.mcap" in output


def test_junk_cdr_in_a_recording(tmp_path: Path):
    messages = [Recorded("/velodyne_points", POINTCLOUD2, 1_700_000_000_000_000_000, b"\x00\x01\x00\x00junk")]
    folder = write_rosbag2(tmp_path / "bag", messages)
    assert_one_line_error(folder, tmp_path, "not a PointCloud2 in CDR")
