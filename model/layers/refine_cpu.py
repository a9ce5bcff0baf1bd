"""The box refiner's point lookup as a CPU kernel (numba): the fast twin of `refine.box_points_torch`.

The torch version sorts every point of the turn by its 1 m cell (~120,000 points for a KITTI turn) and
gathers candidate rows as tensor ops: 10-15 ms a step on the 2-core machine. Here the points are bucketed
by a counting sort into the cells of a grid that just covers the boxes' grown outlines (points outside it
can be in no box), and each box walks the cells under its bounding rectangle, tests their points in its own
frame, sorts the ones inside into firing order and picks `p` of them evenly, as `refine._pick` does. The
result is the reference's for the same inputs up to float32 rounding of a point lying on a box's face
(tests/test_refine.py).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor


@numba.njit(cache=True, nogil=True)
def _rectangles(boxes, grow, cell, eps):  # pragma: no cover - compiled
    """boxes (B, 7) float32 -> (B, 4) int64 cells lo_x, lo_y, hi_x, hi_y of each grown box's rectangle."""
    out = np.empty((boxes.shape[0], 4), np.int64)
    for b in range(boxes.shape[0]):
        hl, hw = (boxes[b, 3] + grow[0]) / 2, (boxes[b, 4] + grow[1]) / 2
        c, s = math.cos(boxes[b, 6]), math.sin(boxes[b, 6])
        ex, ey = abs(c) * hl + abs(s) * hw, abs(s) * hl + abs(c) * hw  # half extents of the rectangle
        out[b, 0] = math.floor((boxes[b, 0] - ex - eps) / cell)
        out[b, 1] = math.floor((boxes[b, 1] - ey - eps) / cell)
        out[b, 2] = math.floor((boxes[b, 0] + ex + eps) / cell)
        out[b, 3] = math.floor((boxes[b, 1] + ey + eps) / cell)
    return out


@numba.njit(cache=True, nogil=True)
def _box_points(points, boxes, grow, p, cell, eps, local, counts):  # pragma: no cover - compiled
    """points (N, >=3) float32, boxes (B, 7) float32 -> fills local (B, p, 3) and counts (B,)."""
    rect = _rectangles(boxes, grow, cell, eps)
    x0, y0 = rect[:, 0].min(), rect[:, 1].min()
    w, h = rect[:, 2].max() - x0 + 1, rect[:, 3].max() - y0 + 1
    start = np.zeros(w * h + 1, np.int64)
    where = np.full(points.shape[0], -1, np.int64)
    for i in range(points.shape[0]):  # counting sort: points by cell, in firing order within a cell
        cx, cy = math.floor(points[i, 0] / cell) - x0, math.floor(points[i, 1] / cell) - y0
        if 0 <= cx < w and 0 <= cy < h:
            where[i] = cx * h + cy
            start[where[i] + 1] += 1
    for k in range(w * h):
        start[k + 1] += start[k]
    order = np.empty(start[w * h], np.int64)
    fill = start[:-1].copy()
    for i in range(points.shape[0]):
        if where[i] >= 0:
            order[fill[where[i]]] = i
            fill[where[i]] += 1
    found = np.empty(points.shape[0], np.int64)
    spare = np.empty(points.shape[0], np.int64)
    for b in range(boxes.shape[0]):
        c, s = np.float32(math.cos(boxes[b, 6])), np.float32(math.sin(boxes[b, 6]))
        half = (boxes[b, 3:6] + grow) / np.float32(2.0)
        n = 0
        for cx in range(rect[b, 0] - x0, rect[b, 2] - x0 + 1):
            for k in range(start[cx * h + rect[b, 1] - y0], start[cx * h + rect[b, 3] - y0 + 1]):
                i = order[k]
                dx, dy = points[i, 0] - boxes[b, 0], points[i, 1] - boxes[b, 1]
                dz = points[i, 2] - boxes[b, 2]
                u, v = c * dx + s * dy, -s * dx + c * dy
                if abs(u) <= half[0] and abs(v) <= half[1] and abs(dz) <= half[2]:
                    found[n] = i
                    n += 1
        counts[b] = n
        if n == 0:
            continue
        inside = _sorted(found[:n], spare)
        for j in range(p):
            i = inside[(j * n) // p]
            dx, dy = points[i, 0] - boxes[b, 0], points[i, 1] - boxes[b, 1]
            local[b, j, 0] = c * dx + s * dy
            local[b, j, 1] = -s * dx + c * dy
            local[b, j, 2] = points[i, 2] - boxes[b, 2]


@numba.njit(cache=True, nogil=True)
def _sorted(a, spare):  # pragma: no cover - compiled
    """a (n,) distinct non-negative int64 -> the same sorted ascending: a radix sort of 8 bits a pass (a box
    on vegetation holds thousands of points: np.sort took 2 of a KITTI turn's 3.7 ms), np.sort for a few; `a`
    and spare (>= n,) are overwritten."""
    n = a.shape[0]
    if n <= 64:
        return np.sort(a)
    src, dst = a, spare[:n]
    count = np.empty(257, np.int64)
    shift, top = 0, a.max()
    while (top >> shift) > 0:
        count[:] = 0
        for i in range(n):
            count[((src[i] >> shift) & 255) + 1] += 1
        for k in range(256):
            count[k + 1] += count[k]
        for i in range(n):
            d = (src[i] >> shift) & 255
            dst[count[d]] = src[i]
            count[d] += 1
        src, dst = dst, src
        shift += 8
    return src


def box_points_cpu(
    points: Tensor, boxes: Tensor, grow: tuple[float, float, float], p: int, cell: float, eps: float
) -> tuple[Tensor, Tensor]:
    """CPU tensors points (N, >=3), boxes (B, 7) -> (B, p, 3) box-frame points and (B,) counts."""
    b = boxes.shape[0]
    local = np.zeros((b, p, 3), np.float32)
    counts = np.zeros(b, np.int64)
    if b and points.shape[0]:
        pts = np.ascontiguousarray(points[:, :3].detach().numpy(), np.float32)
        bx = np.ascontiguousarray(boxes.detach().numpy(), np.float32)
        _box_points(pts, bx, np.asarray(grow, np.float32), p, cell, eps, local, counts)
    return torch.from_numpy(local), torch.from_numpy(counts)
