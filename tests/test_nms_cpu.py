"""The numba greedy NMS (model/geometry/nms_cpu.py, every CPU NMS) against its torch twin (GPU tensors),
kept index for kept index; tests/test_boxes.py holds both against an independent shapely reference."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_boxes import clustered, rand_boxes

from model.geometry.nms import _grouped_nms_torch
from model.geometry.nms_cpu import grouped_nms_cpu


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
