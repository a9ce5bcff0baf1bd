"""CenterPoint head shapes and decoding of hand-built head outputs."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from model.config import BEVConfig, HeadConfig, paper, tiny
from model.geometry.boxes import Detections
from model.layers.head import HEATMAP_PRIOR_BIAS, CenterHead, HeadOutput, decode, local_maxima

BEV = BEVConfig(x_min=-20.48, x_max=20.48, y_min=-10.24, y_max=10.24, cell=0.32)  # 128 x 64 cells
CFG = HeadConfig()  # NMS 0.75 / 0.6 / 0.55, rectifier 0.68 / 0.71 / 0.65, heatmap score threshold 0.1


@dataclasses.dataclass
class Planted:
    box: tuple[float, float, float, float, float, float, float]  # x, y, z, l, w, h, yaw
    label: int
    prob: float  # heatmap probability at the centre cell
    iou: float  # predicted IoU in [0, 1]

    def score(self, cfg: HeadConfig) -> float:
        a = cfg.iou_rectifier[self.label]
        return self.prob ** (1 - a) * self.iou**a


def cell_of(p: Planted, bev: BEVConfig) -> tuple[int, int, float, float]:
    """Row, column and in-cell offsets (x, y) of a box centre, lower-left corner as the reference."""
    fx, fy = (p.box[0] - bev.x_min) / bev.cell, (p.box[1] - bev.y_min) / bev.cell
    col, row = math.floor(fx), math.floor(fy)
    return row, col, fx - col, fy - row


def plant(items: list[list[Planted]], bev: BEVConfig, classes: int = 3) -> HeadOutput:
    """A HeadOutput (B = len(items)) that encodes the given boxes; background logits -10."""
    b, h, w = len(items), bev.ny, bev.nx
    out = HeadOutput(
        heatmap=torch.full((b, classes, h, w), -10.0),
        offset=torch.zeros(b, 2, h, w),
        z=torch.zeros(b, 1, h, w),
        log_dim=torch.zeros(b, 3, h, w),
        rot=torch.zeros(b, 2, h, w),
        iou=torch.full((b, 1, h, w), -1.0),
    )
    for i, planted in enumerate(items):
        for p in planted:
            row, col, ox, oy = cell_of(p, bev)
            _, _, z, length, width, height, yaw = p.box
            out.heatmap[i, p.label, row, col] = math.log(p.prob / (1 - p.prob))
            out.offset[i, :, row, col] = torch.tensor([ox, oy])
            out.z[i, 0, row, col] = z
            out.log_dim[i, :, row, col] = torch.tensor([length, width, height]).log()
            out.rot[i, :, row, col] = 0.7 * torch.tensor(
                [math.sin(yaw), math.cos(yaw)]
            )  # scale must not matter
            out.iou[i, 0, row, col] = 2 * p.iou - 1
    return out


def assert_detections(det: Detections, expected: list[Planted], cfg: HeadConfig) -> None:
    expected = sorted(expected, key=lambda p: -p.score(cfg))
    assert len(det) == len(expected)
    assert det.boxes.dtype == torch.float32 and det.labels.dtype == torch.int64
    torch.testing.assert_close(det.boxes, torch.tensor([p.box for p in expected]), rtol=0, atol=1e-4)
    torch.testing.assert_close(
        det.scores, torch.tensor([p.score(cfg) for p in expected]), rtol=1e-5, atol=1e-6
    )
    assert det.labels.tolist() == [p.label for p in expected]


@pytest.mark.parametrize(("in_channels", "cfg", "rot"), [(32, tiny().head, 3), (384, paper().head, 2)])
def test_forward_shapes(in_channels: int, cfg: HeadConfig, rot: int) -> None:
    head = CenterHead(in_channels, cfg)
    out = head(torch.randn(2, in_channels, 12, 20))
    assert out.heatmap.shape == (2, 3, 12, 20)
    assert out.offset.shape == (2, 2, 12, 20) and out.rot.shape == (2, rot, 12, 20)
    assert out.z.shape == (2, 1, 12, 20) and out.iou.shape == (2, 1, 12, 20)
    assert out.log_dim.shape == (2, 3, 12, 20)
    assert head.heatmap[-1].bias.detach().eq(HEATMAP_PRIOR_BIAS).all()
    assert sum(isinstance(m, torch.nn.Conv2d) for m in head.offset.modules()) == cfg.head_convs
    out.heatmap.sum().backward()
    assert head.shared[0].weight.grad is not None
    dets = decode(head.eval()(torch.randn(1, in_channels, 12, 20)), cfg, tiny().bev)
    assert len(dets) == 1 and torch.isfinite(dets[0].boxes).all()
    assert dets[0].boxes[:, 6].abs().max() <= math.pi


@pytest.mark.parametrize("convs", [1, 2, 3])
def test_stacked_entry_convs_equal_per_branch(convs: int) -> None:
    """`forward` runs the branches' first convs as one conv; `forward_per_branch` runs them one by one."""
    cfg = dataclasses.replace(tiny().head, head_convs=convs)
    torch.manual_seed(convs)
    head = CenterHead(24, cfg)
    for m in head.modules():  # BN statistics that are not the identity
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
    x = torch.randn(2, 24, 9, 13)
    for mode in (head.train, head.eval):
        mode()
        got, want = head(x), head.forward_per_branch(x)
        for f in dataclasses.fields(HeadOutput):
            torch.testing.assert_close(getattr(got, f.name), getattr(want, f.name), rtol=1e-5, atol=1e-5)
    got.heatmap.sum().backward()
    assert all(p.grad is not None for p in head.heatmap.parameters())


def test_decode_recovers_planted_boxes() -> None:
    item0 = [
        Planted((3.17, -2.05, -0.4, 4.6, 1.9, 1.6, 0.3), 0, 0.9, 0.8),
        Planted((-12.3, 5.51, 0.1, 0.8, 0.7, 1.8, -2.9), 1, 0.7, 0.6),
        Planted((10.01, 9.9, 0.2, 1.8, 0.6, 1.7, math.pi / 2), 2, 0.5, 0.9),
    ]
    item1 = [Planted((-20.3, -10.1, 1.0, 5.0, 2.1, 1.9, -1.0), 0, 0.6, 0.7)]  # corner cell (0, 0)
    # the threshold applies to the heatmap score, before the IoU rectification (CenterPoint, OpenPCDet)
    kept = Planted((8.0, -8.0, 0.0, 1.0, 1.0, 1.0, 0.0), 0, 0.3, 0.01)  # heatmap 0.3, rectified 0.03
    dropped = [
        Planted((0.5, 0.5, 0.0, 1.0, 1.0, 1.0, 0.0), 1, 0.02, 0.05),  # heatmap and score below it
        Planted((-8.0, 8.0, 0.0, 1.0, 1.0, 1.0, 0.0), 2, 0.08, 0.99),  # heatmap 0.08, rectified 0.19
    ]
    assert kept.score(CFG) < CFG.score_threshold < dropped[1].score(CFG)
    item0.append(kept)
    out = plant([item0 + dropped, item1], BEV)
    row, col, _, _ = cell_of(item0[0], BEV)
    out.heatmap[0, 0, row, col + 1] = math.log(0.85 / 0.15)  # a neighbour, not a local maximum: no box
    out.iou[0, 0, row, col + 1] = 0.8  # (its box would not be suppressed: 1 m cube, IoU < 0.75)
    dets = decode(out, CFG, BEV)
    assert len(dets) == 2
    assert_detections(dets[0], item0, CFG)
    assert_detections(dets[1], item1, CFG)


def test_nms_in_decode() -> None:
    x0, cell = BEV.x_min, BEV.cell
    car = Planted((x0 + 70.9 * cell, 0.1, 0.0, 4.5, 2.0, 1.5, 0.05), 0, 0.9, 0.9)
    near = Planted((x0 + 72.1 * cell, 0.1, 0.0, 4.6, 2.0, 1.5, 0.0), 0, 0.8, 0.8)  # 2 cells on, IoU ~0.82
    ped = Planted((x0 + 71.3 * cell, 0.1, 0.0, 4.5, 2.0, 1.5, 0.05), 1, 0.7, 0.7)  # same place, other class
    assert cell_of(near, BEV)[1] - cell_of(car, BEV)[1] == 2
    dets = decode(plant([[car, near, ped]], BEV), CFG, BEV)[0]
    assert_detections(dets, [car, ped], CFG)
    loose = dataclasses.replace(CFG, nms_iou=(0.9, 0.6, 0.55))  # a vehicle threshold above their IoU
    assert_detections(decode(plant([[car, near, ped]], BEV), loose, BEV)[0], [car, near, ped], loose)


def test_top_k_limits() -> None:
    boxes = [
        Planted((-15.0 + 2.0 * k, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0), k % 3, 0.9 - 0.05 * k, 0.9) for k in range(8)
    ]
    out = plant([boxes], BEV)
    best = sorted(boxes, key=lambda p: -p.score(CFG))
    assert_detections(decode(out, dataclasses.replace(CFG, post_nms_top_k=3), BEV)[0], best[:3], CFG)
    by_heat = sorted(boxes, key=lambda p: -p.prob)[:5]  # pre-NMS top-k ranks the heatmap peaks
    assert_detections(decode(out, dataclasses.replace(CFG, pre_nms_top_k=5), BEV)[0], by_heat, CFG)


def test_empty_heatmap() -> None:
    dets = decode(plant([[], []], BEV), CFG, BEV)
    assert len(dets) == 2
    for d in dets:
        assert len(d) == 0 and d.boxes.shape == (0, 7) and d.labels.dtype == torch.int64


def test_local_maxima_equals_max_pool() -> None:
    """The shifted-comparison peak test is the 3x3 max-pool equality, ties and borders included."""
    g = torch.Generator().manual_seed(3)
    hm = torch.rand(2, 3, 17, 23, generator=g)
    hm = torch.where(torch.rand(hm.shape, generator=g) < 0.3, torch.full_like(hm, 0.5), hm)  # plateaus: ties
    hm[0, 0] = 0.0  # a flat map: every cell is a maximum
    pooled = torch.nn.functional.max_pool2d(hm, kernel_size=3, stride=1, padding=1) == hm
    peaks = local_maxima(hm)
    assert torch.equal(peaks, pooled)
    assert peaks[0, 0].all() and 0 < int(peaks[1].sum()) < peaks[1].numel()


def test_every_cell_of_a_class_is_a_candidate_where_its_every_cell_says() -> None:
    """Two pedestrians in neighbouring cells (and two cars the same): with the 3x3 local maxima the weaker
    of each pair gets no box; a class whose `every_cell` is true gets both, the others still one."""
    x0, y0, cell = BEV.x_min, BEV.y_min, BEV.cell
    at = [(x0 + 40.5 * cell, y0 + 20.5 * cell), (x0 + 41.5 * cell, y0 + 20.5 * cell)]  # columns 40 and 41
    people = [
        Planted((x, y, 0.0, 0.3, 0.3, 1.7, 0.0), 1, p, 0.9) for (x, y), p in zip(at, (0.8, 0.6), strict=True)
    ]
    cars = [
        Planted((x, y + 16 * cell, 0.0, 0.3, 0.3, 1.5, 0.0), 0, p, 0.9)
        for (x, y), p in zip(at, (0.8, 0.6), strict=True)
    ]
    out = plant([people + cars], BEV)
    for every_cell, per_class in (((), (1, 1)), ((False, True, False), (1, 2)), ((True, True, True), (2, 2))):
        (det,) = decode(out, CFG, BEV, every_cell)
        assert (int((det.labels == 0).sum()), int((det.labels == 1).sum())) == per_class, every_cell
