"""sensor_msgs/msg/PointCloud2 decoding (ros/pointcloud2.py): every driver layout gives back the points
it was written from (a KITTI scan where the samples are, else a synthetic turn), row padding, big-endian
data, NaN returns, and errors that name the field."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
from conftest import REPO
from ros2_helpers import (
    BIG_ENDIAN,
    FLOAT32,
    LAYOUTS,
    OUSTER,
    UINT8,
    UINT8_INTENSITY,
    UINT16,
    UINT16_INTENSITY,
    VELODYNE_XYZIRT,
    Layout,
    pointcloud2_cdr,
    pointcloud2_message,
    sample_turns,
)

from lidar.readers import Spin
from ros.pointcloud2 import cloud_spin, decode_pointcloud2, pointcloud2_points, stamp_ns

INT_SCALES = {UINT8: 1 / 255, UINT16: 1 / 65535}  # integer intensity: 0..1 stored as 0..255 / 0..65535


@pytest.fixture(scope="module")
def turn() -> np.ndarray:
    return sample_turns(1)[0]  # (N, 4) float32, intensity 0..1


def expected(points: np.ndarray, layout: Layout) -> np.ndarray:
    """What decoding `layout` with its intensity scale must give: the same float32 x, y, z (float64 holds
    every float32), intensity exact for float layouts, else the rounded integer times the scale."""
    out = points.copy()
    scale = INT_SCALES.get(layout.intensity_type())
    if scale is not None:
        stored = np.rint(points[:, 3].astype(np.float64) / scale)
        out[:, 3] = (stored * scale).astype(np.float32)
    return out


@pytest.mark.parametrize("layout", LAYOUTS, ids=[layout.name for layout in LAYOUTS])
def test_every_layout_decodes_to_the_points_it_was_written_from(turn: np.ndarray, layout: Layout) -> None:
    scale = INT_SCALES.get(layout.intensity_type(), 1.0)
    cdr = pointcloud2_cdr(turn, layout, intensity_scale=scale, stamp_ns=1_700_000_000_123_456_789)
    msg = decode_pointcloud2(cdr)
    assert stamp_ns(msg) == 1_700_000_000_123_456_789 and msg.header.frame_id == "lidar"
    got = pointcloud2_points(msg, scale)
    assert got.dtype == np.float32 and got.shape == turn.shape
    np.testing.assert_array_equal(got, expected(turn, layout))
    if scale == 1.0:
        assert np.array_equal(got, turn)  # float32 intensity: bit for bit
    else:
        np.testing.assert_allclose(got[:, 3], turn[:, 3], atol=0.5 * scale + 1e-7)


@pytest.mark.parametrize("layout", [VELODYNE_XYZIRT, OUSTER, BIG_ENDIAN], ids=lambda layout: layout.name)
def test_organized_clouds_with_padded_rows(turn: np.ndarray, layout: Layout) -> None:
    """height > 1 and row_step > width * point_step: the junk after each row is skipped."""
    points = turn[: turn.shape[0] - turn.shape[0] % 16]
    msg = pointcloud2_message(points, layout, height=16, row_pad=7)
    assert msg.row_step == msg.width * layout.point_step + 7
    np.testing.assert_array_equal(pointcloud2_points(msg), points)
    # the last row without its padding is still a whole cloud
    short = replace(msg, data=msg.data[:-7])
    np.testing.assert_array_equal(pointcloud2_points(short), points)


def test_big_endian_flag_is_honoured(turn: np.ndarray) -> None:
    msg = pointcloud2_message(turn[:100], BIG_ENDIAN)
    assert msg.is_bigendian
    read_as_little = pointcloud2_points(replace(msg, is_bigendian=False))
    assert not np.array_equal(read_as_little[:, :3], turn[: read_as_little.shape[0], :3])


def test_intensity_scale_for_a_0_255_driver(turn: np.ndarray) -> None:
    """velodyne_pointcloud publishes float32 0..255: 1/255 brings it to the 0..1 the model was trained on."""
    msg = pointcloud2_message(turn, VELODYNE_XYZIRT, intensity_scale=1 / 255)
    raw = pointcloud2_points(msg)
    assert raw[:, 3].max() > 1.5  # as published
    scaled = pointcloud2_points(msg, intensity_scale=1 / 255)
    np.testing.assert_array_equal(scaled[:, :3], turn[:, :3])
    np.testing.assert_allclose(scaled[:, 3], turn[:, 3], rtol=1e-6, atol=1e-7)


def test_points_without_finite_xyz_are_dropped(turn: np.ndarray) -> None:
    points = turn[:1000].copy()
    points[::7, 0] = np.nan  # organized clouds fill missing returns with NaN
    points[3::11, 2] = np.inf
    points[5::13, 3] = np.nan  # a non-finite intensity alone keeps its point
    keep = np.isfinite(points[:, :3]).all(axis=1)
    for layout in (VELODYNE_XYZIRT, BIG_ENDIAN):
        msg = decode_pointcloud2(pointcloud2_cdr(points, layout, height=10))
        assert not msg.is_dense
        got = pointcloud2_points(msg)
        np.testing.assert_array_equal(got, points[keep])


def without(layout: Layout, name: str) -> Layout:
    return replace(layout, fields=tuple(f for f in layout.fields if f[0] != name))


def test_missing_and_unusable_fields_are_named(turn: np.ndarray) -> None:
    pts = turn[:10]
    for name in ("x", "y", "z", "intensity"):
        msg = pointcloud2_message(pts, VELODYNE_XYZIRT)
        msg = replace(msg, fields=[f for f in msg.fields if f.name != name])
        with pytest.raises(ValueError, match=rf"field '{name}': missing; the message has fields"):
            pointcloud2_points(msg)
    msg = pointcloud2_message(pts, VELODYNE_XYZIRT)
    bad_type = [replace(f, datatype=UINT8) if f.name == "y" else f for f in msg.fields]
    with pytest.raises(ValueError, match=r"field 'y': datatype 2; expected one of \['f4', 'f8'\]"):
        pointcloud2_points(replace(msg, fields=bad_type))
    unknown = [replace(f, datatype=9) if f.name == "intensity" else f for f in msg.fields]
    with pytest.raises(ValueError, match=r"field 'intensity': datatype 9"):
        pointcloud2_points(replace(msg, fields=unknown))
    counted = [replace(f, count=3) if f.name == "x" else f for f in msg.fields]
    with pytest.raises(ValueError, match=r"field 'x': count 3"):
        pointcloud2_points(replace(msg, fields=counted))
    past = [replace(f, offset=20) if f.name == "intensity" else f for f in msg.fields]
    with pytest.raises(ValueError, match=r"field 'intensity': offset 20 \+ 4 bytes is past point_step 22"):
        pointcloud2_points(replace(msg, fields=past))
    with pytest.raises(ValueError, match=r"PointCloud2 data: 219 bytes"):
        pointcloud2_points(replace(msg, data=msg.data[:-1]))
    assert UINT8_INTENSITY.intensity_type() == UINT8 and UINT16_INTENSITY.intensity_type() == UINT16
    assert VELODYNE_XYZIRT.intensity_type() == FLOAT32


def test_an_empty_cloud_is_no_points(turn: np.ndarray) -> None:
    msg = pointcloud2_message(turn[:0], OUSTER)
    assert pointcloud2_points(msg).shape == (0, 4)


def test_spin_from_the_net_rotation(turn: np.ndarray) -> None:
    """Ring-by-ring (KITTI) and firing-by-firing (synthetic) orders both tell the spin, either way round."""
    from lidar.synthetic import synthetic_turn

    for points in (turn, synthetic_turn(seed=3)):
        assert cloud_spin(points) is Spin.CCW
        assert cloud_spin(points[::-1]) is Spin.CW


def test_the_ros_package_imports_no_ros_library_until_one_is_used() -> None:
    code = (
        "import sys, ros.pointcloud2, ros.recordings, ros.scene, ros.messages, ros.node, ros.scans;"
        "import ros.live_view;"
        "print([m for m in ('rosbags', 'mcap', 'foxglove', 'torch') if m in sys.modules])"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True)
    assert done.stdout.strip() == "[]", done.stdout + done.stderr
