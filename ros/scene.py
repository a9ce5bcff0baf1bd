"""Detections and points -> Foxglove messages (the scene of `phim replay --mcap` and of the live view).

`scene_messages` turns one prediction (a `contract.DetectionsReply`, or anything with the same `boxes`,
`scores` and `class_names`, e.g. a replay's `PredictionRecord`) and the points it saw into a foxglove
`PointCloud` and a `SceneUpdate`; `SceneChannels` logs them on two channels of a foxglove `Context` (an MCAP
file's, a WebSocket server's); `record_scenes` opens an MCAP file with its own context, so a recording never
receives what another sink in the same process logs.

The scene: each update first deletes every entity, then adds one entity per box (id `box-<i>`): a
translucent CubePrimitive in its class colour (centre x, y, z; size l, w, h along the box's heading, yaw
about +z) and a billboard TextPrimitive "<class> <score>" above it, the class and score also as entity
metadata (Foxglove shows it on click). Timestamps are the scan's sensor time; the frame is the points'.

foxglove-sdk is imported lazily (`pip install "phim[ros2]"`); importing this module costs nothing.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    from foxglove import Context
    from foxglove.messages import PointCloud, SceneUpdate

POINTS_TOPIC = "/phim/points"
DETECTIONS_TOPIC = "/phim/detections"
DEFAULT_FRAME = "lidar"
# RGBA per class (model.config.CLASS_NAMES); another class name gets OTHER_COLOR
CLASS_COLORS: dict[str, tuple[float, float, float, float]] = {
    "VEHICLE": (0.1, 0.6, 1.0, 0.4),
    "PEDESTRIAN": (1.0, 0.3, 0.2, 0.4),
    "CYCLIST": (1.0, 0.8, 0.1, 0.4),
}
OTHER_COLOR = (0.7, 0.7, 0.7, 0.4)


class Detections(Protocol):
    boxes: np.ndarray  # (K, 7) x, y, z (centre), l, w, h, yaw in the points' frame
    scores: np.ndarray  # (K,)
    class_names: tuple[str, ...]  # (K,) each box's class


def _timestamp(timestamp_ns: int) -> Any:
    from foxglove.messages import Timestamp

    return Timestamp(sec=timestamp_ns // 1_000_000_000, nsec=timestamp_ns % 1_000_000_000)


def point_cloud(points: np.ndarray, timestamp_ns: int, frame_id: str = DEFAULT_FRAME) -> PointCloud:
    """(N, >=4) x, y, z, intensity, ... -> a foxglove PointCloud of x, y, z, intensity float32 (16 bytes
    a point); Foxglove colours it by intensity."""
    from foxglove.messages import PackedElementField, PackedElementFieldNumericType, PointCloud

    data = np.ascontiguousarray(points[:, :4], dtype="<f4")  # (N, 4)
    f32 = PackedElementFieldNumericType.Float32
    fields = [PackedElementField(name=n, offset=4 * i, type=f32) for i, n in enumerate(("x", "y", "z"))]
    fields.append(PackedElementField(name="intensity", offset=12, type=f32))
    return PointCloud(
        timestamp=_timestamp(timestamp_ns),
        frame_id=frame_id,
        pose=_pose(0.0, 0.0, 0.0, 0.0),
        point_stride=16,
        fields=fields,
        data=data.tobytes(),
    )


def _pose(x: float, y: float, z: float, yaw: float) -> Any:
    from foxglove.messages import Pose, Quaternion, Vector3

    # a rotation by yaw about +z: (0, 0, sin(yaw/2), cos(yaw/2))
    q = Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))
    return Pose(position=Vector3(x=x, y=y, z=z), orientation=q)


def scene_update(detections: Detections, timestamp_ns: int, frame_id: str = DEFAULT_FRAME) -> SceneUpdate:
    """The boxes of one prediction -> a SceneUpdate that replaces whatever the last one showed."""
    from foxglove.messages import (
        Color,
        CubePrimitive,
        KeyValuePair,
        SceneEntity,
        SceneEntityDeletion,
        SceneEntityDeletionType,
        SceneUpdate,
        TextPrimitive,
        Vector3,
    )

    stamp = _timestamp(timestamp_ns)
    entities = []
    boxes = np.asarray(detections.boxes, dtype=np.float64).reshape(-1, 7)  # (K, 7)
    for i, ((x, y, z, length, w, h, yaw), score, name) in enumerate(
        zip(boxes.tolist(), np.asarray(detections.scores).tolist(), detections.class_names, strict=True)
    ):
        r, g, b, a = CLASS_COLORS.get(name.upper(), OTHER_COLOR)
        cube = CubePrimitive(
            pose=_pose(x, y, z, yaw), size=Vector3(x=length, y=w, z=h), color=Color(r=r, g=g, b=b, a=a)
        )
        text = TextPrimitive(
            pose=_pose(x, y, z + h / 2 + 0.5, 0.0),
            billboard=True,
            font_size=14.0,
            scale_invariant=True,
            color=Color(r=r, g=g, b=b, a=1.0),
            text=f"{name} {score:.2f}",
        )
        meta = [KeyValuePair(key="class", value=name), KeyValuePair(key="score", value=f"{score:.4f}")]
        entities.append(
            SceneEntity(
                timestamp=stamp, frame_id=frame_id, id=f"box-{i}", metadata=meta, cubes=[cube], texts=[text]
            )
        )
    clear = SceneEntityDeletion(timestamp=stamp, type=SceneEntityDeletionType.All)
    return SceneUpdate(deletions=[clear], entities=entities)


def scene_messages(
    detections: Detections, points: np.ndarray, timestamp_ns: int, frame_id: str = DEFAULT_FRAME
) -> tuple[PointCloud, SceneUpdate]:
    """One prediction and the (N, >=4) points it saw -> (PointCloud, SceneUpdate), both at `timestamp_ns`."""
    return point_cloud(points, timestamp_ns, frame_id), scene_update(detections, timestamp_ns, frame_id)


@dataclass
class SceneChannels:
    """The points and detections channels of one foxglove Context (None: the SDK's default context)."""

    context: Context | None = None
    points_topic: str = POINTS_TOPIC
    detections_topic: str = DETECTIONS_TOPIC

    def __post_init__(self) -> None:
        from foxglove.channels import PointCloudChannel, SceneUpdateChannel

        self._points = PointCloudChannel(self.points_topic, context=self.context)
        self._detections = SceneUpdateChannel(self.detections_topic, context=self.context)

    def log(
        self,
        detections: Detections,
        points: np.ndarray,
        timestamp_ns: int,
        frame_id: str = DEFAULT_FRAME,
        log_time_ns: int | None = None,
    ) -> None:
        """Log the scene of one prediction; its log time is `log_time_ns` (a live view: now), by default
        `timestamp_ns` (a recording plays back at sensor time)."""
        cloud, scene = scene_messages(detections, points, timestamp_ns, frame_id)
        at = timestamp_ns if log_time_ns is None else log_time_ns
        self._points.log(cloud, log_time=at)
        self._detections.log(scene, log_time=at)

    def watched(self) -> bool:
        """Whether anything receives these channels (a live view draws nothing for nobody)."""
        return self._points.has_sinks() or self._detections.has_sinks()

    def close(self) -> None:
        self._points.close()
        self._detections.close()


@contextlib.contextmanager
def record_scenes(path: Path, **topics: str) -> Iterator[SceneChannels]:
    """An MCAP file at `path` (replaced if there) receiving the scenes logged on the yielded channels."""
    try:
        import foxglove
    except ImportError as e:  # the clients extra alone has no foxglove-sdk
        raise ValueError(
            f"{path}: writing Foxglove MCAP scenes needs foxglove-sdk: pip install 'phim[ros2]'"
        ) from e
    context = foxglove.Context()
    with foxglove.open_mcap(Path(path), allow_overwrite=True, context=context):
        channels = SceneChannels(context, **topics)
        try:
            yield channels
        finally:
            channels.close()
