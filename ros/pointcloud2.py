"""ROS 2 sensor_msgs/msg/PointCloud2 -> the model's (N, 4) float32 x, y, z, intensity points.

Drivers lay their points out as they like (velodyne_pointcloud: x, y, z, intensity float32 + ring uint16
+ time float32, 22 bytes a point; Ouster: padding, t, reflectivity, ambient; Hesai: uint8 intensity; ...), so
the layout is read from the message itself: each field's name, offset, datatype and count, `point_step` bytes
a point, `row_step` bytes a row (rows may be padded), `height` x `width` points, `is_bigendian`. Only x,
y, z and intensity are read; every other field is ignored.

Intensity scale: the models take intensity in 0..1 (docs/model-card.md; KITTI's reflectance, the simulator's,
nuScenes' 0..255 divided by 255 on reading: docs/data.md), so a driver publishing 0..255
(velodyne_pointcloud, Ouster's 8-bit reflectivity, uint8 Hesai/Livox) needs `intensity_scale=1/255`; a
driver already in 0..1 needs 1.0.

Numpy only at import time: rosbags (CDR) is imported when a message is first decoded.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from contract import MAX_COORDINATE_M
from lidar.readers import Spin

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
OUTPUT_FIELDS: tuple[str, ...] = ("x", "y", "z", "intensity")

# sensor_msgs/msg/PointField datatype constants -> numpy type (without byte order)
POINT_FIELD_TYPES: dict[int, str] = {
    1: "i1",  # INT8
    2: "u1",  # UINT8
    3: "i2",  # INT16
    4: "u2",  # UINT16
    5: "i4",  # INT32
    6: "u4",  # UINT32
    7: "f4",  # FLOAT32
    8: "f8",  # FLOAT64
}
_XYZ_TYPES = (7, 8)  # coordinates are float32 or float64 in every driver we know; ints would be scaled units


@functools.cache
def typestore() -> Any:
    # Humble's and Jazzy's PointCloud2 / PointField / Header definitions are identical, so either store
    # decodes both; cached because building a typestore parses every message definition
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def decode_pointcloud2(cdr: bytes | bytearray | memoryview) -> Any:
    """CDR bytes of a sensor_msgs/msg/PointCloud2 (as on the wire or in a rosbag2) -> the rosbags message
    (`.header.stamp.sec/.nanosec`, `.header.frame_id`, `.fields`, `.data` (B,) uint8, ...)."""
    return typestore().deserialize_cdr(bytes(cdr), POINTCLOUD2)


def stamp_ns(msg: Any) -> int:
    """The message's header stamp in nanoseconds."""
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def _field_dtype(
    msg: Any, name: str, allowed: tuple[int, ...], point_step: int, order: str
) -> tuple[np.dtype, int]:
    """(numpy dtype, offset) of field `name`; ValueError naming the field when missing or unusable."""
    found = [f for f in msg.fields if f.name == name]
    if not found:
        have = [f.name for f in msg.fields]
        raise ValueError(f"PointCloud2 field {name!r}: missing; the message has fields {have}")
    f = found[0]
    if f.datatype not in allowed:
        names = [POINT_FIELD_TYPES[t] for t in allowed]
        raise ValueError(f"PointCloud2 field {name!r}: datatype {f.datatype}; expected one of {names}")
    if f.count > 1:
        raise ValueError(f"PointCloud2 field {name!r}: count {f.count}; expected 1")
    dt = np.dtype(order + POINT_FIELD_TYPES[f.datatype])
    if f.offset < 0 or f.offset + dt.itemsize > point_step:
        raise ValueError(
            f"PointCloud2 field {name!r}: offset {f.offset} + {dt.itemsize} bytes"
            f" is past point_step {point_step}"
        )
    return dt, int(f.offset)


def _packed_rows(msg: Any) -> np.ndarray:
    """The message's data without row padding -> (height * width * point_step,) uint8."""
    height, width, point_step, row_step = (
        int(msg.height),
        int(msg.width),
        int(msg.point_step),
        int(msg.row_step),
    )
    raw = msg.data  # rosbags gives (B,) uint8; raw bytes from elsewhere are read in place
    if isinstance(raw, bytes | bytearray | memoryview):
        data = np.frombuffer(raw, dtype=np.uint8)
    else:
        data = np.ascontiguousarray(raw, dtype=np.uint8).reshape(-1)
    row_bytes = width * point_step
    if row_step < row_bytes:
        raise ValueError(f"PointCloud2 row_step: {row_step}; expected >= width * point_step = {row_bytes}")
    # the last row may omit its padding: only its points must be there
    need = (height - 1) * row_step + row_bytes if height else 0
    if data.size < need:
        raise ValueError(
            f"PointCloud2 data: {data.size} bytes; {height} rows of row_step {row_step} need {need}"
        )
    if row_step == row_bytes or height <= 1:
        return data[: height * row_bytes]
    # a strided view (H, row_bytes) over the padded rows: the byte count was checked above, so it stays inside
    rows = np.lib.stride_tricks.as_strided(
        data, shape=(height, row_bytes), strides=(row_step, 1), writeable=False
    )
    return rows.reshape(-1)  # copies once, without the padding


def pointcloud2_points(msg: Any, intensity_scale: float = 1.0) -> np.ndarray:
    """A decoded PointCloud2 -> (N, 4) float32 x, y, z, intensity * `intensity_scale`, in the message's
    point order (firing order for a driver that publishes a turn as it fires).

    Points whose x, y or z is not finite (NaN/inf: no return, in organized clouds) are dropped, whatever
    `is_dense` says. ValueError naming the field when x, y, z or intensity is missing, has count > 1, lies
    past `point_step`, or has a datatype the model cannot use (x, y, z: float32/float64; intensity: any
    numeric PointField type), and when a finite x, y or z lies beyond the contract's coordinate range
    (`contract.MAX_COORDINATE_M`: a corrupt cloud or a wrong `is_bigendian`; the whole cloud is refused).
    See the module docstring for which `intensity_scale` a driver needs.
    """
    point_step = int(msg.point_step)
    order = ">" if msg.is_bigendian else "<"
    all_types = tuple(POINT_FIELD_TYPES)
    parts = [_field_dtype(msg, n, _XYZ_TYPES, point_step, order) for n in OUTPUT_FIELDS[:3]]
    parts.append(_field_dtype(msg, "intensity", all_types, point_step, order))
    n = int(msg.height) * int(msg.width)
    if n == 0:
        return np.zeros((0, 4), np.float32)
    if point_step <= 0:
        raise ValueError(f"PointCloud2 point_step: {point_step}; expected > 0")
    # explicit offsets and itemsize: padding, unaligned fields and ignored fields need no special case
    layout = np.dtype(
        {
            "names": list(OUTPUT_FIELDS),
            "formats": [dt for dt, _ in parts],
            "offsets": [off for _, off in parts],
            "itemsize": point_step,
        }
    )
    records = np.frombuffer(_packed_rows(msg), dtype=layout, count=n)  # (N,) structured
    out = np.empty((n, 4), np.float32)
    for i, name in enumerate(OUTPUT_FIELDS[:3]):
        out[:, i] = _coordinate(records[name], name, bool(msg.is_bigendian))
    with np.errstate(over="ignore", invalid="ignore"):
        # float64 keeps a scaled uint16/uint32 intensity exact before the cast
        out[:, 3] = records["intensity"].astype(np.float64) * intensity_scale
    keep = np.isfinite(out[:, :3]).all(axis=1)  # (N,)
    return out if keep.all() else out[keep]


def _coordinate(values: np.ndarray, name: str, big_endian: bool) -> np.ndarray:
    """A coordinate field's values (N,) float32 or float64 -> the same as float32; ValueError naming the field
    when a finite value lies beyond the contract's range (|v| <= MAX_COORDINATE_M): no LiDAR returns that
    far, so the cloud is corrupt or its byte order is not the one `is_bigendian` declares (little-endian
    float32 read as big-endian reaches 3e38). NaN and inf (no return) pass, for `pointcloud2_points` to
    drop."""
    with np.errstate(invalid="ignore"):
        far = np.isfinite(values) & (np.abs(values) > MAX_COORDINATE_M)  # (N,)
    if far.any():
        first = int(far.argmax())
        order = "big" if big_endian else "little"
        raise ValueError(
            f"PointCloud2 field {name!r}: {int(far.sum())} points beyond {MAX_COORDINATE_M:g} m (point "
            f"{first}: {float(values[first]):g}); expected |{name}| <= {MAX_COORDINATE_M:g} m (is the data "
            f"{order}-endian, as is_bigendian says?)"
        )
    return values.astype(np.float32)


def cloud_spin(points: np.ndarray) -> Spin:
    """Spin direction of a turn (N, >=2) x, y, ... in message order, from its net rotation: the sum of the
    wrapped azimuth steps between consecutive points.

    The sum, not the median step (`lidar.sectorizer.detect_spin`): a driver that publishes firing by
    firing (all beams of one azimuth, then the next) has a median step of ~0, whose sign is noise, while
    the sum adds up to about +-2 pi per turn (per ring for ring-by-ring clouds) either way.
    """
    if points.shape[0] < 2:
        return Spin.CCW
    azimuth = np.arctan2(points[:, 1], points[:, 0]).astype(np.float64)  # (N,)
    step = np.mod(np.diff(azimuth) + np.pi, 2 * np.pi) - np.pi  # (N-1,) in [-pi, pi)
    return Spin.CCW if float(step.sum()) >= 0 else Spin.CW
