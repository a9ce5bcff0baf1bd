"""Rotated IoU and rotated NMS against an independent shapely reference."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest
import shapely
import torch

import model.geometry.boxes as boxes_mod
from model.geometry.boxes import (
    Detections,
    box_corners_bev,
    iou_bev_upper_bound,
    near_pairs,
    rotated_iou_3d,
    rotated_iou_3d_aligned,
    rotated_iou_bev,
    rotated_iou_bev_aligned,
)
from model.geometry.nms import class_nms, nms_rotated

# ----------------------------------------------------------------------------------------- reference


def ref_polygons(b: np.ndarray) -> np.ndarray:
    """(N, 7) boxes -> (N,) shapely polygons, corners written out independently of model.boxes."""
    out = []
    for x, y, _, length, w, _, yaw in b:
        c, s = math.cos(yaw), math.sin(yaw)
        hl = length / 2
        local = [(hl, -w / 2), (hl, w / 2), (-hl, w / 2), (-hl, -w / 2)]
        out.append(shapely.Polygon([(x + c * u - s * v, y + s * u + c * v) for u, v in local]))
    return np.array(out, dtype=object)


def ref_iou_pairs(a: np.ndarray, b: np.ndarray, three_d: bool = False) -> np.ndarray:
    """Aligned IoU of a[i], b[i] with shapely: (N, 7), (N, 7) -> (N,) float64."""
    inter = shapely.area(shapely.intersection(ref_polygons(a), ref_polygons(b)))
    area_a, area_b = a[:, 3] * a[:, 4], b[:, 3] * b[:, 4]
    if three_d:
        top = np.minimum(a[:, 2] + a[:, 5] / 2, b[:, 2] + b[:, 5] / 2)
        bottom = np.maximum(a[:, 2] - a[:, 5] / 2, b[:, 2] - b[:, 5] / 2)
        inter = inter * np.clip(top - bottom, 0, None)
        area_a, area_b = area_a * a[:, 5], area_b * b[:, 5]
    union = area_a + area_b - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1), 0.0)


def ref_iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, 7), (M, 7) -> (N, M) BEV IoU; shapely only where the circumscribed circles meet (else it is 0)."""
    reach = (np.hypot(a[:, 3], a[:, 4])[:, None] + np.hypot(b[:, 3], b[:, 4])[None, :]) / 2
    i, j = np.nonzero(np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1]) < reach)
    out = np.zeros((len(a), len(b)))
    out[i, j] = ref_iou_pairs(a[i], b[j])
    return out


def ref_greedy_nms(b: np.ndarray, scores: np.ndarray, threshold: float) -> list[int]:
    iou = ref_iou_matrix(b, b)
    kept: list[int] = []
    for i in np.argsort(-scores, kind="stable"):
        if all(iou[i, k] <= threshold for k in kept):
            kept.append(int(i))
    return kept


# ----------------------------------------------------------------------------------------- box pairs


def rand_boxes(g: np.random.Generator, n: int, spread: float = 3.0) -> np.ndarray:
    b = np.empty((n, 7))
    b[:, :2] = g.uniform(-spread, spread, (n, 2))
    b[:, 2] = g.uniform(-1, 1, n)
    b[:, 3:6] = g.uniform(0.3, 5.0, (n, 3))
    b[:, 6] = g.uniform(-math.pi, math.pi, n)
    return b


def box_pairs() -> tuple[np.ndarray, np.ndarray]:
    """A few hundred aligned pairs: generic, nested, disjoint, identical, touching, parallel, far away."""
    g = np.random.default_rng(0)
    pairs = [(rand_boxes(g, 200), rand_boxes(g, 200))]  # generic, about half overlapping
    outer = rand_boxes(g, 30)  # nested: a small box inside a big one, any rotation
    outer[:, 3:5] = g.uniform(4.0, 6.0, (30, 2))
    inner = outer.copy()
    inner[:, 3:5] = g.uniform(0.2, 1.0, (30, 2))
    inner[:, :2] += g.uniform(-0.5, 0.5, (30, 2))
    inner[:, 6] = g.uniform(-math.pi, math.pi, 30)
    pairs += [(outer, inner), (inner, outer)]
    far = rand_boxes(g, 20)  # disjoint
    far[:, 0] += 30.0
    pairs.append((rand_boxes(g, 20), far))
    same = rand_boxes(g, 20)  # identical, and the same box turned by pi (same footprint)
    turned = same.copy()
    turned[:, 6] += math.pi
    pairs += [(same, same.copy()), (same, turned)]
    touch = rand_boxes(g, 20)  # sharing a full edge: shifted by its length along the heading
    shifted = touch.copy()
    shifted[:, 0] += touch[:, 3] * np.cos(touch[:, 6])
    shifted[:, 1] += touch[:, 3] * np.sin(touch[:, 6])
    pairs.append((touch, shifted))
    par = rand_boxes(g, 20)  # parallel, partly overlapping (collinear edges possible)
    par_b = par.copy()
    par_b[:, 0] += 0.5 * par[:, 3] * np.cos(par[:, 6])
    par_b[:, 1] += 0.5 * par[:, 3] * np.sin(par[:, 6])
    par_b[:, 4] = par[:, 4] * np.array([1.0, 0.5] * 10)
    pairs.append((par, par_b))
    a = np.concatenate([p[0] for p in pairs])
    b = np.concatenate([p[1] for p in pairs])
    offset = np.zeros(7)
    offset[:2] = (61.3, -70.7)  # the same pairs far from the origin: float32 must stay accurate
    return np.concatenate([a, a + offset]), np.concatenate([b, b + offset])


# ----------------------------------------------------------------------------------------- IoU


def test_corners_counter_clockwise() -> None:
    b = torch.tensor([[1.0, 2.0, 0.0, 4.0, 2.0, 1.0, math.pi / 2]])
    c = box_corners_bev(b)[0]
    torch.testing.assert_close(c, torch.tensor([[2.0, 4.0], [0.0, 4.0], [0.0, 0.0], [2.0, 0.0]]))
    boxes = torch.from_numpy(rand_boxes(np.random.default_rng(1), 50))
    c = box_corners_bev(boxes)
    x, y = c[..., 0], c[..., 1]
    signed = 0.5 * (x * y.roll(-1, 1) - y * x.roll(-1, 1)).sum(1)  # shoelace: > 0 iff counter-clockwise
    torch.testing.assert_close(signed, boxes[:, 3] * boxes[:, 4])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("three_d", [False, True])
def test_iou_matches_shapely(dtype: torch.dtype, three_d: bool) -> None:
    a, b = box_pairs()
    expected = torch.from_numpy(ref_iou_pairs(a, b, three_d)).to(dtype)
    ta, tb = torch.from_numpy(a).to(dtype), torch.from_numpy(b).to(dtype)
    aligned = (rotated_iou_3d_aligned if three_d else rotated_iou_bev_aligned)(ta, tb)
    tol = 1e-10 if dtype == torch.float64 else 1e-4
    assert aligned.dtype == dtype
    torch.testing.assert_close(aligned, expected, rtol=tol, atol=tol)
    assert (expected > 0.05).sum() > 150 and (expected == 0).sum() > 60  # the set really mixes both
    assert (aligned[expected == 0] == 0).all()  # disjoint and touching: exactly 0
    # all pairs of a subset, against aligned IoU of the same pairs
    sub = np.arange(0, len(a), 17)
    full = (rotated_iou_3d if three_d else rotated_iou_bev)(ta[sub], tb[sub])  # (S, S)
    i, j = np.meshgrid(sub, sub, indexing="ij")
    pairs = (rotated_iou_3d_aligned if three_d else rotated_iou_bev_aligned)(ta[i.ravel()], tb[j.ravel()])
    torch.testing.assert_close(full, pairs.reshape(full.shape), rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(torch.diagonal(full), expected[sub], rtol=tol, atol=tol)


def test_iou_symmetric_and_self_one() -> None:
    boxes = torch.from_numpy(rand_boxes(np.random.default_rng(2), 60)).float()
    iou = rotated_iou_bev(boxes, boxes)
    torch.testing.assert_close(iou, iou.T, rtol=0, atol=1e-6)
    torch.testing.assert_close(torch.diagonal(iou), torch.ones(60), rtol=0, atol=1e-5)
    iou3 = rotated_iou_3d(boxes, boxes)
    torch.testing.assert_close(torch.diagonal(iou3), torch.ones(60), rtol=0, atol=1e-5)
    assert ((iou >= 0) & (iou <= 1 + 1e-6)).all()


def test_degenerate_boxes_give_zero_not_nan() -> None:
    b = torch.tensor(
        [
            [0.0, 0.0, 0.0, 0.0, 2.0, 1.0, 0.3],  # zero length
            [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],  # a point
            [0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.3],
        ]
    )
    for fn in (rotated_iou_bev, rotated_iou_3d):
        iou = fn(b, b)
        assert torch.isfinite(iou).all()
        torch.testing.assert_close(iou, torch.diag(torch.tensor([0.0, 0.0, 1.0])))
    flat = b[2:].clone()
    flat[:, 5] = 0.0  # zero height: 3D IoU 0, BEV IoU unaffected
    assert rotated_iou_3d(flat, flat).item() == 0.0
    assert rotated_iou_bev(flat, flat).item() == pytest.approx(1.0)


def test_empty_inputs() -> None:
    b = torch.zeros(0, 7)
    assert rotated_iou_bev(b, torch.ones(3, 7)).shape == (0, 3)
    assert rotated_iou_3d(torch.ones(3, 7), b).shape == (3, 0)
    assert rotated_iou_bev_aligned(b, b).shape == (0,)
    assert len(Detections.empty()) == 0


def test_blocked_equals_unblocked(monkeypatch: pytest.MonkeyPatch) -> None:
    boxes = torch.from_numpy(rand_boxes(np.random.default_rng(3), 90)).float()
    whole = rotated_iou_bev(boxes, boxes)
    monkeypatch.setattr(boxes_mod, "_PAIR_CHUNK", 70)  # smaller than one row's candidates: rows go alone
    torch.testing.assert_close(rotated_iou_bev(boxes, boxes), whole, rtol=0, atol=0)
    torch.testing.assert_close(rotated_iou_bev_aligned(boxes, boxes.flip(0)), torch.diagonal(whole.flip(1)))


@pytest.mark.parametrize("chunk", [1 << 16, 50])
def test_near_pairs_is_the_circle_test(monkeypatch: pytest.MonkeyPatch, chunk: int) -> None:
    monkeypatch.setattr(boxes_mod, "_PAIR_CHUNK", chunk)
    g = np.random.default_rng(4)
    a, b = rand_boxes(g, 70, spread=12.0), rand_boxes(g, 50, spread=12.0)

    def brute(a: np.ndarray, b: np.ndarray) -> list[tuple[int, int]]:
        reach = (np.hypot(a[:, 3], a[:, 4])[:, None] + np.hypot(b[:, 3], b[:, 4])[None, :]) / 2
        close = np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1]) < reach  # (N, M)
        return sorted((int(i), int(j)) for i, j in zip(*np.nonzero(close), strict=True))

    def pairs(chunks: Iterator[tuple[torch.Tensor, torch.Tensor]]) -> list[tuple[int, int]]:
        return sorted((int(i), int(j)) for ia, ib in chunks for i, j in zip(ia, ib, strict=True))

    got = pairs(near_pairs(torch.from_numpy(a), torch.from_numpy(b)))
    assert got == brute(a, b) and 100 < len(got) < 70 * 50
    assert pairs(near_pairs(torch.from_numpy(a))) == [(i, j) for i, j in brute(a, a) if i < j]


def test_iou_upper_bound_bounds_and_is_tight_when_axis_aligned() -> None:
    g = np.random.default_rng(11)
    a = rand_boxes(g, 400, spread=3.0)
    b = a + np.concatenate([g.normal(0, 0.5, (400, 2)), np.zeros((400, 4)), g.normal(0, 0.5, (400, 1))], 1)
    exact = ref_iou_pairs(a, b)
    bound = iou_bev_upper_bound(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    assert (bound >= exact - 1e-9).all() and (exact > 0.3).sum() > 50
    aligned = a.copy()
    aligned[:, 6] = 0.0
    shifted = aligned.copy()
    shifted[:, 0] += g.uniform(-1, 1, 400)
    got = iou_bev_upper_bound(torch.from_numpy(aligned), torch.from_numpy(shifted)).numpy()
    np.testing.assert_allclose(got, ref_iou_pairs(aligned, shifted), rtol=0, atol=1e-9)


def test_aligned_iou_gradient() -> None:
    a = torch.tensor([[0.1, 0.2, 0.0, 4.0, 2.0, 1.5, 0.3]], dtype=torch.float64, requires_grad=True)
    b = torch.tensor([[0.9, -0.4, 0.3, 3.5, 1.8, 1.2, -0.2]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(rotated_iou_bev_aligned, (a, b))
    assert torch.autograd.gradcheck(rotated_iou_3d_aligned, (a, b))


# ----------------------------------------------------------------------------------------- NMS


def clustered(g: np.random.Generator, clusters: int, per: int) -> np.ndarray:
    centres = rand_boxes(g, clusters, spread=20.0)
    out = np.repeat(centres, per, axis=0)
    n = len(out)
    out[:, :2] += g.normal(0, 0.4, (n, 2))
    out[:, 3:6] *= g.uniform(0.8, 1.2, (n, 3))
    out[:, 6] += g.normal(0, 0.2, n) + math.pi * (g.uniform(size=n) < 0.1)
    return out


@pytest.mark.parametrize("threshold", [0.1, 0.5, 0.75])
def test_nms_matches_reference(threshold: float) -> None:
    g = np.random.default_rng(int(threshold * 100))
    b = clustered(g, 12, 15)
    s = g.uniform(size=len(b))
    expected = ref_greedy_nms(b, s, threshold)
    kept = nms_rotated(torch.from_numpy(b), torch.from_numpy(s), threshold, max_out=1000)
    assert kept.tolist() == expected
    assert 12 < len(expected) < len(b)  # suppression happened, and not everything went
    kept = nms_rotated(torch.from_numpy(b).float(), torch.from_numpy(s).float(), threshold, max_out=5)
    assert kept.tolist() == expected[:5]


@pytest.mark.parametrize("threshold", [0.1, 0.75])
@pytest.mark.parametrize("max_out", [1, 4, 12, 60])
def test_nms_max_out_equals_truncated_full_nms(threshold: float, max_out: int) -> None:
    """NMS first tries the best 2 x max_out candidates alone: here enough, or (0.1, max_out >= 12) not."""
    g = np.random.default_rng(max_out)
    b = clustered(g, 12, 15)
    s = g.uniform(size=len(b))
    expected = ref_greedy_nms(b, s, threshold)
    kept = nms_rotated(torch.from_numpy(b), torch.from_numpy(s), threshold, max_out=max_out)
    assert kept.tolist() == expected[:max_out]


def test_nms_long_chain_across_blocks() -> None:
    """A row of boxes each overlapping the next: greedy keeps every other one; chains cross block borders."""
    n = 300
    b = np.zeros((n, 7))
    b[:, 0] = np.arange(n) * 0.5
    b[:, 3:6] = (1.0, 1.0, 1.0)
    s = np.linspace(1.0, 0.1, n)
    kept = nms_rotated(torch.from_numpy(b), torch.from_numpy(s), 0.2, max_out=n)
    assert kept.tolist() == list(range(0, n, 2))


def test_class_nms_classes_independent_and_thresholds() -> None:
    base = np.array([[0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0]])
    shifted = base.copy()
    shifted[0, 0] = 4.0 * (1 - 0.65) / (1 + 0.65)  # same size shifted along l by d: IoU = (l - d) / (l + d)
    assert ref_iou_pairs(base, shifted)[0] == pytest.approx(0.65)
    b = np.concatenate([base, shifted] * 3)  # pairs of classes 0, 1, 2
    labels = torch.tensor([0, 0, 1, 1, 2, 2])
    s = torch.tensor([0.9, 0.8, 0.7, 0.6, 0.5, 0.4])
    thresholds = (0.75, 0.6, 0.55)  # 0.65 exceeds only the pedestrian and cyclist thresholds
    kept = class_nms(torch.from_numpy(b).float(), s, labels, thresholds, 100, 100)
    assert kept.tolist() == [0, 1, 2, 4]
    same = torch.from_numpy(np.concatenate([base] * 3)).float()  # identical boxes, different classes
    kept = class_nms(same, s[:3], torch.tensor([2, 0, 1]), thresholds, 100, 100)
    assert kept.tolist() == [0, 1, 2]


def test_class_nms_matches_reference_and_top_k() -> None:
    g = np.random.default_rng(7)
    b = clustered(g, 10, 12)
    s = g.uniform(size=len(b))
    labels = g.integers(0, 3, len(b))
    thresholds = (0.3, 0.5, 0.2)
    kept = class_nms(torch.from_numpy(b), torch.from_numpy(s), torch.from_numpy(labels), thresholds, 25, 1000)
    expected = []
    for c in range(3):
        idx = np.nonzero(labels == c)[0]
        idx = idx[np.argsort(-s[idx], kind="stable")[:25]]  # pre_top_k per class
        expected += [int(idx[k]) for k in ref_greedy_nms(b[idx], s[idx], thresholds[c])]
    expected.sort(key=lambda i: -s[i])
    assert kept.tolist() == expected
    kept = class_nms(torch.from_numpy(b), torch.from_numpy(s), torch.from_numpy(labels), thresholds, 25, 10)
    assert kept.tolist() == expected[:10]
    none = torch.zeros(0, dtype=torch.int64)
    assert class_nms(torch.zeros(0, 7), torch.zeros(0), none, thresholds, 5, 5).numel() == 0
