"""The rmw_zenoh wire formats of the ROS 2 bridge (contract/ros2.py, ros/messages.py), against
literals written out here, not built by the code under test: ros2/rmw_zenoh docs/design.md (key expressions,
tokens, the attachment's bytes, the RIHS01 hash of std_msgs/msg/String) and its liveliness_utils.cpp /
qos.cpp (the QoS chunk). The bridge itself over real sessions: tests/test_ros2_bridge.py."""

from __future__ import annotations

import numpy as np
import pytest
from ros2_helpers import assert_boxes, reply_for
from server_helpers import make_settings

from contract import (
    SectorMessage,
)
from contract.ros2 import (
    SENSOR_DATA,
    Attachment,
    EntityKind,
    Node,
    Qos,
    check_topic,
    default_detections_topic,
    default_stream_id,
    node_name,
)
from lidar.synthetic import synthetic_turn
from ros import messages
from ros.messages import DETECTION3D_ARRAY, MARKER_ARRAY, POINTCLOUD2, Header
from ros.node import Ros2Config

WAIT_S = 60.0  # a guard against hangs; answers come as soon as the (CPU) forward is done
PC2_HASH = "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5"
DET_HASH = "RIHS01_793f5eab9595ac1c0da07873cc859db42eae51f0ee76056db8562515d830e018"
POINTS_KEY = f"0/car1/lidar/points/sensor_msgs::msg::dds_::PointCloud2_/{PC2_HASH}"
DETECTIONS_KEY = f"0/car1/detections/vision_msgs::msg::dds_::Detection3DArray_/{DET_HASH}"
MARKERS_KEY = "0/car1/markers/visualization_msgs::msg::dds_::MarkerArray_/" + messages.type_hash(MARKER_ARRAY)
FIELDS = ("x", "y", "z", "intensity")
STAMP_NS = 1_700_000_000_250_000_000


# ------------------------------------------------------------------------------------ the wire formats


def test_the_keys_and_tokens_are_rmw_zenohs() -> None:
    # design.md's own examples, character for character
    chatter = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
    listener = Node(2, "aac3178e146ba6f1fc6e6a4085e77f21", "listener")
    assert listener.token() == "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    sub = listener.entity_token(
        10, EntityKind.SUBSCRIPTION, "/chatter", "std_msgs/msg/String", chatter, Qos()
    )
    assert sub == (
        f"@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/"
        f"std_msgs::msg::dds_::String_/{chatter}/::,10:,:,:,,"
    )
    talker = Node(2, "8b20917502ee955ac4476e0266340d5c", "talker")
    pub = talker.entity_token(
        10, EntityKind.PUBLISHER, "chatter", "std_msgs/msg/String", chatter, Qos(depth=7)
    )
    assert pub.endswith(f"/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/{chatter}/::,7:,:,:,,")
    # the QoS chunk: only what differs from rmw_zenoh's default (reliable, volatile, keep last 42)
    assert SENSOR_DATA.key() == "2::,5:,:,:,,"
    assert Qos(transient_local=True, depth=42).key() == ":1:,:,:,:,,"
    ns = Node(0, "z", "velodyne", namespace="/car1/sensors")
    assert ns.token() == "@ros2_lv/0/z/0/0/NN/%/%car1%sensors/velodyne"


def test_the_attachment_is_zenoh_ext_serialization_of_seq_time_gid() -> None:
    from zenoh.ext import Int64, z_serialize

    gid = bytes(range(100, 116))
    a = Attachment(41, STAMP_NS, gid)
    wire = a.encode()
    assert wire == z_serialize((Int64(41), Int64(STAMP_NS), gid)).to_bytes()  # what zenoh-cpp writes
    assert wire == (41).to_bytes(8, "little") + STAMP_NS.to_bytes(8, "little") + b"\x10" + gid
    assert Attachment.decode(wire) == a
    # rmw_zenoh 0.2.0 .. 0.2.3 named each value; still read
    named = ("sequence_number", Int64(41), "source_timestamp", Int64(STAMP_NS), "source_gid", gid)
    assert Attachment.decode(z_serialize(named).to_bytes()) == a
    for bad in (wire[:-1], wire + b"\x00", wire[:16] + b"\x0f" + gid[:15], b""):
        with pytest.raises(ValueError, match="attachment"):
            Attachment.decode(bad)


def test_topic_names_and_what_is_derived_from_them() -> None:
    assert check_topic("car1/lidar/points") == "/car1/lidar/points"
    for bad in ("/", "/car1//points", "/1car/points", "/car-1/points", "", "/cmd__vel", "car__1/points"):
        with pytest.raises(ValueError, match="ROS 2 topic name"):
            check_topic(bad)
    assert default_stream_id("/car1/lidar/points") == "car1"
    assert default_stream_id("/points") == "points"
    assert default_detections_topic("/car1/lidar/points") == "/car1/detections"
    assert default_detections_topic("/points") == "/detections"
    assert node_name("gpu-0.a") == "phim_gpu_0_a"


def test_settings_fill_in_the_bridges_defaults(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PHIM_ROS2_MARKERS", "")  # an empty variable: unset
    cfg = make_settings(ros2_points="car1/lidar/points", worker_id="gpu-0").ros2_config()
    assert cfg == Ros2Config(
        "/car1/lidar/points", "/car1/detections", None, 0, "car1", 1.0, False, "phim_gpu_0"
    )
    assert cfg.stream == "car1"
    with pytest.raises(ValueError, match="ros2_detections"):
        make_settings(ros2_points="/car1/points", ros2_detections="/car1/2d")
    with pytest.raises(ValueError, match="ros2_stream_id"):
        make_settings(ros2_points="/car1/points", ros2_stream_id="car 1")


def test_type_hashes_are_ros_rihs01() -> None:
    # known hashes of built-in types (rmw_zenoh's design.md; a real Jazzy graph's PointCloud2 key), and the
    # registered vision_msgs 4.x type, the same as another implementation computes from the same .msg files
    assert messages.type_hash("std_msgs/msg/String").endswith(
        "df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
    )
    assert messages.type_hash(POINTCLOUD2) == PC2_HASH
    assert messages.type_hash(DETECTION3D_ARRAY) == DET_HASH
    assert messages.type_hash("vision_msgs/msg/Detection3D") == (
        "RIHS01_ddd703be132ab0b69d33121f1bb034132bfbb3b0ac5f9fb1516005ba1c8a265b"
    )


def test_detection_array_and_markers_carry_each_box() -> None:
    msg = SectorMessage("car1", 3, 2, STAMP_NS, synthetic_turn()[:500], FIELDS)
    reply = reply_for(msg)
    header = Header(STAMP_NS, "velodyne")
    array = messages.decode(
        messages.encode(messages.detection_array(reply, header), DETECTION3D_ARRAY), DETECTION3D_ARRAY
    )
    assert (array.header.stamp.sec, array.header.stamp.nanosec, array.header.frame_id) == (
        1_700_000_000,
        250_000_000,
        "velodyne",
    )
    assert_boxes(array, reply)
    markers = messages.decode(
        messages.encode(messages.marker_array(reply, header), MARKER_ARRAY), MARKER_ARRAY
    ).markers
    assert [(m.action, m.type) for m in markers] == [(3, 0), (0, 1), (0, 1)]  # DELETEALL, then a CUBE per box
    np.testing.assert_allclose(
        [markers[1].scale.x, markers[1].scale.y, markers[1].scale.z], reply.boxes[0, 3:6]
    )
