"""Ground-truth sampling: objects cut from bank scans with their points, pasted where no box is, faded out
for the last part of training."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lidar.types import GroundTruth, LabeledScan, points_in_boxes
from model.config import tiny
from model.train.data import SampleConfig, SampleStream
from model.train.gt_sampling import GTSamplingConfig, build_bank, paste_objects

FIELDS = ("x", "y", "z", "intensity")


def scene(seed: int, count: int = 6) -> LabeledScan:
    """Ground points plus `count` vehicles (30 points each) at random places 8-40 m away."""
    rng = np.random.default_rng(seed)
    ground = np.concatenate(
        [rng.uniform(-45, 45, (4000, 2)), np.full((4000, 1), -1.7), rng.random((4000, 1))], 1
    )
    r, a = rng.uniform(8, 40, count), rng.uniform(-np.pi, np.pi, count)
    dims = np.tile(np.array([4.5, 1.9, 1.6]), (count, 1))  # (count, 3)
    centre = np.stack([r * np.cos(a), r * np.sin(a), np.full(count, -0.9)], 1)
    boxes = np.concatenate([centre, dims, rng.uniform(-np.pi, np.pi, (count, 1))], 1).astype(np.float32)
    cars = [b[:3] + (rng.random((30, 3)) - 0.5) * np.array([1.0, 1.0, 0.8]) for b in boxes]
    car_points = np.concatenate([np.concatenate([c, np.full((30, 1), 0.5)], 1) for c in cars])
    points = np.concatenate([ground, car_points]).astype(np.float32)
    labels = np.zeros(count, np.int64)
    return LabeledScan(f"s{seed}", points, FIELDS, GroundTruth.from_boxes(boxes, labels, points))


def test_the_bank_holds_each_object_with_its_points() -> None:
    bank = build_bank(scene, 3, min_points=5)
    assert len(bank) >= 15 and bank.fields == FIELDS
    for k in range(len(bank)):
        pts = bank.object_points(k)
        assert len(pts) >= 5 and points_in_boxes(pts[:, :3], bank.boxes[k : k + 1]).all()


def test_pasted_objects_bring_their_points_and_never_overlap_a_box() -> None:
    bank = build_bank(scene, 5, min_points=5)
    base = scene(100, count=3)
    cfg = GTSamplingConfig(per_class=(8, 0, 0))
    out = paste_objects(base, bank, np.random.default_rng(1), cfg)
    added = len(out.gt) - len(base.gt)
    assert 0 < added <= 8
    centres = out.gt.boxes[:, :2]
    gaps = np.hypot(*(centres[:, None] - centres[None]).transpose(2, 0, 1)) + np.eye(len(centres)) * 99
    assert gaps.min() > 2 * 0.5 * np.hypot(4.5, 1.9)  # footprint circles apart
    np.testing.assert_array_equal(out.gt.num_points[: len(base.gt)], base.gt.num_points)
    assert (out.gt.num_points[len(base.gt) :] >= 5).all()
    again = paste_objects(base, bank, np.random.default_rng(1), cfg)
    np.testing.assert_array_equal(again.points, out.points)
    with pytest.raises(ValueError, match="fields"):
        paste_objects(
            dataclasses.replace(base, fields=("x", "y", "z", "i")), bank, np.random.default_rng(1), cfg
        )


def test_training_pastes_only_before_the_fade() -> None:
    cfg = SampleConfig(gt_sampling=GTSamplingConfig(per_class=(6, 0, 0), bank_scans=4))
    stream = SampleStream(
        lambda i: scene(200 + i, count=2), tiny(), cfg, 0, 0, 1, bank_at=scene, paste_before=3
    )
    samples = [s for _, s in zip(range(5), stream, strict=False)]
    targets = [len(s.targets[-1].index) for s in samples]
    assert all(t > 2 for t in targets[:3]) and targets[3:] == [2, 2]
    plain = SampleStream(lambda i: scene(200 + i, count=2), tiny(), cfg, 0, 0, 1)
    assert [len(s.targets[-1].index) for _, s in zip(range(2), plain, strict=False)] == [2, 2]
