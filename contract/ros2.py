"""How ROS 2 over rmw_zenoh looks on the wire, in pure Python: the data key of a topic, the attachment of
every sample, the liveliness tokens of the ROS graph (docs/ros2.md).

Followed: rmw_zenoh_cpp 0.2.4 and later (ROS 2 Jazzy; Rolling and Kilted since ros2/rmw_zenoh#601, which
0.2.4 backports as #605), as its docs/design.md ("Topic and Service name mapping to Zenoh key expressions",
"Graph Cache", "Publishers") and src/detail/liveliness_utils.cpp describe them:

- data key:   `<domain_id>/<topic without the leading and trailing />/<DDS type name>/<type hash>`
              e.g. `0/car1/lidar/points/sensor_msgs::msg::dds_::PointCloud2_/RIHS01_9198...`
- attachment: int64 sequence number, int64 source time (ns since the epoch), both little-endian, then the
              publisher's GID as a sequence: its length as LEB128 (one byte, 16) and 16 bytes (33 bytes in
              all; zenoh-ext's serialization of (int64, int64, std::array<uint8_t, 16>)). rmw_zenoh drops a
              sample without one. Versions 0.2.0 to 0.2.3 wrote each value after its name as a string; those
              are read too, never written.
- tokens:     `@ros2_lv/<domain_id>/<zenoh session ID>/<node_id>/<node_id>/NN/<enclave>/<namespace>/<node>`
              for a node; publishers (MP) and subscriptions (MS) put their entity ID in the 5th chunk and add
              `/<topic>/<DDS type name>/<type hash>/<qos>`; names mangled (every `/` as `%`).

No zenoh and no ROS here: strings and bytes only (the server's bridge and any test vehicle share them).
"""

from __future__ import annotations

import enum
import re
import struct
from dataclasses import dataclass

RMW_ZENOH_VERSION = "rmw_zenoh_cpp >= 0.2.4 (Jazzy), Rolling/Kilted since ros2/rmw_zenoh#601"
ADMIN_SPACE = "@ros2_lv"  # a verbatim chunk: `*` and `**` never match it
GID_SIZE = 16  # RMW_GID_STORAGE_SIZE since Iron
ATTACHMENT_SIZE = 8 + 8 + 1 + GID_SIZE
_INT64 = struct.Struct("<q")
_OLD_KEYS = (b"sequence_number", b"source_timestamp", b"source_gid")  # 0.2.0 .. 0.2.3
# a ROS name's tokens: letters, digits, underscores, not starting with a digit, and no name with repeated
# underscores (design.ros2.org, "Topic and Service name mapping"; rcl's topic name validation refuses `__`);
# `~` and substitutions are for nodes to expand, never on the wire
_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


class EntityKind(enum.StrEnum):
    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE = "SS"
    CLIENT = "SC"


# ------------------------------------------------------------------------------------------------- names


def check_topic(name: str, what: str = "topic") -> str:
    """A fully qualified ROS 2 topic name (`/car1/lidar/points`; a relative one gets its leading `/`);
    ValueError saying what is wrong otherwise."""
    full = name if name.startswith("/") else "/" + name
    tokens = full[1:].split("/")
    if not full[1:] or not all(_TOKEN.fullmatch(t) for t in tokens) or "__" in full:
        raise ValueError(
            f"{what} {name!r}: expected a ROS 2 topic name, /-separated tokens of letters, digits and "
            "underscores, none empty or starting with a digit, no two underscores in a row (e.g. "
            "/car1/lidar/points)"
        )
    return full


def namespace_of(topic: str) -> str:
    """The topic's first namespace (`/car1/lidar/points` -> `car1`), or '' for a topic at the root."""
    tokens = check_topic(topic)[1:].split("/")
    return tokens[0] if len(tokens) > 1 else ""


def default_stream_id(topic: str) -> str:
    """The stream a topic's scans go to: its first namespace (`/car1/lidar/points` -> `car1`), or the topic's
    own name for a topic at the root (`/points` -> `points`). Always a stream ID: a ROS name's characters
    are a subset of a stream ID's."""
    return namespace_of(topic) or check_topic(topic)[1:]


def default_detections_topic(points_topic: str) -> str:
    """Where detections go by default: `detections` in the points topic's first namespace."""
    ns = namespace_of(points_topic)
    return f"/{ns}/detections" if ns else "/detections"


def node_name(worker_id: str) -> str:
    """The bridge's ROS node name for a worker ID (node names take no `-` or `.`)."""
    return "phim_" + re.sub(r"[^A-Za-z0-9_]", "_", worker_id)


def mangle(name: str) -> str:
    """A name as one key chunk: every `/` as `%` (the root namespace `/` is `%`)."""
    return name.replace("/", "%")


def dds_type_name(ros_type: str) -> str:
    """`sensor_msgs/msg/PointCloud2` -> `sensor_msgs::msg::dds_::PointCloud2_` (the name fastrtps' type
    support gives, which rmw_zenoh puts in keys and tokens)."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def topic_key(domain_id: int, topic: str, ros_type: str, type_hash: str) -> str:
    """The key expression a topic's samples travel on."""
    return f"{domain_id}/{check_topic(topic).strip('/')}/{dds_type_name(ros_type)}/{type_hash}"


# ------------------------------------------------------------------------------------------------- QoS


@dataclass(frozen=True)
class Qos:
    """The QoS an entity announces. rmw_zenoh writes each field only where it differs from its own default
    (reliable, volatile, keep last 42, infinite deadline/lifespan/lease, automatic liveliness)."""

    reliable: bool = True
    transient_local: bool = False
    depth: int = 10  # keep last `depth`

    def key(self) -> str:
        """`<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,
        <lease s>,<ns>` (no spaces), values as rmw's enum numbers (RELIABLE 1, BEST_EFFORT 2;
        TRANSIENT_LOCAL 1, VOLATILE 2; KEEP_LAST 1): here always keep last, infinite durations, automatic
        liveliness."""
        reliability = "" if self.reliable else "2"
        durability = "1" if self.transient_local else ""
        depth = "" if self.depth == 42 else str(self.depth)
        return f"{reliability}:{durability}:,{depth}:,:,:,,"


RELIABLE = Qos()  # the bridge's publishers: reliable, volatile, keep last 10 (rclcpp's default)
SENSOR_DATA = Qos(reliable=False, depth=5)  # rclcpp's SensorDataQoS: matches any publisher


# ------------------------------------------------------------------------------------------------ tokens


@dataclass(frozen=True)
class Node:
    """A ROS node as rmw_zenoh announces it; `zid` is the zenoh session's ID as zenoh prints it."""

    domain_id: int
    zid: str
    name: str
    node_id: int = 0
    namespace: str = "/"
    enclave: str = "/"

    def _head(self, entity_id: int, kind: EntityKind) -> str:
        return (
            f"{ADMIN_SPACE}/{self.domain_id}/{self.zid}/{self.node_id}/{entity_id}/{kind}/"
            f"{mangle(self.enclave)}/{mangle(self.namespace)}/{self.name}"
        )

    def token(self) -> str:
        """The node's own liveliness token."""
        return self._head(self.node_id, EntityKind.NODE)

    def entity_token(
        self, entity_id: int, kind: EntityKind, topic: str, ros_type: str, type_hash: str, qos: Qos
    ) -> str:
        """The liveliness token of one of the node's publishers or subscriptions."""
        tail = f"{mangle(check_topic(topic))}/{dds_type_name(ros_type)}/{type_hash}/{qos.key()}"
        return f"{self._head(entity_id, kind)}/{tail}"


# -------------------------------------------------------------------------------------------- attachment


@dataclass(frozen=True)
class Attachment:
    """What rmw_zenoh attaches to every sample: the publisher's message count, its clock, its GID."""

    sequence_number: int
    source_timestamp_ns: int
    source_gid: bytes  # GID_SIZE bytes

    def encode(self) -> bytes:
        if len(self.source_gid) != GID_SIZE:
            raise ValueError(f"source_gid: {len(self.source_gid)} bytes; expected {GID_SIZE}")
        return (
            _INT64.pack(self.sequence_number)
            + _INT64.pack(self.source_timestamp_ns)
            + _leb128(GID_SIZE)
            + bytes(self.source_gid)
        )

    @staticmethod
    def decode(data: bytes) -> Attachment:
        """Either format (0.2.4+, or the named values of 0.2.0 to 0.2.3); ValueError if neither."""
        reader = _Reader(bytes(data))
        named = data[:1] == bytes([len(_OLD_KEYS[0])]) and data[1:16] == _OLD_KEYS[0]
        values = []
        for key in _OLD_KEYS:
            if named and reader.sequence() != key:
                raise ValueError(f"attachment: expected the key {key.decode()!r}")
            values.append(reader.sequence() if key == b"source_gid" else reader.int64())
        if not reader.done():
            raise ValueError(f"attachment: {len(data) - reader.pos} bytes after the GID")
        seq, stamp, gid = values
        assert isinstance(seq, int) and isinstance(stamp, int) and isinstance(gid, bytes)
        if len(gid) != GID_SIZE:
            raise ValueError(f"attachment: a GID of {len(gid)} bytes; expected {GID_SIZE}")
        return Attachment(seq, stamp, gid)


def _leb128(n: int) -> bytes:
    out = bytearray()
    while True:
        byte, n = n & 0x7F, n >> 7
        out.append(byte | (0x80 if n else 0))
        if not n:
            return bytes(out)


class _Reader:
    """Reads zenoh-ext serialized values: little-endian int64s, LEB128-length-prefixed byte sequences."""

    def __init__(self, data: bytes):
        self.data, self.pos = data, 0

    def _take(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise ValueError(f"attachment: {len(self.data)} bytes end before byte {self.pos + n}")
        out = self.data[self.pos : self.pos + n]
        self.pos += n
        return out

    def int64(self) -> int:
        return _INT64.unpack(self._take(8))[0]

    def sequence(self) -> bytes:
        n, shift = 0, 0
        while True:
            byte = self._take(1)[0]
            n |= (byte & 0x7F) << shift
            shift += 7
            if not byte & 0x80:
                return self._take(n)
            if shift > 63:
                raise ValueError("attachment: a sequence length longer than 64 bits")

    def done(self) -> bool:
        return self.pos == len(self.data)
