"""ROS 2 recordings -> Scans: one sensor_msgs/msg/PointCloud2 message is one turn.

A recording is a rosbag2 folder (metadata.yaml beside MCAP or sqlite3 storage files, read by rosbags), or one
storage file on its own: a `.db3` (rosbags) or a `.mcap` (the `mcap` library: rosbag2's, or one written by
any tool with ros2msg schemas and CDR messages, whatever its profile). Only the PointCloud2 messages of one
topic are read, in log order; every other topic is skipped. Each message's points are decoded by its own
field layout (ros.pointcloud2), its spin is detected from the points, its time is the header stamp
(the log time when the stamp is zero).

Numpy only at import time: rosbags and mcap are imported when a recording is opened (`pip install
"phim[ros2]"`).
"""

from __future__ import annotations

import contextlib
import importlib
import itertools
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from contract import REQUIRED_FIELDS
from lidar.readers import Scan
from ros.pointcloud2 import POINTCLOUD2, cloud_spin, decode_pointcloud2, pointcloud2_points, stamp_ns

RECORDING_SUFFIXES = (".mcap", ".db3")


def is_recording(path: Path) -> bool:
    """A rosbag2 folder (holds metadata.yaml) or a single .mcap / .db3 storage file."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.is_file() and path.suffix in RECORDING_SUFFIXES


def _import(module: str, path: Path) -> Any:
    try:
        return importlib.import_module(module)
    except ImportError as e:  # the clients extra alone has neither rosbags nor mcap
        raise ValueError(f"{path}: reading ROS 2 recordings needs {module}: pip install 'phim[ros2]'") from e


def _is_mcap_file(path: Path) -> bool:
    return path.is_file() and path.suffix == ".mcap"


def recording_topics(path: Path) -> dict[str, str]:
    """Every topic of the recording -> its message type (e.g. 'sensor_msgs/msg/PointCloud2'; an MCAP
    channel that is not CDR gets its encoding in front, e.g. 'protobuf:foxglove.PointCloud')."""
    path = Path(path)
    if _is_mcap_file(path):
        return _mcap_topics(path)
    rosbag2 = _import("rosbags.rosbag2", path)
    try:
        with rosbag2.Reader(path) as reader:
            return {c.topic: c.msgtype for c in reader.connections}
    except rosbag2.ReaderError as e:
        raise ValueError(f"{path}: not a readable rosbag2 recording: {e}") from e


def _mcap_topics(path: Path) -> dict[str, str]:
    """A single .mcap, read with the mcap library: rosbags' MCAP reader wants the ros2 profile, which
    MCAP files written by other tools (ros2msg schemas, CDR messages) need not declare."""
    reader_module = _import("mcap.reader", path)
    topics: dict[str, str] = {}
    try:
        with open(path, "rb") as f:
            reader = reader_module.make_reader(f)
            summary = reader.get_summary()
            if summary is not None and summary.channels:
                pairs = [(summary.schemas.get(c.schema_id), c) for c in summary.channels.values()]
            else:  # no channels in a summary (a recorder that did not finish, or wrote none): read through
                pairs = [(schema, c) for schema, c, _ in reader.iter_messages()]
            for schema, channel in pairs:
                name = schema.name if schema is not None else "?"
                cdr = channel.message_encoding == "cdr"
                topics[channel.topic] = name if cdr else f"{channel.message_encoding}:{name}"
    except Exception as e:  # the mcap library raises its own errors (and struct/EOF ones) on bad files
        raise ValueError(f"{path}: not a readable MCAP file: {e}") from e
    return topics


def choose_topic(path: Path, topic: str | None = None) -> str:
    """The PointCloud2 topic to read: `topic` when it holds PointCloud2, else the only PointCloud2 topic;
    ValueError listing the candidates when there are none or several, or `topic` is not one of them."""
    topics = recording_topics(path)
    clouds = sorted(t for t, kind in topics.items() if kind == POINTCLOUD2)
    if topic is not None:
        if topic in clouds:
            return topic
        what = f"a {topics[topic]} topic" if topic in topics else "not in the recording"
        raise ValueError(f"{path}: topic {topic!r} is {what}; its {POINTCLOUD2} topics: {clouds}")
    if len(clouds) == 1:
        return clouds[0]
    if not clouds:
        raise ValueError(f"{path}: no {POINTCLOUD2} topic; its topics: {dict(sorted(topics.items()))}")
    raise ValueError(f"{path}: {len(clouds)} {POINTCLOUD2} topics {clouds}; name one (phim replay --topic)")


def read_recording(path: Path, topic: str | None = None, intensity_scale: float = 1.0) -> Iterator[Scan]:
    """The PointCloud2 messages of `topic` (see `choose_topic`) -> one Scan per message, in log order:
    (N, 4) float32 x, y, z, intensity * `intensity_scale` (ros.pointcloud2 says which scale a
    driver needs), named by their index ('000000', ...).

    The topic is checked now (ValueError before anything is read); the messages are read as the iterator
    is consumed, so a long drive is never held in memory.
    """
    path = Path(path)
    chosen = choose_topic(path, topic)
    return _scans(path, chosen, intensity_scale)


def _messages(path: Path, topic: str) -> Iterator[tuple[int, bytes]]:
    """(log time ns, CDR bytes) of the PointCloud2 messages on `topic`, in log order."""
    if _is_mcap_file(path):
        reader_module = _import("mcap.reader", path)
        with open(path, "rb") as f:
            reader = reader_module.make_reader(f)
            for schema, channel, message in reader.iter_messages(topics=[topic], log_time_order=True):
                if schema is not None and schema.name == POINTCLOUD2 and channel.message_encoding == "cdr":
                    yield message.log_time, message.data
        return
    rosbag2 = _import("rosbags.rosbag2", path)
    with rosbag2.Reader(path) as reader:
        conns = [c for c in reader.connections if c.topic == topic and c.msgtype == POINTCLOUD2]
        for _, log_ns, raw in reader.messages(connections=conns):
            yield log_ns, raw


def _scans(path: Path, topic: str, intensity_scale: float) -> Iterator[Scan]:
    """ValueError naming the file (and the message) for a storage file or a message that cannot be read."""
    with contextlib.closing(_messages(path, topic)) as messages:  # the file closes on an error too
        for i in itertools.count():
            try:
                log_ns, raw = next(messages)
            except StopIteration:
                return
            except Exception as e:  # mcap, rosbags and sqlite raise their own errors (struct's, EOF) on junk
                raise ValueError(f"{path}: not a readable recording after {i} messages: {e!r}") from e
            yield _scan(path, topic, intensity_scale, i, log_ns, raw)


def _scan(path: Path, topic: str, intensity_scale: float, i: int, log_ns: int, raw: bytes) -> Scan:
    try:
        msg = decode_pointcloud2(raw)
    except Exception as e:  # rosbags raises what the bytes make it hit: struct, index, value errors
        raise ValueError(f"{path}: {topic} message {i}: not a PointCloud2 in CDR ({e!r})") from e
    try:
        points = pointcloud2_points(msg, intensity_scale)  # (N, 4)
        points = points[np.isfinite(points[:, 3])]  # one rule, as the bridge's: a NaN drops its point
    except ValueError as e:
        raise ValueError(f"{path}: {topic} message {i}: {e}") from e
    stamp = stamp_ns(msg) or int(log_ns)
    return Scan(f"{i:06d}", path, points, REQUIRED_FIELDS, cloud_spin(points), stamp)
