"""ROS 2 recordings through `phim replay` against a real server: rosbag2 folders (MCAP and sqlite3 storage)
and a plain MCAP written by the `mcap` library, PointCloud2 in velodyne_pointcloud's XYZIRT layout beside a
topic of another type, give the same boxes as replaying the same points from .npz files; `--mcap` writes
one PointCloud and one SceneUpdate per scan holding the boxes the server returned."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from foxglove_helpers import read_foxglove_mcap
from ros2_helpers import (
    OUSTER,
    Recorded,
    recording,
    sample_turns,
    write_plain_mcap,
    write_rosbag2,
)
from server_helpers import RunningServer, default_detector, serve

from clients.connect import ConnectConfig
from clients.predictions import PredictionRecord, read_predictions
from clients.replay import ReplayConfig, replay
from contract import REQUIRED_FIELDS
from lidar.readers import write_native_scan
from phim.cli import main as app
from ros.pointcloud2 import POINTCLOUD2
from ros.recordings import choose_topic, read_recording

EVERY = 8  # every 8th point of each turn: fast CPU forwards
WRITERS = {
    "rosbag2-mcap": lambda path, msgs: write_rosbag2(path / "bag", msgs, "mcap"),
    "rosbag2-sqlite3": lambda path, msgs: write_rosbag2(path / "bag", msgs, "sqlite3"),
    "plain-mcap": lambda path, msgs: write_plain_mcap(path / "drive.mcap", msgs),
    "plain-mcap-ros2-no-summary": lambda path, msgs: write_plain_mcap(path / "d.mcap", msgs, "ros2", False),
    # a rosbag2's storage file on its own (no metadata.yaml beside it)
    "rosbag2-mcap-file": lambda path, msgs: write_rosbag2(path / "bag", msgs, "mcap") / "bag.mcap",
    "rosbag2-db3-file": lambda path, msgs: write_rosbag2(path / "bag", msgs, "sqlite3") / "bag.db3",
}


@pytest.fixture(scope="module")
def server() -> Iterator[RunningServer]:
    with serve(default_detector()) as s:
        yield s


@pytest.fixture(scope="module")
def turns() -> list[np.ndarray]:
    return sample_turns(2, every=EVERY)  # (N_i, 4) float32 each


@pytest.fixture(scope="module")
def reference(server: RunningServer, turns: list[np.ndarray], tmp_path_factory) -> list[PredictionRecord]:
    """The same turns replayed the existing way: a folder of native .npz scans."""
    drive = tmp_path_factory.mktemp("npz")
    for i, pts in enumerate(turns):
        write_native_scan(drive / f"{i:06d}.npz", pts, REQUIRED_FIELDS)
    cfg = ReplayConfig(drive, drive / "p.jsonl", ConnectConfig(url=server.url), "ref", turns_per_s=0)
    assert replay(cfg).ok == 4 * len(turns)
    return read_predictions(cfg.predictions)[1]


def same_predictions(got: list[PredictionRecord], want: list[PredictionRecord]) -> None:
    assert [(r.scan, r.sector_index, r.points) for r in got] == [
        (r.scan, r.sector_index, r.points) for r in want
    ]
    for g, w in zip(got, want, strict=True):
        assert g.error is None and g.class_names == w.class_names
        np.testing.assert_array_equal(g.boxes, w.boxes)
        np.testing.assert_array_equal(g.scores, w.scores)


@pytest.mark.parametrize("kind", list(WRITERS))
def test_replay_a_recording_gives_the_boxes_of_the_same_points_from_files(
    kind: str, server: RunningServer, turns: list[np.ndarray], reference, tmp_path: Path
) -> None:
    messages = recording(turns)  # /velodyne_points (XYZIRT) and /chatter (std_msgs/String) between
    source = WRITERS[kind](tmp_path, messages)
    assert choose_topic(source) == "/velodyne_points"
    out, scenes = tmp_path / "p.jsonl", tmp_path / "scenes.mcap"
    cfg = ReplayConfig(source, out, ConnectConfig(url=server.url), f"bag-{kind}", turns_per_s=0, mcap=scenes)
    summary = replay(cfg)
    assert summary.scans == len(turns) and summary.sectors == summary.ok == 4 * len(turns)
    assert summary.errors == 0 and summary.scenes == len(turns)
    header, records = read_predictions(out)
    assert header["source"] == str(source)
    same_predictions(records, reference)
    assert sum(r.boxes.shape[0] for r in records) > 0  # the comparison is not between empty answers
    # sector times: each scan's header stamp, then a sector period (25 ms) per sector
    stamps = [m.stamp_ns for m in messages if m.topic == "/velodyne_points"]
    assert [r.timestamp_ns for r in records[:2]] == [stamps[0], stamps[0] + 25_000_000]
    check_scenes(scenes, records, turns, stamps)


def check_scenes(
    path: Path, records: list[PredictionRecord], turns: list[np.ndarray], stamps: list[int]
) -> None:
    """One PointCloud (the points sent) and one SceneUpdate (the boxes of the scan's last sector) per scan,
    both at the scan's sensor time."""
    messages = read_foxglove_mcap(path)
    clouds = [(t, m) for topic, t, m in messages if topic == "/phim/points"]
    updates = [(t, m) for topic, t, m in messages if topic == "/phim/detections"]
    last = [r for r in records if r.last_in_scan]
    assert len(clouds) == len(updates) == len(last) == len(turns)
    for (t_cloud, cloud), (t_update, update), record, pts, stamp in zip(
        clouds, updates, last, turns, stamps, strict=True
    ):
        assert t_cloud == t_update == stamp
        assert cloud["point_stride"] == 16 and [f["name"] for f in cloud["fields"]] == list(REQUIRED_FIELDS)
        sent = np.frombuffer(cloud["data"], "<f4").reshape(-1, 4)
        np.testing.assert_array_equal(
            np.sort(sent, axis=0), np.sort(pts, axis=0)
        )  # sector order, same points
        assert update["deletions"][0]["type"] == 1  # ALL: the last scan's boxes go
        entities = update.get("entities", [])
        assert len(entities) == record.boxes.shape[0]
        for entity, box, name, score in zip(
            entities, record.boxes, record.class_names, record.scores, strict=True
        ):
            (cube,) = entity["cubes"]
            pos, size = cube["pose"]["position"], cube["size"]
            got = [pos.get(k, 0.0) for k in "xyz"] + [size.get(k, 0.0) for k in "xyz"]
            q = cube["pose"]["orientation"]
            yaw = 2 * np.arctan2(q.get("z", 0.0), q.get("w", 0.0))
            np.testing.assert_allclose(got, box[:6], atol=1e-4)
            assert abs(np.angle(np.exp(1j * (yaw - box[6])))) < 1e-4
            meta = {kv["key"]: kv["value"] for kv in entity["metadata"]}
            assert meta["class"] == name and abs(float(meta["score"]) - score) < 1e-4
            assert entity["texts"][0]["text"].startswith(name)


def test_cli_replays_a_bag_and_refuses_what_it_cannot_choose(
    server: RunningServer, turns: list[np.ndarray], reference, tmp_path: Path
) -> None:
    two = recording(turns, "/lidar_top") + [
        Recorded("/lidar_front", m.msgtype, m.stamp_ns, m.cdr)
        for m in recording(turns[:1], layout=OUSTER)
        if m.msgtype == POINTCLOUD2
    ]
    bag = write_rosbag2(tmp_path / "two", sorted(two, key=lambda m: m.stamp_ns), "mcap")
    args = ["replay", str(bag), "--url", server.url, "--rate", "0", "--out", str(tmp_path / "p.jsonl")]
    runner = CliRunner()
    refused = runner.invoke(app, args)
    assert refused.exit_code == 2 and "2 sensor_msgs/msg/PointCloud2 topics" in refused.output
    assert "'/lidar_front', '/lidar_top'" in refused.output and "--topic" in refused.output
    wrong = runner.invoke(app, [*args, "--topic", "/chatter"])
    assert wrong.exit_code == 2 and "is a std_msgs/msg/String topic" in wrong.output
    scenes = tmp_path / "s.mcap"
    done = runner.invoke(app, [*args, "--topic", "/lidar_top", "--stream-id", "cli", "--mcap", str(scenes)])
    assert done.exit_code == 0, done.output
    assert "replayed 2 scans, 8 sectors: 8 answered" in done.output and f"2 scenes in {scenes}" in done.output
    same_predictions(read_predictions(tmp_path / "p.jsonl")[1], reference)
    npz_with_topic = runner.invoke(app, ["replay", str(tmp_path / "p.jsonl"), "--topic", "/x"])
    assert npz_with_topic.exit_code == 2


def test_recording_intensity_scale_and_layouts(turns: list[np.ndarray], tmp_path: Path) -> None:
    """A 0..255 driver read with --intensity-scale 1/255 gives the 0..1 points back; an Ouster-like layout
    in a sqlite3 bag reads as the same points; a recording with no PointCloud2 says what it holds."""
    bag = write_rosbag2(tmp_path / "v", recording(turns, intensity_scale=1 / 255), "sqlite3")
    scans = list(read_recording(bag, intensity_scale=1 / 255))
    assert [s.name for s in scans] == ["000000", "000001"]
    for scan, pts in zip(scans, turns, strict=True):
        np.testing.assert_array_equal(scan.points[:, :3], pts[:, :3])
        np.testing.assert_allclose(scan.points[:, 3], pts[:, 3], rtol=1e-6, atol=1e-7)
    ouster = write_rosbag2(tmp_path / "o", recording(turns, "/os_cloud_node/points", OUSTER), "sqlite3")
    (first, _) = list(read_recording(ouster))
    np.testing.assert_array_equal(first.points, turns[0])
    chatter = write_plain_mcap(tmp_path / "c.mcap", [m for m in recording(turns) if m.topic == "/chatter"])
    with pytest.raises(ValueError, match=r"no sensor_msgs/msg/PointCloud2 topic; its topics: \{'/chatter'"):
        choose_topic(chatter)
