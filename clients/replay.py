"""`phim replay`: stream a recorded drive to a server, one stream, at sensor rate or as fast as answered.

Each scan is cut into the model's sectors in sweep order (lidar.sectorizer.split_scan) and sent in order;
every sector's answer (detections or the server's error) becomes one record of the prediction file
(clients.predictions). With `min_score`, every sector asks for the boxes scored at least that (else the
server's min_score applies). With `frames_dir`, one bird's-eye-view PNG per scan after its last sector:
points, the boxes the reply returned and the labels when they sit beside the scan (KITTI label_2 + calib,
nuScenes boxes), drawn as `phim eval --pictures` draws (lidar.pictures).

The scans come from scan files (lidar.readers) or from a ROS 2 recording (rosbag2 folder, .mcap, .db3:
ros.recordings, one PointCloud2 message per turn). With `mcap`, the points of each scan and the
boxes of its last sector are written as a Foxglove scene (ros.scene) at the scan's sensor time.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from itertools import islice
from pathlib import Path
from typing import Any

import numpy as np

from clients.base import DetectorClient, ServerError
from clients.connect import ConnectConfig, make_client
from clients.predictions import PredictionRecord, PredictionWriter
from contract import REQUIRED_FIELDS, SectorMessage
from lidar.labels import labels_for
from lidar.pictures import BoxSet, draw_bev
from lidar.readers import Scan, find_scans, read_scan
from lidar.sectorizer import split_scan
from ros.recordings import is_recording, read_recording
from ros.scene import SceneChannels, record_scenes

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReplayConfig:
    source: Path  # a folder of scans, one scan file, or a ROS 2 recording (rosbag2 folder, .mcap, .db3)
    predictions: Path  # the JSON-lines prediction file to write
    connect: ConnectConfig = field(default_factory=ConnectConfig)
    stream_id: str = "replay"
    turns_per_s: float = 10.0  # sensor rate; 0: as fast as the server answers
    sectors_per_turn: int | None = None  # None: ask the server
    frames_dir: Path | None = None  # BEV PNGs, one per scan
    max_scans: int | None = None
    every: int = 1  # keep every n-th point
    end_stream: bool = True  # end the stream on the server when done
    topic: str | None = None  # recordings: the PointCloud2 topic (None: the only one)
    intensity_scale: float = 1.0  # recordings: intensity multiplier (1/255 for 0..255 drivers)
    mcap: Path | None = None  # write the replayed points and boxes as a Foxglove MCAP here
    min_score: float | None = None  # the boxes each reply keeps, 0..1; None: the server's min_score


@dataclass
class ReplaySummary:
    scans: int = 0
    sectors: int = 0
    ok: int = 0
    errors: int = 0
    late_sectors: int = 0  # sent after their due time (the server was slower than the sensor)
    frames: list[Path] = field(default_factory=list)
    scenes: int = 0  # scans written to the MCAP file


def replay(cfg: ReplayConfig) -> ReplaySummary:
    scans = scan_source(cfg)  # input errors raise here, before anything is sent
    with make_client(cfg.connect) as client:
        info = _model_info(client)
        spt = cfg.sectors_per_turn or int(info.get("sectors_per_turn", 4))
        header = {
            "source": str(cfg.source),
            "stream_id": cfg.stream_id,
            "sectors_per_turn": spt,
            "model": info,
        }
        with PredictionWriter(cfg.predictions, header) as writer, _scenes(cfg.mcap) as scenes:
            summary = _run(client, cfg, scans, spt, writer, scenes, info.get("min_score"))
        if cfg.end_stream:
            client.end_stream(cfg.stream_id)
    return summary


def scan_source(cfg: ReplayConfig) -> Iterator[Scan]:
    """The scans to replay, read one by one: a recording's PointCloud2 messages or the scan files."""
    if is_recording(cfg.source):
        return islice(read_recording(cfg.source, cfg.topic, cfg.intensity_scale), cfg.max_scans)
    if cfg.topic is not None or cfg.intensity_scale != 1.0:
        raise ValueError(
            f"{cfg.source}: a topic and an intensity scale are for ROS 2 recordings"
            " (rosbag2 folder, .mcap, .db3)"
        )
    paths = find_scans(cfg.source)[: cfg.max_scans]
    if not paths:
        raise FileNotFoundError(f"{cfg.source}: no scans (.bin, .pcd.bin, .npz) and not a ROS 2 recording")
    return (read_scan(p) for p in paths)


def _scenes(path: Path | None) -> contextlib.AbstractContextManager[SceneChannels | None]:
    return contextlib.nullcontext() if path is None else record_scenes(path)


def _model_info(client: DetectorClient) -> dict[str, Any]:
    try:
        info = client.model_info()
    except Exception as e:  # zenoh without an HTTP address: the file then says so
        log.warning("model info unavailable: %s", e)
        return {}
    keys = ("name", "version", "config", "weights", "classes", "sectors_per_turn", "min_score")
    return {k: info.get(k) for k in keys}


def _run(
    client: DetectorClient,
    cfg: ReplayConfig,
    scans: Iterator[Scan],
    spt: int,
    w: PredictionWriter,
    scenes: SceneChannels | None = None,
    server_min_score: float | None = None,
) -> ReplaySummary:
    """server_min_score: the server's (GET /v1/model; None: unknown), which replies keep without one of
    the replay's own."""
    summary = ReplaySummary()
    least = server_min_score if cfg.min_score is None else cfg.min_score  # what the frames say
    period = 1.0 / (cfg.turns_per_s * spt) if cfg.turns_per_s > 0 else 0.0
    t0, seq = time.monotonic(), 0
    for scan_index, scan in enumerate(scans):
        sectors = split_scan(scan.points, scan.fields, spt, scan.spin)
        sent = [sector.points[:: cfg.every] for sector in sectors]  # (N_k, 4) each
        last: PredictionRecord | None = None
        for position, sector in enumerate(sectors):
            due = t0 + seq * period
            lag = due - time.monotonic()
            if lag > 0:
                time.sleep(lag)
            elif period and lag < -period:
                summary.late_sectors += 1
            msg = SectorMessage(
                cfg.stream_id,
                seq,
                sector.index,
                _stamp(scan, seq, position, period),
                sent[position],
                REQUIRED_FIELDS,
                reset=seq == 0,
                min_score=cfg.min_score,
            )
            last = _send(client, msg, scan.name, scan_index, position, position == len(sectors) - 1)
            w.write(last)
            summary.sectors += 1
            summary.ok += last.error is None
            summary.errors += last.error is not None
            seq += 1
        summary.scans += 1
        if cfg.frames_dir is not None and last is not None:
            summary.frames.append(draw_scan(cfg.frames_dir, scan, last, least))
        if scenes is not None and last is not None:
            scenes.log(last, np.concatenate(sent), _stamp(scan, seq - len(sectors), 0, period))
            summary.scenes += 1
    return summary


def _stamp(scan: Scan, seq: int, position: int, period: float) -> int:
    """A sector's sensor time: its scan's stamp plus its place in the turn, or (scans without a stamp) the
    drive's start plus its place in the drive."""
    step = (period or 0.025) * 1e9
    if scan.timestamp_ns is not None:
        return scan.timestamp_ns + round(position * step)
    return round(seq * step)


def _send(
    client: DetectorClient, msg: SectorMessage, scan: str, scan_index: int, pos: int, last: bool
) -> PredictionRecord:
    start = time.monotonic()
    common: dict[str, Any] = dict(
        scan=scan,
        scan_index=scan_index,
        seq=msg.seq,
        sector_index=msg.sector_index,
        position=pos,
        last_in_scan=last,
        timestamp_ns=msg.timestamp_ns,
        points=int(msg.points.shape[0]),
    )
    try:
        r = client.send(msg)
    except ServerError as e:
        empty = np.zeros((0, 7), np.float32)
        return PredictionRecord(
            **common,
            context_sectors=0,
            boxes=empty,
            scores=np.zeros(0, np.float32),
            labels=np.zeros(0, np.int32),
            class_names=(),
            timings={},
            latency_ms=(time.monotonic() - start) * 1e3,
            error={"code": e.code.value, "message": e.message, "field": e.field},
        )
    return PredictionRecord(
        **common,
        context_sectors=r.context_sectors,
        boxes=r.boxes,
        scores=r.scores,
        labels=r.labels,
        class_names=r.class_names,
        timings=asdict(r.timings),
        latency_ms=(time.monotonic() - start) * 1e3,
    )


def draw_scan(folder: Path, scan: Scan, prediction: PredictionRecord, min_score: float | None = None) -> Path:
    """The scan's points, the boxes of its last sector's reply (which kept those scored at least
    `min_score`; None: unknown) and its labels where they sit beside it."""
    labels = labels_for(scan.path)
    return draw_bev(
        folder / f"{scan.name}.png",
        scan.points,
        BoxSet(prediction.boxes, prediction.class_names, prediction.scores),
        None if labels is None else BoxSet(labels.boxes, labels.names),
        title=f"{scan.name} (context {prediction.context_sectors} sectors)",
        min_score=min_score,
    )
