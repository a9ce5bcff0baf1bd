"""The live view (`phim serve --foxglove-port P`): a real server and a real WebSocket client speaking the
Foxglove WebSocket protocol (subprotocol foxglove.sdk.v1): the channels a stream gets, a subscription's
messages decoded, and that the view never holds serving up."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import struct
import threading
import time
from base64 import b64decode
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import websockets
from foxglove_helpers import decode, descriptors
from pydantic import ValidationError
from server_helpers import CONTROL, START_TIMEOUT_S, default_detector, sector_msg, serve

from clients.bench.server import free_port
from contract import MSGPACK, DetectionsReply, decode_response, encode_sector
from model.stream import StreamingDetector
from ros.live_view import LiveView, topics
from server.settings import Settings
from server.worker import Worker, WorkerConfig

SUBPROTOCOL = "foxglove.sdk.v1"  # the only one foxglove-sdk's server accepts (0.30)
MESSAGE_DATA = 0x01  # binary opcode: u8 opcode, u32 subscription id, u64 log time (little-endian), payload
WAIT_S = START_TIMEOUT_S  # bounded, generous: a busy machine is slow, and each wait ends once met
SECTOR_NS = 1000  # sector_msg's timestamp for seq k: k * SECTOR_NS


@pytest.fixture(scope="module")
def det() -> StreamingDetector:
    return default_detector()


def post(url: str, stream: str, seq: int) -> DetectionsReply:
    """The CONTROL sector (a sector with boxes) as `stream`'s sector `seq`, over HTTP."""
    body = encode_sector(sector_msg(stream, seq, CONTROL))
    headers = {"Content-Type": MSGPACK}
    r = httpx.post(f"{url}/v1/streams/{stream}/sectors", content=body, headers=headers, timeout=WAIT_S)
    reply = decode_response(r.content)
    assert r.status_code == 200 and isinstance(reply, DetectionsReply), reply
    return reply


def decoded(channel: dict[str, Any], payload: bytes) -> dict[str, Any]:
    """A message of a protobuf channel, decoded by the schema its advertisement carries."""
    assert channel["encoding"] == "protobuf" and channel["schemaEncoding"] == "protobuf", channel
    types = descriptors(b64decode(channel["schema"]))
    return decode(types, "." + channel["schemaName"], payload)


def sensor_time_ns(message: dict[str, Any]) -> int:
    """A decoded PointCloud's or SceneUpdate's sensor time (unset proto3 fields are absent: zero)."""
    stamp = message["entities"][0]["timestamp"] if "entities" in message else message.get("timestamp", {})
    return stamp.get("sec", 0) * 1_000_000_000 + stamp.get("nanos", 0)


# --------------------------------------------------------------------------------------------- the client


class FoxgloveClient:
    def __init__(self, ws: Any) -> None:
        self.ws = ws
        self.channels: dict[str, dict[str, Any]] = {}  # topic -> its advertisement
        self.statuses: list[str] = []  # the server's status messages (e.g. dropped messages), for failures

    async def json(self, op: str) -> dict[str, Any]:
        """The next JSON message with this op (advertisements seen on the way are kept)."""
        while True:
            msg = await asyncio.wait_for(self.ws.recv(), WAIT_S)
            assert isinstance(msg, str), f"binary before {op}"
            data = json.loads(msg)
            if data["op"] == "advertise":
                self.channels.update({c["topic"]: c for c in data["channels"]})
            if data["op"] == op:
                return data

    async def advertised(self, *wanted: str) -> None:
        while not set(wanted) <= set(self.channels):
            await self.json("advertise")

    async def subscribe(self, wanted: dict[int, str]) -> None:
        """Subscribe to these topics (subscription id -> topic) in one message."""
        subs = [{"id": i, "channelId": self.channels[topic]["id"]} for i, topic in wanted.items()]
        await self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    async def message(self) -> tuple[int, bytes]:
        """The next message data: (subscription id, payload)."""
        while True:
            msg = await asyncio.wait_for(self.ws.recv(), WAIT_S)
            if isinstance(msg, bytes):
                assert msg[0] == MESSAGE_DATA, msg[:1]
                subscription, _log_time = struct.unpack_from("<IQ", msg, 1)
                return subscription, msg[13:]
            if json.loads(msg)["op"] == "status":
                self.statuses.append(msg)


async def watch(url: str, port: int) -> tuple[DetectionsReply, dict[int, bytes], dict[str, Any], str]:
    """Connect, see a stream's channels come with its first sector, subscribe, send sectors until one is
    seen on both subscriptions -> (its reply, payload per subscription, channels, server name). The protocol
    does not acknowledge a subscription: the sectors sent before the server has it are not drawn for us. A
    subscription sent right after the advertisement may find the channel not yet known to the server (a
    status "Unknown channel ID", seen on a busy machine): that subscription is dead, so it is sent again."""
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL]) as ws:
        assert ws.subprotocol == SUBPROTOCOL
        client = FoxgloveClient(ws)
        info = await client.json("serverInfo")
        points, boxes = topics("car-1")
        assert points not in client.channels
        await asyncio.to_thread(post, url, "car-1", 0)
        await client.advertised(points, boxes)
        subscriptions = {7: boxes, 8: points}
        await client.subscribe(subscriptions)
        by_subscription = {7: client.channels[boxes], 8: client.channels[points]}
        refusals = 0  # the server's "Unknown channel ID" statuses answered so far
        replies: dict[int, DetectionsReply] = {}
        seen: dict[int, dict[int, bytes]] = {}  # seq -> subscription -> payload
        deadline = time.monotonic() + WAIT_S
        both = lambda: [k for k, got in sorted(seen.items()) if len(got) == 2 and k in replies]  # noqa: E731
        while not both():
            which = {k: sorted(got) for k, got in sorted(seen.items())}  # seq -> the subscriptions seen
            assert time.monotonic() < deadline, f"no sector on both subscriptions: {which} {client.statuses}"
            refused = [m for m in client.statuses if "Unknown channel ID" in m]
            if len(refused) > refusals:  # subscribe again to what has not come yet
                refusals = len(refused)
                delivered = {i for got in seen.values() for i in got}
                await client.subscribe({i: top for i, top in subscriptions.items() if i not in delivered})
            replies[len(replies) + 1] = await asyncio.to_thread(post, url, "car-1", len(replies) + 1)
            with contextlib.suppress(TimeoutError):  # what came in a second; late ones are kept too
                while True:
                    subscription, payload = await asyncio.wait_for(client.message(), 1.0)
                    seq = sensor_time_ns(decoded(by_subscription[subscription], payload)) // SECTOR_NS
                    seen.setdefault(seq, {})[subscription] = payload  # sector 0's, if any, is not used
        seq = both()[0]
        return replies[seq], seen[seq], client.channels, info["name"]


def test_a_stream_is_seen_live(det):
    port = free_port()
    with serve(det, foxglove_port=port) as s:
        reply, got, channels, name = asyncio.run(watch(s.url, port))
    assert name == "test-worker"
    points, boxes = channels["/phim/car-1/points"], channels["/phim/car-1/boxes"]
    assert (boxes["schemaName"], boxes["encoding"]) == ("foxglove.SceneUpdate", "protobuf")
    assert (points["schemaName"], points["encoding"]) == ("foxglove.PointCloud", "protobuf")
    assert set(got) == {7, 8}
    assert len(reply.boxes) > 0  # the checks below mean something
    scene = decoded(boxes, got[7])
    entities = scene["entities"]
    assert sum(len(e["cubes"]) for e in entities) == len(reply.boxes)
    assert {e["frame_id"] for e in entities} == {"phim/car-1"}
    classes = [{m["key"]: m["value"] for m in e["metadata"]}["class"] for e in entities]
    assert classes == list(reply.class_names)
    sizes = [[c["size"].get(k, 0.0) for k in "xyz"] for e in entities for c in e["cubes"]]
    np.testing.assert_allclose(sizes, reply.boxes[:, 3:6], rtol=1e-6)  # l, w, h
    cloud = decoded(points, got[8])
    assert cloud["frame_id"] == "phim/car-1"
    assert cloud["point_stride"] * len(CONTROL) == len(cloud["data"])


# ---------------------------------------------------------------------------------- never in serving's way


def listening_ports() -> set[int]:
    """TCP ports this process listens on (Linux: LISTEN rows of /proc/net/tcp{,6} with a socket of ours)."""
    ours = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:  # closed meanwhile
            continue
        if target.startswith("socket:["):
            ours.add(target[8:-1])
    ports = set()
    for table in ("tcp", "tcp6"):
        for row in Path(f"/proc/net/{table}").read_text().splitlines()[1:]:
            cols = row.split()
            if cols[3] == "0A" and cols[9] in ours:  # 0A: LISTEN
                ports.add(int(cols[1].rsplit(":", 1)[1], 16))
    return ports


def test_only_foxglove_port_opens_a_port(det):
    before = listening_ports()
    with serve(det) as s:
        assert listening_ports() - before == {int(s.url.rsplit(":", 1)[1])}  # HTTP only
    port = free_port()
    with serve(det, foxglove_port=port) as s:
        assert listening_ports() - before == {int(s.url.rsplit(":", 1)[1]), port}
    assert port not in listening_ports()  # closed on shutdown


def test_a_stuck_view_never_holds_serving_up(det, monkeypatch):
    """The drawing thread blocks on its first sector: every sector is still answered while it is stuck (not
    after it), the view's queue fills (8) and the rest are dropped and counted."""
    gate, drawing, drawn = threading.Event(), threading.Event(), threading.Event()

    def stuck(self: LiveView, msg: Any, reply: Any) -> None:
        drawing.set()
        gate.wait(WAIT_S)
        drawn.set()

    monkeypatch.setattr(LiveView, "_draw", stuck)
    sent = 14
    with serve(det, foxglove_port=free_port()) as s:
        try:
            post(s.url, "car-1", 0)
            assert drawing.wait(WAIT_S)
            for seq in range(1, sent):
                post(s.url, "car-1", seq)
            assert not drawn.is_set()  # all answered while the drawer is still stuck: nothing waited on it
            metrics = httpx.get(f"{s.url}/metrics").text
        finally:
            gate.set()
    (line,) = [m for m in metrics.splitlines() if m.startswith("phim_live_view_dropped_total ")]
    assert float(line.split()[1]) == sent - 1 - 8  # one in the stuck drawer, 8 queued


def test_a_failing_observer_never_fails_a_sector(det, caplog):
    calls = []

    def observer(msg: Any, reply: DetectionsReply) -> None:
        calls.append(reply.seq)
        raise RuntimeError("the view broke")

    worker = Worker(lambda: (det, "test"), WorkerConfig(warmup_sectors=1), observer=observer)
    worker.start()
    try:
        assert worker.wait_ready(START_TIMEOUT_S)
        for seq in range(3):
            reply = worker.submit(sector_msg("car-1", seq, CONTROL)).result(WAIT_S)
            assert reply.seq == seq
    finally:
        worker.close()
    assert calls == [0, 1, 2]
    assert "observer failed on car-1 seq 0" in caplog.text


def test_live_view_settings(monkeypatch):
    assert Settings().foxglove_port is None
    monkeypatch.setenv("PHIM_FOXGLOVE_PORT", "8765")
    assert Settings().live_view_config().port == 8765
    with pytest.raises(ValidationError, match="no authentication"):
        Settings(foxglove_host="0.0.0.0")
    assert Settings(foxglove_host="0.0.0.0", insecure=True).live_view_config().host == "0.0.0.0"
    monkeypatch.delenv("PHIM_FOXGLOVE_PORT")
    Settings(foxglove_host="0.0.0.0")  # no live view: its host does not matter
