"""The ROS 2 bridge as a ROS graph sees it, without zenoh: a node with one subscription (the points topic)
and one or two publishers (the detections, and the markers if asked), their key expressions, liveliness
tokens and GIDs, and the messages each publishes for a sector's answer. The transport that declares them
on a zenoh session is server/ros2_bridge.py; the wire facts are contract/ros2.py (docs/ros2.md).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

from contract import DetectionsReply
from contract.ros2 import RELIABLE, SENSOR_DATA, EntityKind, Node, default_stream_id, topic_key
from ros import messages
from ros.messages import DETECTION3D_ARRAY, MARKER_ARRAY, POINTCLOUD2, Header

SUBSCRIPTION_ID, DETECTIONS_ID, MARKERS_ID = 1, 2, 3  # entity IDs within the bridge's node (node ID 0)


@dataclass(frozen=True)
class Ros2Config:
    points: str  # the PointCloud2 topic, fully qualified
    detections: str  # the Detection3DArray topic
    markers: str | None = None  # the MarkerArray topic (None: none)
    domain_id: int = 0
    stream_id: str = ""  # '' : the points topic's first namespace (contract.ros2.default_stream_id)
    intensity_scale: float = 1.0  # times the raw intensity: 1/255 for drivers publishing 0..255
    partial_scans: bool = False  # each message a piece of a turn (sectorized as it comes), not a whole one
    node_name: str = "phim"

    @property
    def stream(self) -> str:
        return self.stream_id or default_stream_id(self.points)

    def outputs(self) -> list[tuple[str, str]]:
        """(topic, ROS type) of each publisher: the detections, then the markers if asked."""
        out = [(self.detections, DETECTION3D_ARRAY)]
        return out + ([(self.markers, MARKER_ARRAY)] if self.markers is not None else [])

    def key(self, topic: str, ros_type: str) -> str:
        """The data key expression of a topic, as rmw_zenoh writes it."""
        return topic_key(self.domain_id, topic, ros_type, messages.type_hash(ros_type))


class BridgeNode:
    """The bridge's node in the session `zid`: its tokens, and each publisher's GID."""

    def __init__(self, cfg: Ros2Config, zid: str):
        self.cfg = cfg
        self.node = Node(cfg.domain_id, zid, cfg.node_name)

    def tokens(self) -> list[str]:
        """The liveliness tokens of the node, its subscription, its publishers (in `cfg.outputs` order)."""
        node, cfg = self.node, self.cfg
        points_hash = messages.type_hash(POINTCLOUD2)
        out = [
            node.token(),
            node.entity_token(
                SUBSCRIPTION_ID, EntityKind.SUBSCRIPTION, cfg.points, POINTCLOUD2, points_hash, SENSOR_DATA
            ),
        ]
        for entity_id, (topic, ros_type) in zip((DETECTIONS_ID, MARKERS_ID), cfg.outputs(), strict=False):
            type_hash = messages.type_hash(ros_type)
            out.append(
                node.entity_token(entity_id, EntityKind.PUBLISHER, topic, ros_type, type_hash, RELIABLE)
            )
        return out

    def gids(self) -> dict[str, bytes]:
        """topic -> its publisher's GID: stable for the publisher's life (its token names the session).
        rmw_zenoh hashes the token too, with XXH3-128, so `ros2 topic info -v` shows another GID for it
        than the samples carry."""
        _, _, *publishers = self.tokens()
        return {
            topic: hashlib.sha256(token.encode()).digest()[:16]
            for (topic, _), token in zip(self.cfg.outputs(), publishers, strict=True)
        }


def answer_messages(cfg: Ros2Config, reply: DetectionsReply, header: Header) -> list[tuple[str, bytes]]:
    """A sector's answer -> (topic, CDR bytes) to publish: its Detection3DArray, its MarkerArray if asked."""
    out = [(cfg.detections, messages.encode(messages.detection_array(reply, header), DETECTION3D_ARRAY))]
    if cfg.markers is not None:
        out.append((cfg.markers, messages.encode(messages.marker_array(reply, header), MARKER_ARRAY)))
    return out
