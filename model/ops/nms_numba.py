"""Greedy rotated NMS as a CPU kernel (numba): the fast twin of `model.geometry.nms._grouped_nms_torch`
(`nms._grouped_nms` dispatches), and of a batch's class-specific NMS (`model.layers.head.select_detections`
dispatches to it or to its twin, `select_detections_plain`).

The torch version finds overlapping pairs and runs the greedy pass as tensor ops: on the host that is
1.1 ms a `tiny` sector and 5 ms for the 4,096 candidates of an untrained `paper` model on the 2-core
machine (`scripts/bench_nms.py`), for every stream of a batch, after the GPU has finished. Here the
greedy pass is a plain loop in score order: a kept box looks only at the later candidates of its own
group in the 3 x 3 grid cells around it (cells as wide as the largest box's circumscribed circle, so every
pair that can intersect is seen), tests the area ratio (IoU <= smaller / larger area) and the axis-aligned
upper bound of the IoU, and only then computes the exact BEV IoU, in float64, by the same slab clipping as
`model.geometry.boxes`. The result is the torch twin's for the same inputs (the parity test), up to
rounding of IoUs within ~1e-7 of a threshold for float32 boxes.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor

_SX = (1.0, 1.0, -1.0, -1.0)  # corner signs along and across the heading, counter-clockwise
_SY = (-1.0, 1.0, 1.0, -1.0)
_CLIP = float(2**30)  # grid cell coordinates at most, either side of the origin


@numba.njit(cache=True, nogil=True)
def _clip_slab(u, v, n, half, out_u, out_v):  # pragma: no cover - compiled
    """The closed polygon (u, v)[:n] retracted onto |u| <= half (`boxes._clip_slab`): 3 n points."""
    k = 0
    for i in range(n):
        j = (i + 1) % n
        du, dv = u[j] - u[i], v[j] - v[i]
        t1 = t2 = 0.0
        if du != 0.0:
            lo, hi = (-half - u[i]) / du, (half - u[i]) / du
            t1, t2 = (lo, hi) if du > 0 else (hi, lo)
            t1, t2 = min(max(t1, 0.0), 1.0), min(max(t2, 0.0), 1.0)
        for t in (0.0, t1, t2):
            out_u[k] = min(max(u[i] + t * du, -half), half)
            out_v[k] = v[i] + t * dv
            k += 1
    return k


@numba.njit(cache=True, nogil=True)
def _iou_bev(a, b, xa, ya, xb, yb, xc, yc):  # pragma: no cover - compiled
    """BEV IoU of boxes a, b (7,) float64; xa.. are scratch arrays of 4, 12, 36 points."""
    cos_b, sin_b = math.cos(b[6]), math.sin(b[6])
    dx, dy = a[0] - b[0], a[1] - b[1]
    cx, cy = dx * cos_b + dy * sin_b, -dx * sin_b + dy * cos_b  # A's centre in B's frame
    cos_r, sin_r = math.cos(a[6] - b[6]), math.sin(a[6] - b[6])
    for i in range(4):
        lx, ly = 0.5 * a[3] * _SX[i], 0.5 * a[4] * _SY[i]
        xa[i], ya[i] = cx + cos_r * lx - sin_r * ly, cy + sin_r * lx + cos_r * ly
    n = _clip_slab(xa, ya, 4, 0.5 * b[3], xb, yb)
    n = _clip_slab(yb, xb, n, 0.5 * b[4], yc, xc)
    area = 0.0
    for i in range(n):
        j = (i + 1) % n
        area += xc[i] * yc[j] - yc[i] * xc[j]
    area *= 0.5
    area_a, area_b = a[3] * a[4], b[3] * b[4]
    if area <= 64 * 2.220446049250313e-16 * max(area_a, area_b):
        return 0.0
    union = area_a + area_b - area
    return area / union if union > 0 else 0.0


@numba.njit(cache=True, nogil=True)
def _cell(gx, gy, w, cells, hashed):  # pragma: no cover - compiled
    """The bucket of grid cell (gx, gy) >= 0: its row-major index, or a hash of it into `cells`."""
    if hashed:
        return (gx * 73856093 + gy * 19349663) % cells
    return gy * w + gx


@numba.njit(cache=True, nogil=True)
def _grid(boxes):  # pragma: no cover - compiled
    """Buckets of the boxes' grid cells (cells as wide as the largest circumscribed circle, so boxes that
    can intersect lie in neighbouring cells). Boxes with a non-finite value go in no bucket: as in the
    twin, their IoU is never above a threshold. Returns (cx, cy (N,) cell coordinates >= 1, w, cells,
    hashed, by_cell (N,) positions grouped by bucket, first (cells + 1,) CSR offsets, finite (N,))."""
    n = boxes.shape[0]
    finite = np.ones(n, dtype=np.bool_)
    rmax = 0.0
    for i in range(n):
        for c in range(7):
            finite[i] &= np.isfinite(boxes[i, c])
        if finite[i]:
            rmax = max(rmax, 0.5 * math.sqrt(boxes[i, 3] ** 2 + boxes[i, 4] ** 2))
    cell = max(2.0 * rmax, 1e-6)
    # clipped: boxes past the edge share its cell (they are neighbours of what can reach them), the cell
    # coordinates stay below 2^31 and `_cell`'s hash below 2^58 (no int64 overflow for any box)
    fx = np.where(finite, np.floor(np.clip(boxes[:, 0] / cell, -_CLIP, _CLIP)), 0.0)
    fy = np.where(finite, np.floor(np.clip(boxes[:, 1] / cell, -_CLIP, _CLIP)), 0.0)
    cx = (fx - fx.min() + 1).astype(np.int64)  # a neighbour cell of any box has coordinates >= 0
    cy = (fy - fy.min() + 1).astype(np.int64)
    hashed = (fx.max() - fx.min() + 3) * (fy.max() - fy.min() + 3) > 4 * n + 64  # spread wide: hash
    w = cx.max() + 2
    cells = 4 * n + 64 if hashed else w * (cy.max() + 2)
    key = np.empty(n, dtype=np.int64)
    for i in range(n):
        key[i] = _cell(cx[i], cy[i], w, cells, hashed) if finite[i] else cells
    by_cell = np.argsort(key, kind="mergesort")  # positions grouped by bucket, in score order inside
    first = np.searchsorted(key[by_cell], np.arange(cells + 1))
    return cx, cy, w, cells, hashed, by_cell, first, finite


@numba.njit(cache=True, nogil=True)
def _greedy(boxes, thresholds, groups, max_out):  # pragma: no cover - compiled
    """boxes (N, 7) float64 in descending score order, thresholds (N,), groups (N,) int64 -> kept
    positions (K,) int64 in that order, K <= max_out."""
    n = boxes.shape[0]
    cx, cy, w, cells, hashed, by_cell, first, finite = _grid(boxes)
    gone = np.zeros(n, dtype=np.bool_)
    kept = np.empty(min(n, max_out), dtype=np.int64)
    k = 0
    xa, ya, xb, yb = np.empty(4), np.empty(4), np.empty(12), np.empty(12)
    xc, yc = np.empty(36), np.empty(36)
    area = boxes[:, 3] * boxes[:, 4]
    cos, sin = np.abs(np.cos(boxes[:, 6])), np.abs(np.sin(boxes[:, 6]))
    hx = 0.5 * (boxes[:, 3] * cos + boxes[:, 4] * sin)  # (N,) half extents of the axis-aligned bounds
    hy = 0.5 * (boxes[:, 3] * sin + boxes[:, 4] * cos)
    for i in range(n):
        if gone[i]:
            continue
        kept[k] = i
        k += 1
        if k == max_out:
            break
        if not finite[i]:
            continue
        for ox in range(-1, 2):
            for oy in range(-1, 2):
                c = _cell(cx[i] + ox, cy[i] + oy, w, cells, hashed)  # in [0, cells): cx, cy >= 1
                for p in range(first[c], first[c + 1]):
                    j = by_cell[p]
                    if j <= i or gone[j] or groups[j] != groups[i]:
                        continue
                    small, large = min(area[i], area[j]), max(area[i], area[j])
                    if small < thresholds[i] * large:
                        continue  # IoU <= smaller / larger area
                    xi, yi, xj, yj = boxes[i, 0], boxes[i, 1], boxes[j, 0], boxes[j, 1]
                    wx = min(xi + hx[i], xj + hx[j]) - max(xi - hx[i], xj - hx[j])  # overlap of the bounds
                    wy = min(yi + hy[i], yj + hy[j]) - max(yi - hy[i], yj - hy[j])
                    bound = min(max(wx, 0.0) * max(wy, 0.0), small)  # the intersection lies inside both
                    if bound <= (thresholds[i] - 1e-4) * (area[i] + area[j] - bound):
                        continue  # the IoU's upper bound (`boxes.iou_bev_upper_bound`) is below the threshold
                    if _iou_bev(boxes[i], boxes[j], xa, ya, xb, yb, xc, yc) > thresholds[i]:
                        gone[j] = True
    return kept[:k]


def grouped_nms_cpu(
    boxes: Tensor, scores: Tensor, thresholds: Tensor, groups: Tensor, max_out: int
) -> Tensor:
    """`nms._grouped_nms_torch`'s contract on CPU tensors: kept indices (K,) by descending score."""
    if boxes.shape[0] == 0 or max_out <= 0:
        return torch.zeros(0, dtype=torch.int64)
    order = torch.argsort(scores, descending=True, stable=True)  # (N,) equal scores keep input order
    b = boxes[order].double().numpy()
    kept = _greedy(b, thresholds[order].double().numpy(), groups[order].long().numpy(), max_out)
    return order[torch.from_numpy(kept)]


@numba.njit(cache=True, nogil=True)
def _class_nms_batch(boxes, scores, labels, valid, iou, pre_k, post_k, kept, counts):  # pragma: no cover
    """`nms.class_nms` of each batch item's valid candidates. boxes (B, T, 7), scores (B, T), labels (B, T)
    int64, valid (B, T) bool, iou (C,) float64 -> fills kept (B, post_k) with each item's kept positions t
    (by descending score) and counts (B,)."""
    nb, nt = scores.shape
    nc = iou.shape[0]
    start = np.empty(nc + 1, np.int64)
    sel = np.empty(nt, np.int64)  # the valid positions, class by class, ascending inside a class
    for b in range(nb):
        start[:] = 0
        for t in range(nt):
            if valid[b, t]:
                c = labels[b, t]
                if c < 0 or c >= nc:
                    raise ValueError("labels must lie in [0, number of IoU thresholds)")
                start[c + 1] += 1
        for c in range(nc):
            start[c + 1] += start[c]
        fill = start[:-1].copy()
        for t in range(nt):
            if valid[b, t]:
                sel[fill[labels[b, t]]] = t
                fill[labels[b, t]] += 1
        n = 0
        for c in range(nc):  # each class's pre_k best (ties: the earlier position), kept in position order
            part = sel[start[c] : start[c + 1]]
            if part.shape[0] > pre_k:
                part = np.sort(part[_descending(scores[b, part])[:pre_k]])
            sel[n : n + part.shape[0]] = part
            n += part.shape[0]
        if n == 0 or post_k <= 0:
            counts[b] = 0
            continue
        cand = sel[:n][_descending(scores[b, sel[:n]])]  # by score, then class, then position
        picked = _greedy(boxes[b, cand].astype(np.float64), iou[labels[b, cand]], labels[b, cand], post_k)
        counts[b] = picked.shape[0]
        kept[b, : picked.shape[0]] = cand[picked]


@numba.njit(cache=True, nogil=True)
def _descending(x):  # pragma: no cover - compiled
    """The stable order of x (n,) by descending value, NaN first (torch's `sort(descending=True,
    stable=True)`)."""
    key = np.empty(x.shape[0], np.float64)
    for i in range(x.shape[0]):
        key[i] = -np.inf if np.isnan(x[i]) else -x[i]
    return np.argsort(key, kind="mergesort")


def class_nms_batch_cpu(
    boxes: Tensor,
    scores: Tensor,
    labels: Tensor,
    valid: Tensor,
    iou_thresholds: tuple[float, ...],
    pre_top_k: int,
    post_top_k: int,
) -> tuple[Tensor, Tensor]:
    """`nms.class_nms` of each batch item's valid candidates in one kernel call: CPU tensors boxes (B, T, 7),
    scores (B, T), labels (B, T) int64, valid (B, T) bool -> kept (K,) int64 flat indices into B * T (item
    by item, each by descending score) and counts (B,) int64. Item by item, `class_nms` (its twin, in
    `head.select_detections_plain`) spent most of its time in the small tensor ops around each item's NMS."""
    if any(not t >= 0.0 for t in iou_thresholds):
        raise ValueError(f"IoU thresholds must be >= 0, got {tuple(iou_thresholds)}")
    nb, nt = scores.shape
    kept = np.zeros((nb, max(min(post_top_k, nt), 0)), np.int64)
    counts = np.zeros(nb, np.int64)
    _class_nms_batch(  # C-contiguous arrays: the layout the warm-up compiles for (`compile_kernels`)
        np.ascontiguousarray(boxes.detach().numpy()),
        np.ascontiguousarray(scores.detach().numpy()),
        np.ascontiguousarray(labels.long().numpy()),
        np.ascontiguousarray(valid.numpy()),
        np.asarray(iou_thresholds, np.float64),
        pre_top_k,
        post_top_k,
        kept,
        counts,
    )
    rows = np.arange(kept.shape[1]) < counts[:, None]  # (B, post_k) the filled part of each row
    flat = (kept + nt * np.arange(nb)[:, None])[rows]
    return torch.from_numpy(flat), torch.from_numpy(counts)


def compile_kernels() -> None:
    """Compile the kernels now (numba compiles at first call, or loads them from its cache beside this file):
    two-box calls. A server calls this in its warm-up: NMS first runs on the first sector with a candidate
    above the score threshold, and the compile (5-15 s on a loaded 2-core machine, once per install) would
    land on that request."""
    boxes = torch.tensor([[0.0, 0, 0, 4, 2, 1.5, 0], [0.5, 0, 0, 4, 2, 1.5, 0.1]])  # (2, 7)
    scores, labels = torch.tensor([0.9, 0.8]), torch.zeros(2, dtype=torch.int64)
    grouped_nms_cpu(boxes, scores, torch.tensor([0.5, 0.5]), labels, 2)
    valid = torch.ones(1, 2, dtype=torch.bool)
    class_nms_batch_cpu(boxes[None], scores[None], labels[None], valid, (0.5,), 2, 2)  # float32, as served
