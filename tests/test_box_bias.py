"""`phim diagnose --matched` (model/eval/box_bias.py): size bias and heading flips of the matched boxes, on
constructed boxes, and the command on the shipped model."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lidar.types import GroundTruth, Predictions
from model.eval.box_bias import PAIR_COLUMNS, MatchConfig, box_bias, match_scan
from model.eval.runner import ScanResult

REPO = Path(__file__).resolve().parents[1]
AHEAD = [20.0, 0.0, -0.9, 4.5, 1.9, 1.6, 0.0]  # a car ahead, heading away: seen end-on
ACROSS = [0.0, 15.0, -0.9, 4.5, 1.9, 1.6, 0.0]  # a car to the left, heading along x: seen side-on


def result(truth: list[list[float]], pred: list[list[float]], scores: list[float], labels=None, name="s"):
    gt = GroundTruth(
        np.asarray(truth, np.float32).reshape(-1, 7),
        np.zeros(len(truth), np.int64),
        np.full(len(truth), 100, np.int64),
        np.ones(len(truth), np.int8),
    )
    lab = np.zeros(len(pred), np.int64) if labels is None else np.asarray(labels, np.int64)
    p = Predictions(np.asarray(pred, np.float32).reshape(-1, 7), np.asarray(scores, np.float32), lab)
    return ScanResult(name, [p], [gt])


def pairs(r: ScanResult) -> list[dict[str, float]]:
    return [dict(zip(PAIR_COLUMNS, row, strict=True)) for row in match_scan(r, MatchConfig()).tolist()]


def test_a_perfect_box_has_no_error_and_a_side_or_end_view():
    (end,) = pairs(result([AHEAD], [AHEAD], [0.9]))
    (side,) = pairs(result([ACROSS], [ACROSS], [0.9]))
    for p in (end, side):
        assert all(p[c] == pytest.approx(0.0, abs=1e-5) for c in ("dl", "dw", "dh", "heading_deg"))
    assert end["view_deg"] == pytest.approx(0.0, abs=1e-4) and side["view_deg"] == pytest.approx(90.0)
    assert end["range_m"] == pytest.approx(20.0) and end["points"] == 100


def test_a_short_box_turned_round_is_short_and_flipped():
    pred = list(AHEAD)
    pred[3] -= 0.4  # 0.4 m too short
    pred[6] = math.pi - 0.05  # the wrong way round, 2.9 deg off the axis
    (p,) = pairs(result([AHEAD], [pred], [0.9]))
    assert p["dl"] == pytest.approx(-0.4, abs=1e-5) and p["dw"] == pytest.approx(0.0, abs=1e-5)
    assert p["heading_deg"] == pytest.approx(180 - math.degrees(0.05), abs=1e-3)
    s = box_bias([result([AHEAD], [pred], [0.9])])["VEHICLE"]
    assert s["flipped"] == 1.0 and s["flipped_end_on"] == 1.0 and s["flipped_side_on"] is None
    assert s["dl_median_m"] == pytest.approx(-0.4, abs=1e-5) and s["dl_median_side_on_m"] is None


def test_a_box_too_long_at_its_far_end_is_off_at_its_far_end_only():
    """A car ahead seen end-on (its back towards the sensor) and one across, seen side-on: a box 0.4 m too
    long whose near end is right is 0.4 m off at its far end; one shifted 0.2 m towards the sensor is
    -0.2 m off at both; a box turned round is the same box."""
    for label in (AHEAD, ACROSS):
        axis = np.array([math.cos(label[6]), math.sin(label[6])])
        away = 1.0 if np.dot(label[:2], axis) >= 0 else -1.0
        longer = list(label)
        longer[3] += 0.4
        longer[0] += away * 0.2 * axis[0]
        longer[1] += away * 0.2 * axis[1]
        (p,) = pairs(result([label], [longer], [0.9]))
        assert p["near"] == pytest.approx(0.0, abs=1e-5) and p["far"] == pytest.approx(0.4, abs=1e-5)
        nearer = list(label)
        nearer[0] -= away * 0.2 * axis[0]
        nearer[1] -= away * 0.2 * axis[1]
        nearer[6] += math.pi
        (p,) = pairs(result([label], [nearer], [0.9]))
        assert p["near"] == pytest.approx(-0.2, abs=1e-5) and p["far"] == pytest.approx(-0.2, abs=1e-5)


def test_only_boxes_above_the_score_of_the_class_overlapping_enough_match_each_label_once():
    far = list(AHEAD)
    far[0] += 3.0  # BEV IoU 1.5 / 7.5 = 0.2 with the label
    r = result([AHEAD], [AHEAD, AHEAD, far, AHEAD], [0.9, 0.8, 0.95, 0.7], labels=[0, 0, 0, 1])
    assert len(pairs(r)) == 1  # the duplicate finds no free label; too far; another class
    assert pairs(result([AHEAD], [AHEAD], [0.4])) == []  # under the operating point
    s = box_bias([r, result([AHEAD, ACROSS], [ACROSS], [0.6])])["VEHICLE"]
    assert s["labels"] == 3 and s["matched"] == 2 and s["side_on"] == 0.5 and s["flipped"] == 0.0
    assert "PEDESTRIAN" not in box_bias([r])  # no pedestrian label: no group


def test_groups_split_by_samples_subfolder():
    rs = [result([AHEAD], [AHEAD], [0.9], name="kitti/0"), result([ACROSS], [ACROSS], [0.9], name="nusc/1")]
    d = box_bias(rs, by_group=True)
    assert d["VEHICLE"]["matched"] == 2 and d["VEHICLE, kitti"]["matched"] == 1
    assert d["VEHICLE, kitti"]["side_on"] == 0.0 and d["VEHICLE, nusc"]["side_on"] == 1.0


def run(*args: str) -> subprocess.CompletedProcess:
    phim = str(Path(sys.executable).parent / "phim")
    return subprocess.run([phim, *args], capture_output=True, text=True, timeout=600, cwd=REPO)


def test_phim_diagnose_matched_on_the_shipped_model_and_from_its_predictions(tmp_path: Path):
    common = ["--data", "sim", "--scans", "1", "--seed", "7"]
    done = run("diagnose", "--matched", *common, "--json")
    assert done.returncode == 0, done.stderr[-3000:]
    direct = json.loads(done.stdout)
    v = direct["VEHICLE"]
    assert 3 <= v["matched"] <= v["labels"] and 0.0 <= v["flipped"] <= 1.0
    assert abs(v["dl_median_m"]) < 1.0 and abs(v["dw_median_m"]) < 0.5  # trained: within a metre
    preds = tmp_path / "p.npz"
    assert run("eval", *common, "--predictions", str(preds), "--json").returncode == 0
    again = run("diagnose", "--matched", "--rescore", str(preds), *common, "--json")
    assert again.returncode == 0, again.stderr[-3000:]
    assert json.loads(again.stdout) == direct  # the same boxes, read back
    bad = run("diagnose", "--by", "group", *common)
    assert bad.returncode != 0 and "--matched" in bad.stderr
