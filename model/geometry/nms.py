"""Greedy rotated non-maximum suppression on BEV IoU, and its class-specific form (as OpenPCDet's
class-specific NMS for Waymo: one IoU threshold per class, classes never suppress each other).

A box is suppressed when its BEV IoU with a kept box of higher score is strictly greater than the threshold.
The IoU is computed once, only for the pairs that can exceed the threshold (circumscribed circles overlap,
area ratio and an axis-aligned upper bound of the IoU above it); the greedy pass itself is tensor ops on the
boolean overlap matrix.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from model.geometry.boxes import iou_bev_upper_bound, near_pairs, rotated_iou_bev_aligned
from model.ops.nms_numba import grouped_nms_cpu
from model.ops.numba_support import numba_kernel

_BOUND_SLACK = 1e-4  # pairs within this of the threshold by the upper bound get the exact IoU
_PREFIX = 2  # first try NMS on the best _PREFIX x max_out candidates only
_BLOCK = 64  # candidates resolved together in the greedy pass (small: cheap, unthreaded ops)


def _overlap_matrix(boxes: Tensor, thresholds: Tensor, groups: Tensor) -> Tensor:
    """(N, 7) boxes in descending score order, (N,) IoU threshold and (N,) group of each box -> (N, N) bool,
    [i, j] = i < j, same group and IoU(i, j) > thresholds[i] (boxes of one group share a threshold)."""
    n = boxes.shape[0]
    area = boxes[:, 3] * boxes[:, 4]  # (N,)
    over = torch.zeros(n, n, dtype=torch.bool, device=boxes.device)
    for ia, ib in near_pairs(boxes):  # (P,), (P,) with ia < ib
        threshold = thresholds[ia]  # (P,)
        # IoU <= min(area) / max(area): boxes of very different size cannot exceed the threshold
        small, large = torch.minimum(area[ia], area[ib]), torch.maximum(area[ia], area[ib])
        fit = (groups[ia] == groups[ib]) & (small >= threshold * large)
        ia, ib, threshold = ia[fit], ib[fit], threshold[fit]
        # the exact IoU only where a cheap upper bound leaves it possible (slack for float rounding)
        fit = iou_bev_upper_bound(boxes[ia], boxes[ib]) > threshold - _BOUND_SLACK
        ia, ib, threshold = ia[fit], ib[fit], threshold[fit]
        hit = rotated_iou_bev_aligned(boxes[ia], boxes[ib]) > threshold  # (P',)
        over[ia[hit], ib[hit]] = True
    return over


def _greedy_keep(over: Tensor, max_out: int) -> Tensor:
    """Greedy selection on a strictly upper-triangular overlap matrix (N, N) bool -> keep (N,) bool.

    keep[i] = not any(keep[j] and over[j, i] for j < i). Candidates are resolved in blocks: first the kept
    boxes of earlier blocks suppress, then inside the block the rule is iterated to its fixed point, which
    is unique and is reached after at most (longest suppression chain + 1) iterations.
    """
    n = over.shape[0]
    keep = torch.zeros(n, dtype=torch.bool, device=over.device)
    for s in range(0, n, _BLOCK):
        e = min(n, s + _BLOCK)
        alive = ~(keep[:s, None] & over[:s, s:e]).any(dim=0)  # (E,) not suppressed by earlier blocks
        inner = over[s:e, s:e]  # (E, E)
        cur = alive
        for _ in range(e - s + 1):
            nxt = alive & ~(cur[:, None] & inner).any(dim=0)  # (E,)
            if torch.equal(nxt, cur):
                break
            cur = nxt
        keep[s:e] = cur
        if int(keep[:e].sum()) >= max_out:  # later candidates cannot change the first max_out kept
            break
    return keep


def nms_rotated(boxes: Tensor, scores: Tensor, iou_threshold: float, max_out: int) -> Tensor:
    """Greedy NMS with BEV rotated IoU.

    boxes (N, 7), scores (N,) -> kept indices into boxes (K,) int64, by descending score, K <= max_out.
    A box goes when its IoU with a kept better box is > iou_threshold (>= 0). Equal scores keep input order.
    """
    if boxes.ndim != 2 or boxes.shape[1] != 7 or scores.shape != boxes.shape[:1]:
        raise ValueError(f"need boxes (N, 7), scores (N,); got {tuple(boxes.shape)}, {tuple(scores.shape)}")
    if not iou_threshold >= 0.0:  # also rejects NaN
        raise ValueError(f"iou_threshold must be >= 0, got {iou_threshold}")
    n, dev = boxes.shape[0], boxes.device
    thresholds = torch.full((n,), iou_threshold, dtype=boxes.dtype, device=dev)
    return _grouped_nms(boxes, scores, thresholds, torch.zeros(n, dtype=torch.int64, device=dev), max_out)


def _grouped_nms(
    boxes: Tensor, scores: Tensor, thresholds: Tensor, groups: Tensor, max_out: int, fast: bool | None = None
) -> Tensor:
    """Greedy NMS in which boxes only suppress boxes of their own group: the numba kernel
    (`model.ops.nms_numba`) or `_grouped_nms_torch`, its reference twin, as `fast` says (`numba_kernel`)."""
    if numba_kernel("grouped_nms", boxes.device, fast):
        return grouped_nms_cpu(boxes.detach(), scores.detach(), thresholds, groups, max_out)
    return _grouped_nms_torch(boxes, scores, thresholds, groups, max_out)


def _grouped_nms_torch(
    boxes: Tensor, scores: Tensor, thresholds: Tensor, groups: Tensor, max_out: int
) -> Tensor:
    """Greedy NMS in which boxes only suppress boxes of their own group, all groups in one pass.

    boxes (N, 7), scores, thresholds, groups (N,) -> kept indices (K,) by descending score, K <= max_out.
    Groups never interact, so the first max_out kept in score order are the best max_out of the union of
    the groups' own NMS results.
    """
    if boxes.shape[0] == 0 or max_out <= 0:
        return torch.zeros(0, dtype=torch.int64, device=boxes.device)
    order = torch.argsort(scores, descending=True, stable=True)  # (N,)
    n = order.shape[0]

    def keep_of(m: int) -> Tensor:  # greedy NMS of the best m candidates -> (m,) bool
        head = order[:m]
        return _greedy_keep(_overlap_matrix(boxes[head], thresholds[head], groups[head]), max_out)

    # greedy decisions on a score-ordered prefix do not depend on what follows it: when the best
    # _PREFIX x max_out candidates already keep max_out boxes, the rest need no overlap test at all
    m = min(n, _PREFIX * max_out)
    keep = keep_of(m)
    if m < n and int(keep.sum()) < max_out:
        m, keep = n, keep_of(n)
    return order[:m][keep][:max_out]


def class_nms(
    boxes: Tensor,
    scores: Tensor,
    labels: Tensor,
    iou_thresholds: Sequence[float],
    pre_top_k: int,
    post_top_k: int,
) -> Tensor:
    """Class-specific NMS: per class c, keep its pre_top_k best boxes, run NMS with iou_thresholds[c]; then
    keep the post_top_k best of all classes. All classes go through one grouped pass (the classes are the
    groups), which gives the same result as one NMS per class and a merge.

    boxes (N, 7), scores (N,), labels (N,) int64 in [0, len(iou_thresholds)) -> kept indices (K,) int64,
    by descending score.
    """
    if labels.shape != scores.shape:
        raise ValueError(f"labels {tuple(labels.shape)} and scores {tuple(scores.shape)} differ")
    if labels.numel() == 0:
        return torch.zeros(0, dtype=torch.int64, device=boxes.device)
    if int(labels.min()) < 0 or int(labels.max()) >= len(iou_thresholds):
        raise ValueError(f"labels must lie in [0, {len(iou_thresholds)}), one IoU threshold per class")
    if any(not t >= 0.0 for t in iou_thresholds):
        raise ValueError(f"IoU thresholds must be >= 0, got {tuple(iou_thresholds)}")
    parts = []
    for c in range(len(iou_thresholds)):
        idx = (labels == c).nonzero(as_tuple=True)[0]  # (Nc,)
        if idx.numel() > pre_top_k:  # the best pre_top_k; among equal scores the earlier ones
            idx = idx[torch.sort(scores[idx], descending=True, stable=True).indices[:pre_top_k]]
        parts.append(idx)
    cand = torch.cat(parts)  # (N',) class by class
    thresholds = torch.tensor(iou_thresholds, dtype=boxes.dtype, device=boxes.device)[labels[cand]]
    return cand[_grouped_nms(boxes[cand], scores[cand], thresholds, labels[cand], post_top_k)]
