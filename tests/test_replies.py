"""Replies a user can act on: the server's `min_score` (a setting, a sector's own override in the contract,
GET /v1/model, the OpenAPI document), the score curve it is chosen from, and the pictures of what a reply
returns (`phim replay --frames`, `phim eval --pictures`); on the real KITTI scans at the default settings,
at most 15 boxes per turn and none on the ego vehicle."""

from __future__ import annotations

import math
from pathlib import Path

import httpx
import msgpack
import numpy as np
import pytest
from click.testing import CliRunner
from client_helpers import png_is_a_picture
from conftest import KITTI_VELODYNE, kitti_scan
from pydantic import ValidationError
from server_helpers import default_detector, sector_msg, serve

from clients.http_client import HttpClient
from clients.predictions import read_predictions
from contract import (
    DEFAULT_MIN_SCORE,
    JSON,
    MSGPACK,
    ErrorCode,
    ErrorReply,
    ServiceError,
    decode_response,
    decode_sector,
    encode_sector,
)
from lidar.types import GroundTruth, Predictions
from model.config import EgoFootprint
from model.ego import on_ego
from model.eval.pictures import replied_boxes
from model.eval.runner import ScanResult
from model.eval.score_curve import score_curve
from model.sectors import split_turn
from phim.cli import main as app
from server.settings import Settings

MAX_BOXES_PER_TURN = 15  # issue 50's target for the default settings on the 6 KITTI scans


# ---------------------------------------------------------------------------------------------- contract


def test_a_sectors_min_score_travels_and_is_absent_unless_set() -> None:
    pts = np.zeros((3, 4), np.float32)
    for media in (MSGPACK, JSON):
        assert (
            decode_sector(
                encode_sector(sector_msg("c", 0, pts, min_score=0.25), media), media_type=media
            ).min_score
            == 0.25
        )
        plain = encode_sector(sector_msg("c", 0, pts), media)
        assert b"min_score" not in plain  # an older server, which refuses unknown keys, still takes it
        assert decode_sector(plain, media_type=media).min_score is None


@pytest.mark.parametrize("value", [1.5, -0.1, math.nan, "high", None])
def test_a_bad_min_score_is_an_error_naming_the_field(value: object) -> None:
    body = msgpack.unpackb(encode_sector(sector_msg("c", 0, np.zeros((3, 4), np.float32))))
    body["min_score"] = value
    with pytest.raises(ServiceError) as e:
        decode_sector(msgpack.packb(body))
    assert e.value.code is ErrorCode.INVALID_FIELD and e.value.field == "min_score"
    assert e.value.message.startswith("min_score: ") and "number" in e.value.message


# ---------------------------------------------------------------------------------------------- settings


def test_the_settings_min_score_and_ego_footprint() -> None:
    s = Settings()
    assert s.min_score == DEFAULT_MIN_SCORE and s.worker_config().min_score == DEFAULT_MIN_SCORE
    assert s.ego_footprint is None  # the checkpoint config's
    assert Settings(min_score=0).worker_config().min_score == 0.0
    with pytest.raises(ValidationError, match="min_score"):
        Settings(min_score=1.2)
    assert Settings(ego_footprint="-1, 2,-0.5,0.5").ego_footprint == (-1.0, 2.0, -0.5, 0.5)
    assert Settings(ego_footprint="off").ego_footprint == ()
    for bad in ("1,2,3", "2,1,0,1", "a,b,c,d"):
        with pytest.raises(ValidationError, match="ego_footprint"):
            Settings(ego_footprint=bad)


def test_serve_help_names_both_settings() -> None:
    out = CliRunner().invoke(app, ["serve", "--help"]).output
    assert "--min-score" in out and "PHIM_MIN_SCORE" in out and "--ego-footprint" in out


# ------------------------------------------------------------------------------------------- score curve


def test_the_score_curve_counts_precision_and_recall_at_each_threshold() -> None:
    """Two labelled vehicles; boxes on both (0.8, 0.2) and one on nothing (0.3)."""
    gt = np.array([[10, 0, -1, 4, 2, 1.5, 0], [20, 5, -1, 4, 2, 1.5, 0]], np.float32)
    truth = GroundTruth(gt, np.array([0, 0]), np.array([100, 100]), np.array([1, 1]))
    boxes = np.concatenate([gt, [[30, -5, -1, 4, 2, 1.5, 0]]]).astype(np.float32)
    pred = Predictions(boxes, np.array([0.8, 0.2, 0.3], np.float32), np.array([0, 0, 0]))
    curve = score_curve([ScanResult("s", [pred], [truth])], cutoffs=(0.1, 0.25, 0.5, 0.9))
    v = curve["classes"]["VEHICLE"]
    assert v["labels"] == 2
    assert v["precision"] == [pytest.approx(2 / 3), 0.5, 1.0, None]
    assert v["recall"] == [1.0, 0.5, 0.5, 0.0]
    assert v["best"] == 0.1 and v["f1"][0] == pytest.approx(0.8)
    assert curve["boxes_per_scan"] == [3.0, 2.0, 1.0, 0.0]


def test_eval_pictures_draw_what_a_server_at_min_score_returns(tmp_path: Path) -> None:
    pred = Predictions(
        np.zeros((3, 7), np.float32), np.array([0.2, 0.5, 0.9], np.float32), np.array([0, 1, 2])
    )
    shown = replied_boxes(pred, 0.5)
    assert shown.names == ("PEDESTRIAN", "CYCLIST") and shown.scores.tolist() == [0.5, pytest.approx(0.9)]


# ------------------------------------------------------------------------------------ the running server


@pytest.fixture(scope="module")
def at_default() -> object:
    """A real server with the shipped default model at the default min_score."""
    with serve(default_detector(), min_score=DEFAULT_MIN_SCORE) as s:
        yield s


@pytest.mark.samples
def test_kitti_replies_at_the_default_settings_are_few_and_keep_off_the_ego_vehicle(at_default) -> None:
    """Every reply of the 6 KITTI scans streamed at full resolution: at most 15 boxes (the whole turn the
    stream's buffer covers), each scored at least min_score, none centred on the ego car."""
    ego = EgoFootprint()
    most = 0
    with HttpClient(at_default.url) as client:
        for i in range(6):
            for seq, sector in enumerate(split_turn(kitti_scan(i), 4)):
                reply = client.send(sector_msg(f"kitti-{i}", seq, sector.numpy()))
                most = max(most, len(reply.scores))
                assert len(reply.scores) <= MAX_BOXES_PER_TURN, (i, seq, len(reply.scores))
                assert (reply.scores >= DEFAULT_MIN_SCORE).all()
                centres = reply.boxes[:, :2]
                assert not on_ego(ego, *(np.ascontiguousarray(c) for c in centres.T)).any()
    assert most > 0  # something was found


@pytest.mark.samples
def test_a_sectors_own_min_score_overrides_the_servers(at_default) -> None:
    sectors = [s.numpy() for s in split_turn(kitti_scan(0), 4)]
    with HttpClient(at_default.url) as client:
        replies = [
            [
                client.send(sector_msg(f"own-{least}", seq, s, min_score=least))
                for seq, s in enumerate(sectors)
            ]
            for least in (None, 0.0, 0.8)
        ]
    server, every, strict = (r[-1] for r in replies)
    assert len(every.scores) > len(server.scores) >= len(strict.scores)
    assert every.scores.min() < DEFAULT_MIN_SCORE and (strict.scores >= 0.8).all()
    # the server's reply is exactly the every-box reply's head
    assert np.array_equal(server.scores, every.scores[every.scores >= np.float32(DEFAULT_MIN_SCORE)])


def test_a_bad_min_score_gets_422_naming_it_and_the_model_route_says_the_servers(at_default) -> None:
    body = msgpack.unpackb(encode_sector(sector_msg("bad", 0, np.zeros((10, 4), np.float32))))
    body["min_score"] = 2.0
    r = httpx.post(
        f"{at_default.url}/v1/streams/bad/sectors",
        content=msgpack.packb(body),
        headers={"Content-Type": MSGPACK},
    )
    reply = decode_response(r.content)
    assert r.status_code == 422 and isinstance(reply, ErrorReply) and reply.field == "min_score"
    info = httpx.get(f"{at_default.url}/v1/model").json()
    assert info["min_score"] == DEFAULT_MIN_SCORE and info["config_detail"]["ego"] == vars(EgoFootprint())
    sector = httpx.get(f"{at_default.url}/openapi.json").json()["components"]["schemas"]["WireSector"]
    field = sector["properties"]["min_score"]
    assert field["minimum"] == 0.0 and field["maximum"] == 1.0 and "min_score" not in sector["required"]


def test_the_servers_ego_footprint_setting_reaches_the_model() -> None:
    with serve(None, ego_footprint="-1,1,-0.5,0.5") as s:
        assert httpx.get(f"{s.url}/v1/model").json()["config_detail"]["ego"] == vars(
            EgoFootprint(-1, 1, -0.5, 0.5)
        )
    with serve(None, ego_footprint="off") as s:
        assert httpx.get(f"{s.url}/v1/model").json()["config_detail"]["ego"] is None


@pytest.mark.samples
def test_replay_asks_for_its_min_score_and_draws_what_came_back(at_default, tmp_path: Path) -> None:
    for least, want in ((None, DEFAULT_MIN_SCORE), ("0.1", 0.1)):
        out, frames = tmp_path / f"p{least}.jsonl", tmp_path / f"frames{least}"
        args = [
            "replay",
            str(KITTI_VELODYNE),
            "--url",
            at_default.url,
            "--out",
            str(out),
            "--frames",
            str(frames),
        ]
        args += ["--rate", "0", "--max-scans", "1"] + ([] if least is None else ["--min-score", least])
        result = CliRunner().invoke(app, args)
        assert result.exit_code == 0, result.output
        header, records = read_predictions(out)
        assert header["model"]["min_score"] == DEFAULT_MIN_SCORE
        scores = np.concatenate([r.scores for r in records])
        assert len(scores) > 0 and scores.min() >= np.float32(want)
        png_is_a_picture(frames / "000000.png")
