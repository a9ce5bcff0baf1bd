"""`phim diagnose`: the error measures on constructed boxes, and the command on the shipped model."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from model.eval.diagnose import COLUMNS, box_errors

REPO = Path(__file__).resolve().parents[1]
TRUE = torch.tensor([[10.0, -5.0, 0.5, 4.0, 2.0, 1.5, 0.3]], dtype=torch.float64)


def errors(pred: torch.Tensor) -> dict[str, float]:
    row = box_errors(pred, TRUE, torch.tensor([0.8], dtype=torch.float64))[0]
    return dict(zip(COLUMNS, row.tolist(), strict=True))


def test_a_perfect_box_has_no_error() -> None:
    e = errors(TRUE.clone())
    assert all(e[c] == pytest.approx(1.0) for c in COLUMNS if c.startswith("iou"))
    assert all(e[c] == pytest.approx(0.0, abs=1e-9) for c in COLUMNS[:7])
    assert e["score"] == pytest.approx(0.8)


def test_a_box_turned_round_is_flipped_with_the_axis_right() -> None:
    pred = TRUE.clone()
    pred[0, 6] += math.pi
    e = errors(pred)
    assert e["flipped"] == 1.0 and e["axis_deg"] == pytest.approx(0.0, abs=1e-6)
    assert e["iou"] == pytest.approx(1.0)  # IoU cannot see the direction


def test_each_part_of_the_error_is_measured_on_its_own() -> None:
    pred = TRUE.clone()
    pred[0, :2] += torch.tensor([0.3, 0.4], dtype=torch.float64)  # centre 0.5 m off
    pred[0, 3] *= 1.25  # 25 % too long
    pred[0, 6] -= math.radians(100)  # 100 deg off: flipped, axis 80 deg off
    e = errors(pred)
    assert e["centre_m"] == pytest.approx(0.5) and e["rel_l"] == pytest.approx(0.25)
    assert e["axis_deg"] == pytest.approx(80.0) and e["flipped"] == 1.0
    assert e["iou"] < e["iou_true_yaw"] < 1.0  # with the true yaw only centre and length are off
    assert e["iou"] < e["iou_true_size"] < 1.0  # (crossed boxes: the true centre alone changes nothing here)


@pytest.mark.parametrize("part", ["size", "centre"])
def test_the_true_part_put_in_is_the_whole_error_when_it_is_the_only_one(part: str) -> None:
    pred = TRUE.clone()
    if part == "size":
        pred[0, 3:6] *= torch.tensor([1.2, 0.9, 1.1], dtype=torch.float64)
    else:
        pred[0, :3] += torch.tensor([0.4, -0.3, 0.2], dtype=torch.float64)
    e = errors(pred)
    assert e["iou"] < 0.8 and e[f"iou_true_{part}"] == pytest.approx(1.0)
    other = "centre" if part == "size" else "size"
    assert e[f"iou_true_{other}"] == pytest.approx(e["iou"]) and e["iou_true_yaw"] == pytest.approx(e["iou"])


def phim_diagnose(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    cmd = [str(Path(sys.executable).parent / "phim"), "diagnose", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=REPO)


@pytest.fixture(scope="module")
def by_class() -> dict:
    """`phim diagnose` of the shipped model on two held-out scans, by class: the checkpoint and the seed
    named as their defaults are (the tests below read it as either)."""
    done = phim_diagnose("--checkpoint", "default", "--scans", "2", "--seed", "7", "--json")
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout)


def test_phim_diagnose_on_the_shipped_model(by_class: dict) -> None:
    vehicles = by_class["VEHICLE"]
    assert vehicles["targets"] >= 5 and vehicles["iou_threshold"] == 0.7
    assert 0.0 <= vehicles["at_threshold"] <= 1.0 and 0.0 < vehicles["iou"] <= 1.0
    for part in ("size", "centre"):  # the shipped model's sizes and centres are off: the true ones gain
        assert vehicles[f"at_threshold_true_{part}"] >= vehicles["at_threshold"], part
    assert vehicles["centre_m"] < 1.0  # the trained model finds vehicle centres to within a metre


def test_phim_diagnose_by_points_and_range(by_class: dict) -> None:
    groups = {}
    for by in ("points", "range"):  # the default checkpoint and seed
        done = phim_diagnose("--scans", "2", "--by", by, "--json")
        assert done.returncode == 0, done.stderr[-3000:]
        groups[by] = json.loads(done.stdout)
    for by, result in groups.items():  # the buckets split each class's targets
        vehicle_keys = [k for k in result if k.startswith("VEHICLE, ")]
        assert len(vehicle_keys) >= 2, result.keys()
        assert sum(result[k]["targets"] for k in vehicle_keys) == by_class["VEHICLE"]["targets"], by
    assert "VEHICLE, >= 301 points" in groups["points"] or "VEHICLE, 0-20 points" in groups["points"]
    bad = phim_diagnose("--by", "colour", timeout=120)
    assert bad.returncode != 0 and "--by" in bad.stderr
