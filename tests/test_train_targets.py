"""Training targets, losses and samples: the targets decode back to their boxes as the head decodes."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from lidar.readers import sector_of_xy
from lidar.synthetic import synthetic_turn
from lidar.types import GroundTruth, LabeledScan, points_in_boxes
from model.config import HeadingCode, tiny
from model.layers.head import HeadOutput, decode, decode_yaw, decoded_boxes, encode_yaw
from model.layers.head_targets import TargetConfig, build_targets, gaussian_radius
from model.train.data import AugmentConfig, SampleConfig, augment, make_sample
from model.train.loss import LossConfig, center_loss, focal_loss

CFG = tiny()
BOXES = np.array(
    [
        [10.3, 3.1, -0.9, 4.5, 1.9, 1.6, 0.3],  # a vehicle ahead
        [-20.2, -5.7, -0.9, 4.2, 1.8, 1.5, 2.0],  # behind, sector 1
        [5.1, -12.4, -0.8, 0.7, 0.7, 1.8, -1.0],  # a pedestrian
        [30.6, 20.2, -0.9, 1.8, 0.6, 1.7, 1.0],  # a cyclist
    ],
    np.float32,
)
LABELS = np.array([0, 0, 1, 2])


def test_gaussian_radius_grows_with_size_and_shrinks_with_overlap():
    assert gaussian_radius(10, 5, 0.1) > gaussian_radius(5, 2.5, 0.1) > 0
    assert gaussian_radius(10, 5, 0.7) < gaussian_radius(10, 5, 0.1)


def test_targets_decode_back_to_the_boxes():
    t = build_targets(BOXES, LABELS, 3, CFG.bev, TargetConfig())
    assert len(t.index) == 4
    flat = torch.from_numpy(t.index)
    boxes = decoded_boxes(torch.from_numpy(t.reg), flat, CFG.bev.nx, CFG.bev.ny, CFG.bev, HeadingCode.SIN_COS)
    order = np.argsort(np.hypot(BOXES[:, 0], BOXES[:, 1]))  # targets are kept nearest first
    np.testing.assert_allclose(boxes.numpy(), BOXES[order], atol=1e-4)
    for label, cell in zip(t.labels, t.index, strict=True):  # the peak sits at the centre cell
        assert t.heatmap[label].reshape(-1)[cell] == 1.0
    assert t.heatmap.max() == 1.0 and (t.heatmap == 1.0).sum() == 4


@pytest.mark.parametrize("code", list(HeadingCode))
def test_yaw_encodes_and_decodes_all_round_the_circle(code: HeadingCode):
    yaw = torch.cat([torch.linspace(-math.pi, math.pi, 721, dtype=torch.float64), torch.tensor([0.3, -2.0])])
    rot, direction = encode_yaw(yaw, code)
    assert (direction is None) == (code is HeadingCode.SIN_COS)
    parts = [*rot.unbind(1)] + ([] if direction is None else [direction * 40 - 20])  # logits +-20
    back = decode_yaw(parts, code)
    wrapped = torch.remainder(back - yaw + math.pi, 2 * math.pi) - math.pi
    assert wrapped.abs().max() < 1e-9


def _perfect_output(targets, code: HeadingCode) -> HeadOutput:
    """Head maps that predict exactly the targets (logits +-20 from the heatmap, regression at centres)."""
    t = targets
    k, h, w = t.heatmap.shape
    hm = torch.full((1, k, h, w), -20.0)
    cells = torch.from_numpy(t.index)
    hm.view(1, k, -1)[0, torch.from_numpy(t.labels), cells] = 20.0
    rot, direction = encode_yaw(torch.from_numpy(t.boxes[:, 6]), code)
    values = [torch.from_numpy(t.reg[:, :6]), rot] + (
        [] if direction is None else [direction[:, None] * 40 - 20]
    )
    values = torch.cat(values, 1)  # (T, 6 + R)
    reg = torch.zeros(1, values.shape[1], h * w)
    reg[0, :, cells] = values.T
    reg = reg.view(1, -1, h, w)
    iou = torch.ones(1, 1, h, w)
    return HeadOutput(hm, reg[:, 0:2], reg[:, 2:3], reg[:, 3:6], reg[:, 6:], iou)


@pytest.mark.parametrize("code", list(HeadingCode))
def test_perfect_head_output_decodes_to_the_boxes_and_has_a_small_loss(code: HeadingCode):
    t = build_targets(BOXES, LABELS, 3, CFG.bev, TargetConfig())
    out = _perfect_output(t, code)
    det = decode(out, replace(CFG.head, heading=code), CFG.bev)[0]
    order = np.argsort(np.hypot(BOXES[:, 0], BOXES[:, 1]))
    got = det.boxes.numpy()[np.argsort(np.hypot(det.boxes[:, 0].numpy(), det.boxes[:, 1].numpy()))]
    np.testing.assert_allclose(got, BOXES[order], atol=1e-4)
    parts = center_loss(out, [t], CFG.bev, code, LossConfig())
    assert parts.reg < 1e-5 and parts.iou_loss < 1e-3 and parts.mean_iou > 0.999
    noisy = HeadOutput(out.heatmap, out.offset + 0.3, out.z, out.log_dim, out.rot, out.iou)
    worse = center_loss(noisy, [t], CFG.bev, code, LossConfig())
    assert worse.reg > 0.1 and worse.mean_iou < 0.9 and float(worse.total) > float(parts.total)
    turned = out.rot.clone()
    if code is HeadingCode.SIN_COS:
        turned = -turned  # (-sin, -cos): yaw + pi
    else:
        turned[:, 2] *= -1  # the direction logit
    flipped = HeadOutput(out.heatmap, out.offset, out.z, out.log_dim, turned, out.iou)
    parts = center_loss(flipped, [t], CFG.bev, code, LossConfig())
    assert parts.reg > 0.5 and parts.mean_iou > 0.999  # the wrong way round costs, though the IoU is the same


def test_focal_loss_prefers_the_right_heatmap():
    t = torch.from_numpy(build_targets(BOXES, LABELS, 3, CFG.bev, TargetConfig()).heatmap)[None]
    good = torch.logit(t.clamp(1e-4, 1 - 1e-4))
    assert focal_loss(good, t) < focal_loss(torch.zeros_like(t), t) < focal_loss(-good, t)


def _scan() -> LabeledScan:
    pts = synthetic_turn(0)
    # drop a cloud of points into every box so that all four are targets
    rng = np.random.default_rng(0)
    inside = [b[:3] + (rng.random((50, 3)) - 0.5) * b[3:6] * 0.5 for b in BOXES]
    extra = np.concatenate([np.concatenate([c, np.full((50, 1), 0.5)], 1) for c in inside]).astype(np.float32)
    pts = np.concatenate([pts, extra])
    return LabeledScan("t", pts, ("x", "y", "z", "intensity"), GroundTruth.from_boxes(BOXES, LABELS, pts))


def test_augment_keeps_points_inside_their_boxes():
    scan = _scan()
    before = points_in_boxes(scan.points[:, :3], BOXES).sum(0)
    for seed in range(5):
        p, b = augment(scan.points, BOXES, np.random.default_rng(seed), AugmentConfig())
        np.testing.assert_array_equal(points_in_boxes(p[:, :3], b).sum(0), before)
        assert np.all(np.abs(b[:, 6]) <= math.pi)


@pytest.mark.parametrize(("clockwise", "step"), [(0.0, 1), (1.0, -1)])
def test_sample_sectors_in_time_order_and_targets_grow_with_the_buffer(clockwise: float, step: int):
    scan = _scan()
    cfg = SampleConfig(augment=AugmentConfig(rotate=False, flip=False, scale=(1.0, 1.0)), clockwise=clockwise)
    s = make_sample(scan, CFG, cfg, np.random.default_rng(3))
    assert sum(len(x) for x in s.sectors) == len(scan.points)
    ks = [int(sector_of_xy(x[:, 0].numpy(), x[:, 1].numpy(), 4)[0]) for x in s.sectors]
    assert sorted(ks) == [0, 1, 2, 3] and all((b - a) % 4 == step % 4 for a, b in itertools.pairwise(ks))
    counts = [len(t.index) for t in s.targets]
    assert counts == sorted(counts) and counts[-1] == 4
    box_sector = sector_of_xy(BOXES[:, 0], BOXES[:, 1], 4)
    assert counts[0] == int((box_sector == ks[0]).sum())


def test_a_box_beyond_the_polar_range_is_not_a_target():
    """The BEV square's corners lie beyond r_max: a box there (with points in the labels, none the model
    keeps) gets no heatmap peak; the same box just inside the range does."""
    corner = 0.97 * CFG.bev.x_max  # inside the BEV map, about 1.37 x_max from the sensor: beyond r_max
    assert math.hypot(corner, corner) > CFG.grid.r_max
    inside = CFG.grid.r_max * 0.9 / math.sqrt(2)
    boxes = np.array([[corner, corner, -0.9, 4.5, 1.9, 1.6, 0.0], [inside, inside, -0.9, 4.5, 1.9, 1.6, 0.0]])
    scan = _scan()
    gt = GroundTruth(boxes.astype(np.float32), np.array([0, 0]), np.array([50, 50]), np.zeros(2, np.int64))
    far = LabeledScan(scan.name, scan.points, scan.fields, gt)
    s = make_sample(far, CFG, SampleConfig(augment=AugmentConfig(rotate=False, flip=False, scale=(1.0, 1.0))),
                    np.random.default_rng(0))  # fmt: skip
    np.testing.assert_allclose(s.targets[-1].boxes[:, :2], boxes[1:, :2], atol=1e-4)


@pytest.mark.parametrize("bad", [0])
def test_a_box_without_points_is_not_a_target(bad):
    scan = _scan()
    gt = scan.gt
    counts = gt.num_points.copy()
    counts[bad] = 0
    empty = LabeledScan(
        scan.name, scan.points, scan.fields, GroundTruth(gt.boxes, gt.labels, counts, gt.difficulty)
    )
    s = make_sample(empty, CFG, SampleConfig(), np.random.default_rng(0))
    assert len(s.targets[-1].index) == 3


def test_samples_spin_both_ways():
    """Sensors spin either way round: about half the samples run clockwise by default."""
    scan, cfg = _scan(), SampleConfig()
    steps = []
    for seed in range(40):
        s = make_sample(scan, CFG, cfg, np.random.default_rng(seed))
        k = [int(sector_of_xy(x[:2, 0].numpy(), x[:2, 1].numpy(), 4)[0]) for x in s.sectors[:2]]
        steps.append((k[1] - k[0]) % 4)
    assert set(steps) == {1, 3} and 10 < steps.count(3) < 30


def test_intensity_is_scaled_per_scan_and_sometimes_constant():
    """Real intensities differ by sensor (KITTI's median 0.3, nuScenes' 0.05, the Argoverse conversion a
    constant 1.0): a scan's intensities get one gain, and now and then a single value."""
    scan = _scan()
    points = scan.points.copy()
    points[:, 3] = np.linspace(0.0, 0.5, len(points))
    cfg = AugmentConfig(rotate=False, flip=False, scale=(1.0, 1.0), constant_intensity=0.3)
    gains, constants = [], 0
    for seed in range(60):
        p, _ = augment(points, BOXES, np.random.default_rng(seed), cfg)
        np.testing.assert_array_equal(p[:, :3], points[:, :3])
        assert p[:, 3].min() >= 0.0 and p[:, 3].max() <= 1.0
        if np.ptp(p[:, 3]) == 0:
            constants += 1
        else:
            gains.append(p[1000, 3] / points[1000, 3])
    assert 8 < constants < 30 and min(gains) < 0.8 and max(gains) > 1.4
