"""Test-only writers of ROS 2 data: sensor_msgs/msg/PointCloud2 CDR in the layouts real drivers publish, and
recordings holding them (rosbag2 with MCAP or sqlite3 storage, a plain MCAP written by the `mcap` library).

Nothing here is product code: the product only reads (ros/pointcloud2.py, ros/recordings.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from contract import MSGPACK, DetectionsReply, SectorMessage, Timings, decode_response, encode_sector
from lidar.sectorizer import Sector
from ros import messages
from ros.pointcloud2 import POINT_FIELD_TYPES, POINTCLOUD2, typestore

FLOAT32, FLOAT64, UINT8, UINT16, UINT32 = 7, 8, 2, 4, 6


@dataclass(frozen=True)
class Layout:
    name: str
    fields: tuple[tuple[str, int, int], ...]  # (name, offset, PointField datatype)
    point_step: int
    big_endian: bool = False

    def dtype(self) -> np.dtype:
        order = ">" if self.big_endian else "<"
        return np.dtype(
            {
                "names": [f[0] for f in self.fields],
                "formats": [order + POINT_FIELD_TYPES[f[2]] for f in self.fields],
                "offsets": [f[1] for f in self.fields],
                "itemsize": self.point_step,
            }
        )

    def intensity_type(self) -> int:
        return next(t for n, _, t in self.fields if n == "intensity")


# velodyne_pointcloud's PointXYZIRT: packed, 22 bytes, time unaligned at 18; intensity float32 0..255
VELODYNE_XYZIRT = Layout(
    "velodyne_xyzirt",
    (
        ("x", 0, FLOAT32),
        ("y", 4, FLOAT32),
        ("z", 8, FLOAT32),
        ("intensity", 12, FLOAT32),
        ("ring", 16, UINT16),
        ("time", 18, FLOAT32),
    ),
    22,
)
# Ouster-like (modelled on ouster-ros' point: PCL's 16-byte point with 4 bytes of padding after z, then
# intensity float32, t uint32 ns, reflectivity, ring, ambient uint16, range uint32; padded to 48 bytes)
OUSTER = Layout(
    "ouster",
    (
        ("x", 0, FLOAT32),
        ("y", 4, FLOAT32),
        ("z", 8, FLOAT32),
        ("intensity", 16, FLOAT32),
        ("t", 20, UINT32),
        ("reflectivity", 24, UINT16),
        ("ring", 26, UINT16),
        ("ambient", 28, UINT16),
        ("range", 32, UINT32),
    ),
    48,
)
# big-endian, float64 coordinates, intensity float32 at an unaligned offset, 30 bytes (odd-aligned points)
BIG_ENDIAN = Layout(
    "big_endian_f64",
    (
        ("x", 0, FLOAT64),
        ("y", 8, FLOAT64),
        ("z", 16, FLOAT64),
        ("ring", 24, UINT16),
        ("intensity", 26, FLOAT32),
    ),
    30,
    big_endian=True,
)
# Hesai-like: intensity uint8 0..255 right after z, ring uint16 and timestamp float64 unaligned after it
UINT8_INTENSITY = Layout(
    "uint8_intensity",
    (
        ("x", 0, FLOAT32),
        ("y", 4, FLOAT32),
        ("z", 8, FLOAT32),
        ("intensity", 12, UINT8),
        ("ring", 13, UINT16),
        ("timestamp", 15, FLOAT64),
    ),
    23,
)
# intensity first, uint16 (some drivers publish 16-bit signal), x, y, z unaligned after it
UINT16_INTENSITY = Layout(
    "uint16_intensity",
    (("intensity", 0, UINT16), ("x", 2, FLOAT32), ("y", 6, FLOAT32), ("z", 10, FLOAT32)),
    16,
)
LAYOUTS = (VELODYNE_XYZIRT, OUSTER, BIG_ENDIAN, UINT8_INTENSITY, UINT16_INTENSITY)


def pointcloud2_message(
    points: np.ndarray,
    layout: Layout = VELODYNE_XYZIRT,
    intensity_scale: float = 1.0,
    height: int = 1,
    row_pad: int = 0,
    frame_id: str = "lidar",
    stamp_ns: int = 0,
):
    """(N, 4) float32 x, y, z, intensity -> a rosbags PointCloud2 in `layout`: stored intensity is
    intensity / intensity_scale (rounded for integer types), other fields get plausible values (ring,
    time), `height` rows (N must divide) each followed by `row_pad` bytes of junk (0xAB)."""
    ts = typestore()
    n = points.shape[0]
    if n % height:
        raise ValueError(f"{n} points do not split into {height} rows")
    width = n // height
    rec = np.zeros(n, layout.dtype())  # (N,) structured, padding bytes zero
    for i, name in enumerate(("x", "y", "z")):
        rec[name] = points[:, i]
    stored = points[:, 3].astype(np.float64) / intensity_scale
    rec["intensity"] = np.rint(stored) if layout.intensity_type() not in (FLOAT32, FLOAT64) else stored
    for name in rec.dtype.names or ():
        if name not in ("x", "y", "z", "intensity"):
            rec[name] = np.arange(n) % 64  # ring-like values: what they are does not matter to the reader
    rows = rec.view(np.uint8).reshape(height, width * layout.point_step)
    junk = np.full((height, row_pad), 0xAB, np.uint8)
    data = np.ascontiguousarray(np.concatenate([rows, junk], axis=1)).reshape(-1)
    pf = ts.types["sensor_msgs/msg/PointField"]
    fields = [pf(name=name, offset=off, datatype=t, count=1) for name, off, t in layout.fields]
    header = ts.types["std_msgs/msg/Header"](
        stamp=ts.types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9),
        frame_id=frame_id,
    )
    return ts.types[POINTCLOUD2](
        header=header,
        height=height,
        width=width,
        fields=fields,
        is_bigendian=layout.big_endian,
        point_step=layout.point_step,
        row_step=width * layout.point_step + row_pad,
        data=data,
        is_dense=bool(np.isfinite(points[:, :3]).all()),
    )


def pointcloud2_cdr(points: np.ndarray, layout: Layout = VELODYNE_XYZIRT, **kw) -> bytes:
    """`pointcloud2_message` serialized as CDR (what a rosbag2 or a ROS 2 subscriber holds)."""
    return bytes(typestore().serialize_cdr(pointcloud2_message(points, layout, **kw), POINTCLOUD2))


def string_cdr(text: str) -> bytes:
    """A std_msgs/msg/String (the other topic a recording holds, which replay must skip)."""
    ts = typestore()
    return bytes(ts.serialize_cdr(ts.types["std_msgs/msg/String"](data=text), "std_msgs/msg/String"))


@dataclass(frozen=True)
class Recorded:
    topic: str
    msgtype: str
    stamp_ns: int
    cdr: bytes


def recording(
    turns: Sequence[np.ndarray], topic: str = "/velodyne_points", layout: Layout = VELODYNE_XYZIRT, **kw
) -> list[Recorded]:
    """A 10 Hz drive: each turn as a PointCloud2 on `topic`, a std_msgs/String on /chatter between them."""
    out: list[Recorded] = []
    for i, pts in enumerate(turns):
        t = 1_700_000_000_000_000_000 + i * 100_000_000
        out.append(Recorded(topic, POINTCLOUD2, t, pointcloud2_cdr(pts, layout, stamp_ns=t, **kw)))
        out.append(Recorded("/chatter", "std_msgs/msg/String", t + 50_000_000, string_cdr(f"turn {i}")))
    return out


def write_rosbag2(path: Path, messages: Sequence[Recorded], storage: str = "mcap") -> Path:
    """A rosbag2 folder (metadata.yaml + one .mcap or .db3) written by rosbags."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    ts = typestore()
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        conns = {}
        for m in messages:
            if m.topic not in conns:
                conns[m.topic] = writer.add_connection(m.topic, m.msgtype, typestore=ts)
            writer.write(conns[m.topic], m.stamp_ns, m.cdr)
    return path


def write_plain_mcap(
    path: Path, messages: Sequence[Recorded], profile: str = "", summary: bool = True
) -> Path:
    """A single .mcap file with ros2msg schemas and cdr channels, written by the `mcap` library as tools
    other than rosbag2 may write them: no metadata.yaml, no rosbag2 metadata record, any `profile` (rosbag2
    says "ros2"), and with `summary` False no index or summary (channels only where first used)."""
    from mcap.writer import IndexType, Writer

    ts = typestore()
    with open(path, "wb") as f:
        if summary:
            writer = Writer(f)
        else:
            off = dict(repeat_channels=False, repeat_schemas=False, use_statistics=False)
            writer = Writer(f, index_types=IndexType.NONE, use_summary_offsets=False, **off)
        writer.start(profile=profile, library="phim-tests")
        channels: dict[str, int] = {}
        for m in messages:
            if m.topic not in channels:
                text = ts.generate_msgdef(m.msgtype, ros_version=2)[0]
                schema = writer.register_schema(name=m.msgtype, encoding="ros2msg", data=text.encode())
                channels[m.topic] = writer.register_channel(
                    topic=m.topic, message_encoding="cdr", schema_id=schema
                )
            writer.add_message(channels[m.topic], log_time=m.stamp_ns, data=m.cdr, publish_time=m.stamp_ns)
        writer.finish()
    return path


def sample_turns(count: int = 2, every: int = 1) -> list[np.ndarray]:
    """(N, 4) float32 turns: KITTI scans 0, 1, ... where the samples are (CI demands them), else synthetic
    turns (lidar.synthetic), so these tests run without ../shared."""
    from conftest import KITTI_VELODYNE, REQUIRE_SAMPLES, kitti_scan

    from lidar.synthetic import synthetic_turn

    if KITTI_VELODYNE.exists() or REQUIRE_SAMPLES:
        return [kitti_scan(i).numpy()[::every].copy() for i in range(count)]
    return [synthetic_turn(seed=i)[::every].copy() for i in range(count)]


def reply_for(msg: SectorMessage, n_boxes: int = 2) -> DetectionsReply:
    """A made-up answer that names its sector: box centres at the sector's mean point, yaw = index - 1."""
    centre = msg.points[:, :3].mean(axis=0) if len(msg.points) else np.zeros(3, np.float32)
    boxes = np.array([[*centre, 4.0, 2.0, 1.5, msg.sector_index - 1.0]] * n_boxes, np.float32)  # (K, 7)
    scores = np.linspace(0.9, 0.5, n_boxes).astype(np.float32)
    return DetectionsReply(
        msg.stream_id, msg.seq, boxes, scores, np.zeros(n_boxes, np.int32), ("VEHICLE",) * n_boxes, 1, 0,
        Timings(1.0, 1.0, 2.0),
    )  # fmt: skip


def http_replies(
    url: str, stream_id: str, sectors: Sequence[Sector], fields: Sequence[str], stamp_ns: int, timeout: float
) -> list[DetectionsReply]:
    """The sectors sent over HTTP as stream `stream_id`, seq 0, 1, ... -> the server's replies, each checked
    to be detections: the reference a bridge's boxes are compared with."""
    replies = []
    for seq, sector in enumerate(sectors):
        msg = SectorMessage(stream_id, seq, sector.index, stamp_ns, sector.points, tuple(fields))
        r = httpx.post(
            f"{url}/v1/streams/{stream_id}/sectors",
            content=encode_sector(msg),
            headers={"Content-Type": MSGPACK},
            timeout=timeout,
        )
        reply = decode_response(r.content)
        assert isinstance(reply, DetectionsReply), reply
        replies.append(reply)
    return replies


def assert_boxes(array: Any, reply: DetectionsReply, atol: float = 1e-5) -> None:
    """A decoded Detection3DArray holds exactly the reply's boxes, in order."""
    assert len(array.detections) == len(reply.boxes)
    for d, box, score, name in zip(
        array.detections, reply.boxes, reply.scores, reply.class_names, strict=True
    ):
        c, s, h = d.bbox.center, d.bbox.size, d.results[0].hypothesis
        got = [c.position.x, c.position.y, c.position.z, s.x, s.y, s.z]
        np.testing.assert_allclose(got, box[:6], atol=atol, rtol=0)
        yaw = messages.yaw_of(c.orientation)
        assert abs(np.angle(np.exp(1j * (yaw - box[6])))) < 1e-5, (yaw, box[6])
        assert (h.class_id, len(d.results)) == (name, 1)
        assert abs(h.score - score) < atol
        assert d.results[0].pose.pose == c
