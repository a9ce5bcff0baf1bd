"""The box refiner's point lookup as a CPU kernel (numba): the fast twin of
`model.layers.refine.box_points_torch` (`refine.box_points` dispatches).

The torch version sorts every point of the turn by its 1 m cell (~120,000 points for a KITTI turn) and
gathers candidate rows as tensor ops: 10-15 ms a step on the 2-core machine. Here the points are bucketed
by a counting sort into the cells of a grid that just covers the boxes' outlines (points outside it can
be in no box), and each box walks the cells under its bounding rectangle, tests their points in its own
frame, sorts the ones inside into firing order and picks `p` of them evenly, as `refine._pick` does. The
result is the reference's for the same inputs up to float32 rounding of a point lying on a box's face
(tests/test_refine.py).

Safe for any input values (tests/test_extremes.py): a coordinate is tested against the grid's bounds as a
float before it becomes a cell index, every index is clamped into the grid, the grid has at most MAX_SIDE
cells a side (its cells grow where the boxes spread wider) and NaN values match nothing. A point at
x = -1e30 once overflowed its int64 cell index, and the kernel wrote outside its buffers (issue 51).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor

# the grid's cells along a side at most: where the boxes spread wider (only boxes far outside a sensor's
# range), the cells grow by powers of two: that changes the candidates a box tests, not its result
MAX_SIDE = 512
SLACK = 1e-6  # a rectangle's relative margin: float32 rounding of the box-frame test, far from the origin
REACH = 1e39  # metres: past every finite float32, the grid's bounds where a rectangle is unbounded


@numba.njit(cache=True, nogil=True)
def _rectangles(boxes, eps):  # pragma: no cover - compiled
    """boxes (B, 7) float32 -> (B, 4) float64 lo_x, lo_y, hi_x, hi_y: each box's bounding rectangle
    in metres, widened by eps and SLACK of its half sides; a NaN bound (a NaN or inf box) is unbounded."""
    out = np.empty((boxes.shape[0], 4), np.float64)
    for b in range(boxes.shape[0]):
        hl, hw = np.float64(boxes[b, 3]) / 2, np.float64(boxes[b, 4]) / 2
        c, s = abs(math.cos(np.float64(boxes[b, 6]))), abs(math.sin(np.float64(boxes[b, 6])))
        ex, ey = c * hl + s * hw, s * hl + c * hw  # half sides of the rectangle
        ex, ey = ex * (1 + SLACK) + eps, ey * (1 + SLACK) + eps
        x, y = np.float64(boxes[b, 0]), np.float64(boxes[b, 1])
        for k, v in enumerate((x - ex, y - ey, x + ex, y + ey)):
            out[b, k] = v if not math.isnan(v) else (-math.inf if k < 2 else math.inf)
    return out


@numba.njit(cache=True, nogil=True)
def grid_cells(lo_x, lo_y, hi_x, hi_y, cell):  # pragma: no cover - compiled
    """The grid over the region [lo, hi] (finite float64 metres, lo <= hi): (cell, w, h) with cells of
    `cell` metres, doubled until neither side has more than MAX_SIDE of them."""
    while (hi_x - lo_x) / cell >= MAX_SIDE or (hi_y - lo_y) / cell >= MAX_SIDE:
        cell *= 2.0
    return cell, int((hi_x - lo_x) / cell) + 1, int((hi_y - lo_y) / cell) + 1


@numba.njit(cache=True, nogil=True)
def _index(v, origin, cell, n):  # pragma: no cover - compiled
    """The cell in [0, n) holding coordinate v (float64, +-inf allowed) of a grid from `origin`, clamped: the
    float is bounded before it becomes an integer."""
    t = (v - origin) / cell
    if not t >= 0.0:
        return 0
    if t >= n - 1:
        return n - 1
    return int(t)


@numba.njit(cache=True, nogil=True)
def _box_points(points, boxes, p, cell, eps, local, counts):  # pragma: no cover - compiled
    """points (N, >=3) float32, boxes (B, 7) float32 -> fills local (B, p, 3) and counts (B,) (zeros)."""
    rect = _rectangles(boxes, eps)
    x0, y0 = max(rect[:, 0].min(), -REACH), max(rect[:, 1].min(), -REACH)  # the rectangles' span, finite
    x1, y1 = min(rect[:, 2].max(), REACH), min(rect[:, 3].max(), REACH)
    if not (x0 <= x1 and y0 <= y1):
        return  # no rectangle holds a finite point
    cell, w, h = grid_cells(x0, y0, x1, y1, cell)
    start = np.zeros(w * h + 1, np.int64)
    where = np.full(points.shape[0], -1, np.int64)
    for i in range(points.shape[0]):  # counting sort: points by cell, in firing order within a cell
        x, y = np.float64(points[i, 0]), np.float64(points[i, 1])
        if x0 <= x <= x1 and y0 <= y <= y1:  # False for NaN: the test is on the float, before any integer
            where[i] = _index(x, x0, cell, w) * h + _index(y, y0, cell, h)
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
        half = boxes[b, 3:6] / np.float32(2.0)
        n = 0
        lo_y, hi_y = _index(rect[b, 1], y0, cell, h), _index(rect[b, 3], y0, cell, h)
        for cx in range(_index(rect[b, 0], x0, cell, w), _index(rect[b, 2], x0, cell, w) + 1):
            for k in range(start[cx * h + lo_y], start[cx * h + hi_y + 1]):
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


def box_points_cpu(points: Tensor, boxes: Tensor, p: int, cell: float, eps: float) -> tuple[Tensor, Tensor]:
    """CPU tensors points (N, >=3), boxes (B, 7) -> (B, p, 3) box-frame points and (B,) counts."""
    b = boxes.shape[0]
    local = np.zeros((b, p, 3), np.float32)
    counts = np.zeros(b, np.int64)
    if b and points.shape[0]:
        pts = np.ascontiguousarray(points[:, :3].detach().numpy(), np.float32)
        bx = np.ascontiguousarray(boxes.detach().numpy(), np.float32)
        _box_points(pts, bx, p, cell, eps, local, counts)
    return torch.from_numpy(local), torch.from_numpy(counts)
