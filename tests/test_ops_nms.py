"""The numba greedy NMS (model/ops/nms_numba.py, every CPU NMS) against its torch twin (GPU tensors),
kept index for kept index; tests/test_boxes.py holds both against an independent shapely reference. The
batch kernel (`class_nms_batch_cpu`, every CPU `select_detections`) against `class_nms` item by item
(`select_detections_plain`)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_boxes import clustered, rand_boxes

from model.config import HeadConfig
from model.geometry.boxes import Detections
from model.geometry.nms import _grouped_nms_torch
from model.layers.head import Candidates, select_detections, select_detections_plain
from model.ops.nms_numba import grouped_nms_cpu


def _both(b: np.ndarray, s: np.ndarray, groups: np.ndarray, thresholds: tuple, max_out: int, dtype):
    boxes, scores = torch.from_numpy(b).to(dtype), torch.from_numpy(s).to(dtype)
    g = torch.from_numpy(groups)
    thr = torch.tensor(thresholds, dtype=dtype)[g]
    return grouped_nms_cpu(boxes, scores, thr, g, max_out), _grouped_nms_torch(boxes, scores, thr, g, max_out)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("seed", range(6))
def test_equals_the_torch_twin_on_clustered_boxes(seed: int, dtype):
    g = np.random.default_rng(seed)
    b = clustered(g, 40, 25)  # 1,000 boxes, heavy overlaps
    s = g.uniform(size=len(b))
    s[::7] = s[0]  # ties: input order decides
    groups = g.integers(0, 3, len(b))
    for max_out in (5, 80, 1000):
        fast, twin = _both(b, s, groups, (0.75, 0.6, 0.55), max_out, dtype)
        assert fast.tolist() == twin.tolist()
    assert 40 < len(twin) < len(b)


def test_equals_the_twin_on_boxes_spread_wide_and_degenerate():
    """Boxes kilometres apart (the grid falls back to hashed cells), duplicates, zero-size boxes."""
    g = np.random.default_rng(3)
    b = np.concatenate([clustered(g, 5, 10), rand_boxes(g, 60, spread=5000.0)])
    b = np.concatenate([b, b[:20]])  # exact duplicates
    b[-5:, 3:5] = 0.0  # zero-size: IoU 0, suppress nothing
    b[3, 0], b[7, 4], b[11, 1] = np.nan, np.inf, 1e300  # non-finite and absurd: never above a threshold
    s = g.uniform(size=len(b))
    groups = np.zeros(len(b), dtype=np.int64)
    for threshold in (0.0, 0.3, 0.9):
        fast, twin = _both(b, s, groups, (threshold,), 1000, torch.float64)
        assert fast.tolist() == twin.tolist()


def test_empty_and_nothing_to_keep():
    none = torch.zeros(0, 7)
    assert (
        grouped_nms_cpu(none, torch.zeros(0), torch.zeros(0), torch.zeros(0, dtype=torch.int64), 5).numel()
        == 0
    )
    one = torch.tensor([[0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0]])
    assert (
        grouped_nms_cpu(one, torch.ones(1), torch.ones(1), torch.zeros(1, dtype=torch.int64), 0).numel() == 0
    )


def _candidates(seed: int, dtype) -> Candidates:
    """A batch of 5 items of 300 clustered candidates, as views into one wider tensor (as the graph engine
    passes them): ties, a NaN score, heat 0 (top-k ran out) and below the threshold, an item with no peak."""
    g = np.random.default_rng(seed)
    b = np.stack([clustered(g, 10, 30) for _ in range(5)])  # (5, 300, 7)
    s = g.uniform(size=b.shape[:2])
    s[:, ::9] = s[:, :1]  # ties: the earlier position first
    s[1, 5] = np.nan
    heat = g.uniform(0.0, 1.0, b.shape[:2]) * (g.uniform(size=b.shape[:2]) < 0.9)  # ~10 % zero, ~10 % < 0.1
    heat[2] = 0.0
    flat = torch.from_numpy(np.concatenate([b, s[..., None], heat[..., None]], 2)).to(dtype)  # (5, 300, 9)
    labels = torch.from_numpy(g.integers(0, 3, b.shape[:2]))
    return Candidates(flat[..., :7], flat[..., 7], labels, flat[..., 8])


def _same(a: list[Detections], b: list[Detections]) -> bool:
    """The same detections, bit for bit (the NaN score too)."""
    return all(
        torch.equal(x.boxes, y.boxes)
        and torch.allclose(x.scores, y.scores, rtol=0, atol=0, equal_nan=True)
        and torch.equal(x.labels, y.labels)
        for x, y in zip(a, b, strict=True)
    )


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", range(4))
def test_the_batch_kernel_equals_class_nms_item_by_item(seed: int, dtype) -> None:
    cand = _candidates(seed, dtype)
    for pre, post in ((1000, 1000), (20, 1000), (1000, 7), (20, 0)):  # 20: below a class's ~80 peaks
        head = HeadConfig(pre_nms_top_k=pre, post_nms_top_k=post)
        fast, twin = select_detections(cand, head), select_detections_plain(cand, head)
        assert _same(fast, twin)
        assert len(fast[2]) == 0 and (post == 0 or all(len(fast[i]) for i in (0, 1, 3, 4)))


def test_the_batch_kernel_rejects_labels_past_the_thresholds_as_class_nms_does() -> None:
    cand, head = _candidates(0, torch.float32), HeadConfig()
    cand.labels[3, 4] = 3  # no IoU threshold for class 3
    for select in (select_detections, select_detections_plain):
        with pytest.raises(ValueError, match="labels must lie in"):
            select(cand, head)
    cand.heat[3, 4] = 0.0  # not a peak: its label is never read
    assert _same(select_detections(cand, head), select_detections_plain(cand, head))
    negative = HeadConfig(nms_iou=(0.5, -0.1, 0.5))
    for select in (select_detections, select_detections_plain):
        with pytest.raises(ValueError, match="IoU thresholds must be >= 0"):
            select(cand, negative)
