"""The ROS 2 messages the bridge sends (server/ros2_bridge.py): vision_msgs/msg/Detection3DArray and
visualization_msgs/msg/MarkerArray, CDR-encoded with rosbags, and the RIHS01 type hashes of every type it
speaks.

rosbags' Jazzy typestore has sensor_msgs, std_msgs, geometry_msgs and visualization_msgs; vision_msgs is not
built in, so its five messages of vision_msgs 4.x (ros-perception/vision_msgs, the ros2 branch) are
registered from their .msg definitions. Type hashes (REP-2011's RIHS01: sha256 over the canonical JSON type
description) come from rosbags' `Typestore.hash_rihs01`; the tests check it against the hashes ROS publishes
for built-in types.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from contract import DetectionsReply

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
DETECTION3D_ARRAY = "vision_msgs/msg/Detection3DArray"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"

# vision_msgs 4.x, field by field (the comments of the upstream files left out)
VISION_MSGS: dict[str, str] = {
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": (
        "vision_msgs/ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n"
    ),
    "vision_msgs/msg/BoundingBox3D": "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n",
    "vision_msgs/msg/Detection3D": (
        "std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
        "vision_msgs/BoundingBox3D bbox\nstring id\n"
    ),
    "vision_msgs/msg/Detection3DArray": "std_msgs/Header header\nvision_msgs/Detection3D[] detections\n",
}
MARKER_NS = "phim"
MARKER_ALPHA = 0.5
# RGB per class name (model.config.CLASS_NAMES, matched case-insensitively), grey for any other
CLASS_COLORS: dict[str, tuple[float, float, float]] = {
    "vehicle": (0.2, 0.6, 1.0),
    "pedestrian": (1.0, 0.4, 0.2),
    "cyclist": (0.3, 0.9, 0.3),
}
OTHER_COLOR = (0.7, 0.7, 0.7)


@functools.cache
def typestore() -> Any:
    """rosbags' Jazzy typestore with vision_msgs registered (built once: it parses every definition)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict[str, Any] = {}
    for name, text in VISION_MSGS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


@functools.cache
def type_hash(ros_type: str) -> str:
    """`RIHS01_<64 hex digits>` of a message type, as rosidl computes it."""
    return typestore().hash_rihs01(ros_type)


@dataclass(frozen=True)
class Header:
    """The input's header, echoed on every answer to it."""

    stamp_ns: int
    frame_id: str


def yaw_quaternion(yaw: np.ndarray) -> np.ndarray:
    """(K,) yaw about +z (radians) -> (K, 4) x, y, z, w."""
    half = np.asarray(yaw, np.float64) / 2
    zeros = np.zeros_like(half)
    return np.stack([zeros, zeros, np.sin(half), np.cos(half)], axis=1)


def _header(t: dict[str, Any], header: Header) -> Any:
    stamp = t["builtin_interfaces/msg/Time"](
        sec=header.stamp_ns // 1_000_000_000, nanosec=header.stamp_ns % 1_000_000_000
    )
    return t["std_msgs/msg/Header"](stamp=stamp, frame_id=header.frame_id)


def _pose(t: dict[str, Any], box: np.ndarray, quat: np.ndarray) -> Any:
    """box (7,) x, y, z, l, w, h, yaw; quat (4,) -> geometry_msgs/Pose at the box's centre."""
    position = t["geometry_msgs/msg/Point"](x=float(box[0]), y=float(box[1]), z=float(box[2]))
    x, y, z, w = (float(v) for v in quat)
    return t["geometry_msgs/msg/Pose"](
        position=position, orientation=t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)
    )


def _size(t: dict[str, Any], box: np.ndarray) -> Any:
    return t["geometry_msgs/msg/Vector3"](x=float(box[3]), y=float(box[4]), z=float(box[5]))


def detection_array(reply: DetectionsReply, header: Header) -> Any:
    """A reply -> vision_msgs/msg/Detection3DArray: one Detection3D per box (bbox: centre, yaw as a
    quaternion about z, size l, w, h; results[0]: class name and score, the same pose, zero covariance)."""
    t = typestore().types
    boxes = np.asarray(reply.boxes, np.float64).reshape(-1, 7)  # (K, 7)
    quats = yaw_quaternion(boxes[:, 6])  # (K, 4)
    head = _header(t, header)
    detections = []
    for box, quat, name, score in zip(boxes, quats, reply.class_names, reply.scores, strict=True):
        pose = _pose(t, box, quat)
        hypothesis = t["vision_msgs/msg/ObjectHypothesis"](class_id=name, score=float(score))
        result = t["vision_msgs/msg/ObjectHypothesisWithPose"](
            hypothesis=hypothesis,
            pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        )
        bbox = t["vision_msgs/msg/BoundingBox3D"](center=pose, size=_size(t, box))
        detections.append(t["vision_msgs/msg/Detection3D"](header=head, results=[result], bbox=bbox, id=""))
    return t[DETECTION3D_ARRAY](header=head, detections=detections)


def marker_array(reply: DetectionsReply, header: Header) -> Any:
    """A reply -> visualization_msgs/msg/MarkerArray: DELETEALL (the previous sector's boxes go), then one
    half-transparent CUBE per box, coloured by class."""
    t = typestore().types
    marker_t = t["visualization_msgs/msg/Marker"]
    head = _header(t, header)
    markers = [_marker(t, head, 0, marker_t.DELETEALL)]
    boxes = np.asarray(reply.boxes, np.float64).reshape(-1, 7)  # (K, 7)
    quats = yaw_quaternion(boxes[:, 6])  # (K, 4)
    for i, (box, quat, name) in enumerate(zip(boxes, quats, reply.class_names, strict=True)):
        m = _marker(t, head, i, marker_t.ADD)
        m.type = marker_t.CUBE
        m.pose, m.scale = _pose(t, box, quat), _size(t, box)
        r, g, b = CLASS_COLORS.get(name.lower(), OTHER_COLOR)
        m.color = t["std_msgs/msg/ColorRGBA"](r=r, g=g, b=b, a=MARKER_ALPHA)
        markers.append(m)
    return t[MARKER_ARRAY](markers=markers)


def _marker(t: dict[str, Any], head: Any, marker_id: int, action: int) -> Any:
    """A Marker with every field at its ROS default but header, ns, id and action."""
    zero = t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0)  # lifetime 0: until deleted
    return t["visualization_msgs/msg/Marker"](
        header=head,
        ns=MARKER_NS,
        id=marker_id,
        type=0,
        action=action,
        pose=t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        ),
        scale=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        color=t["std_msgs/msg/ColorRGBA"](r=0.0, g=0.0, b=0.0, a=0.0),
        lifetime=zero,
        frame_locked=False,
        points=[],
        colors=[],
        texture_resource="",
        texture=t["sensor_msgs/msg/CompressedImage"](header=head, format="", data=np.zeros(0, np.uint8)),
        uv_coordinates=[],
        text="",
        mesh_resource="",
        mesh_file=t["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8)),
        mesh_use_embedded_materials=False,
    )


def encode(message: Any, ros_type: str) -> bytes:
    """A rosbags message -> CDR bytes (little-endian, with its 4-byte encapsulation header)."""
    return bytes(typestore().serialize_cdr(message, ros_type))


def decode(cdr: bytes, ros_type: str) -> Any:
    return typestore().deserialize_cdr(cdr, ros_type)


def yaw_of(quaternion: Any) -> float:
    """A geometry_msgs/Quaternion about z -> yaw (radians, -pi..pi)."""
    return 2.0 * math.atan2(quaternion.z, quaternion.w)
