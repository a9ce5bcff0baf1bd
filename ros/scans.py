"""A PointCloud2 sample of the bridge -> the points it carries, checked, and the model's sectors to send.

`read_scan` decodes one sample's CDR bytes and refuses, with the error code the bridge counts, what cannot
be served: a message over `max_body_bytes`, bytes that are no PointCloud2, a layout the model cannot read
(ros.pointcloud2), a `header.frame_id` over `max_string_len` (it is copied into every box's header). One
rule for a non-finite value, in a coordinate (a driver's "no return") or the intensity alike: the point is
dropped. `ScanCutter` cuts the points into the model's sectors: a whole turn at once, or (partial scans) a
piece of one, sectorized as it comes.
"""

from __future__ import annotations

import numpy as np

from contract import REQUIRED_FIELDS, ErrorCode, Limits, ServiceError
from lidar.sectorizer import StreamSectorizer, split_scan
from ros.messages import Header
from ros.pointcloud2 import cloud_spin, decode_pointcloud2, pointcloud2_points, stamp_ns


def read_scan(data: bytes, limits: Limits, intensity_scale: float) -> tuple[np.ndarray, Header]:
    """CDR bytes of a sensor_msgs/msg/PointCloud2 -> ((N, 4) float32 x, y, z, intensity * `intensity_scale`,
    the header its answers echo); ServiceError (TOO_LARGE, BAD_REQUEST, INVALID_FIELD) saying why not."""
    if len(data) > limits.max_body_bytes:
        why = f"{len(data)} bytes; the limit is {limits.max_body_bytes} (--max-body-bytes)"
        raise ServiceError(ErrorCode.TOO_LARGE, why)
    try:
        msg = decode_pointcloud2(data)
    except Exception as e:  # rosbags raises what the bytes make it hit: struct, index, value errors
        raise ServiceError(
            ErrorCode.BAD_REQUEST, f"not a sensor_msgs/msg/PointCloud2 in CDR ({e!r})"
        ) from None
    try:
        points = pointcloud2_points(msg, intensity_scale)  # (N, 4) float32
    except ValueError as e:
        raise ServiceError(ErrorCode.INVALID_FIELD, str(e)) from None
    frame_id = str(msg.header.frame_id)
    if len(frame_id) > limits.max_string_len:  # copied into every box's and marker's header
        why = f"header.frame_id: {len(frame_id)} characters; at most {limits.max_string_len}"
        raise ServiceError(ErrorCode.INVALID_FIELD, why + " (--max-string-len)")
    points = points[np.isfinite(points[:, 3])]  # (N', 4): one rule, a point with any NaN/inf is dropped
    return points, Header(max(0, stamp_ns(msg)), frame_id)


class ScanCutter:
    """PointCloud2 points, message after message -> the sectors to send, each with the header it answers."""

    def __init__(self, sectors: int, partial_scans: bool):
        self.sectors, self.partial = sectors, partial_scans
        self._stream: StreamSectorizer | None = None

    def push(self, points: np.ndarray, header: Header) -> list[tuple[int, np.ndarray, Header]]:
        """points (N, 4) float32 in the message's (firing) order -> (sector index, (M, 4) points, header)."""
        if not self.partial:  # a whole turn: its sectors in sweep order, starting where the scan starts
            cut = split_scan(points, REQUIRED_FIELDS, self.sectors, cloud_spin(points))
            return [(s.index, s.points, header) for s in cut]
        if self._stream is None:
            if points.shape[0] < 2:
                return []  # the spin is unknown until there are two points
            self._stream = StreamSectorizer(REQUIRED_FIELDS, self.sectors, cloud_spin(points))
        return [(s.index, s.points, header) for s in self._stream.push(points)]
