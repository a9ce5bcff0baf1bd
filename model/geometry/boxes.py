"""3D boxes: the detection result type and rotated IoU (bird's-eye view and 3D), in plain PyTorch.

Box convention: (x, y, z, l, w, h, yaw) in the LiDAR frame (x forward, y left, z up); z is the box centre,
l is measured along the heading, yaw is counter-clockwise from +x in radians.

BEV intersection of two rotated rectangles: in B's frame B is an axis-aligned rectangle, so A's outline is
clipped against two slabs (|x| <= l_b / 2, then |y| <= w_b / 2) by clamping, with the slab-border crossings
inserted; the shoelace formula then gives the area (see `_clip_slab`). Every step is a tensor op over all
pairs at once (no Python loop over pairs, no sorting), so it runs on CPU and CUDA and is differentiable with
respect to the boxes.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Protocol

import torch
from torch import Tensor

_PAIR_CHUNK = 1 << 16  # box pairs per chunk (candidates of the pre-test, then polygon clipping)


@dataclass
class Detections:
    """Detected boxes of one batch item (one sector or one scan)."""

    boxes: Tensor  # (K, 7) float32: x, y, z, l, w, h, yaw
    scores: Tensor  # (K,) float32
    labels: Tensor  # (K,) int64, index into HeadConfig.class_names

    def to(self, device: torch.device | str) -> Detections:
        return Detections(self.boxes.to(device), self.scores.to(device), self.labels.to(device))

    @staticmethod
    def empty(device: torch.device | str = "cpu") -> Detections:
        return Detections(
            torch.zeros(0, 7, dtype=torch.float32, device=device),
            torch.zeros(0, dtype=torch.float32, device=device),
            torch.zeros(0, dtype=torch.int64, device=device),
        )

    def __len__(self) -> int:
        return int(self.scores.shape[0])


_SX = (1.0, 1.0, -1.0, -1.0)  # corner signs along the heading: front-right, front-left, rear-left, rear-right
_SY = (-1.0, 1.0, 1.0, -1.0)  # corner signs across the heading


def box_corners_bev(boxes: Tensor) -> Tensor:
    """(N, 7) boxes -> (N, 4, 2) BEV corners, counter-clockwise, starting at the front-right corner."""
    lx = 0.5 * boxes[:, 3:4] * boxes.new_tensor(_SX)  # (N, 4) along the heading
    ly = 0.5 * boxes[:, 4:5] * boxes.new_tensor(_SY)  # (N, 4) across it
    cos, sin = torch.cos(boxes[:, 6:7]), torch.sin(boxes[:, 6:7])  # (N, 1)
    x = boxes[:, 0:1] + cos * lx - sin * ly  # (N, 4)
    y = boxes[:, 1:2] + sin * lx + cos * ly
    return torch.stack((x, y), dim=-1)


def _clip_slab(u: Tensor, v: Tensor, half: Tensor) -> tuple[Tensor, Tensor]:
    """Retract a closed polygon onto the slab |u| <= half: clamp u, with the crossings of the lines u = +-half
    inserted along every edge. u, v (P, V) vertices in order, half (P, 1) -> u, v (P, 3 V).

    Shoelace area of the result = area of (polygon inside the slab), for any closed polygon: the outside parts
    are mapped onto the slab's border lines, where they add up to zero, and the winding number around every
    point strictly inside the slab is unchanged. No sorting, no tolerances, exact for touching and identical
    boxes; points repeat (zero-length edges add nothing).
    """
    du, dv = torch.roll(u, -1, dims=1) - u, torch.roll(v, -1, dims=1) - v  # (P, V) edges
    moving = du != 0
    safe = torch.where(moving, du, torch.ones_like(du))
    t_low, t_high = (-half - u) / safe, (half - u) / safe  # (P, V) where the edge meets u = -half, u = +half
    rising = du > 0
    zero = torch.zeros_like(du)
    first = torch.where(moving, torch.where(rising, t_low, t_high), zero).clamp(0.0, 1.0)  # line met first
    second = torch.where(moving, torch.where(rising, t_high, t_low), zero).clamp(0.0, 1.0)
    t = torch.stack((zero, first, second), dim=-1)  # (P, V, 3) non-decreasing along each edge
    out_u = torch.minimum(torch.maximum(u[..., None] + t * du[..., None], -half[..., None]), half[..., None])
    out_v = v[..., None] + t * dv[..., None]
    return out_u.flatten(1), out_v.flatten(1)


def _intersection_bev(a: Tensor, b: Tensor) -> Tensor:
    """BEV intersection area of aligned pairs: (P, 7), (P, 7) -> (P,).

    Works in B's own frame (origin at B's centre, x along B's heading), where B is the axis-aligned
    rectangle |x| <= l_b / 2, |y| <= w_b / 2: A's corners are retracted onto the x slab, then the y slab,
    and the shoelace formula gives the area. Relative coordinates keep float32 accurate far from the origin.
    Areas below 64 eps x the larger box's area (IoU below about 1e-5 in float32) are returned as 0.
    """
    sx, sy = a.new_tensor(_SX), a.new_tensor(_SY)  # (4,)
    cos_b, sin_b = torch.cos(b[:, 6:7]), torch.sin(b[:, 6:7])  # (P, 1)
    dx, dy = a[:, 0:1] - b[:, 0:1], a[:, 1:2] - b[:, 1:2]
    cx, cy = dx * cos_b + dy * sin_b, -dx * sin_b + dy * cos_b  # (P, 1) A's centre in B's frame
    rel_yaw = a[:, 6:7] - b[:, 6:7]  # (P, 1) A's yaw in B's frame
    cos_r, sin_r = torch.cos(rel_yaw), torch.sin(rel_yaw)
    lx, ly = 0.5 * a[:, 3:4] * sx, 0.5 * a[:, 4:5] * sy  # (P, 4) A's corners in A's frame
    ax, ay = cx + cos_r * lx - sin_r * ly, cy + sin_r * lx + cos_r * ly  # (P, 4) counter-clockwise
    x, y = _clip_slab(ax, ay, 0.5 * b[:, 3:4])  # (P, 12)
    y, x = _clip_slab(y, x, 0.5 * b[:, 4:5])  # (P, 36)
    area = 0.5 * (x * torch.roll(y, -1, dims=1) - y * torch.roll(x, -1, dims=1)).sum(dim=1)  # (P,)
    # rounding leaves ~eps * area_b where the true area is 0 (disjoint, touching): report those as 0
    floor = 64 * torch.finfo(a.dtype).eps * torch.maximum(a[:, 3] * a[:, 4], b[:, 3] * b[:, 4])  # (P,)
    return torch.where(area > floor, area, torch.zeros_like(area))


def _safe_ratio(num: Tensor, den: Tensor) -> Tensor:
    """num / den where den > 0, else 0 (zero-size boxes give IoU 0, not NaN)."""
    pos = den > 0
    return torch.where(pos, num / torch.where(pos, den, torch.ones_like(den)), torch.zeros_like(num))


def _z_overlap(a: Tensor, b: Tensor) -> Tensor:
    """Overlap of the vertical extents of aligned pairs: (P, 7), (P, 7) -> (P,) metres."""
    top = torch.minimum(a[:, 2] + 0.5 * a[:, 5], b[:, 2] + 0.5 * b[:, 5])
    bottom = torch.maximum(a[:, 2] - 0.5 * a[:, 5], b[:, 2] - 0.5 * b[:, 5])
    return (top - bottom).clamp_min(0.0)


class _PairFn(Protocol):
    def __call__(self, a: Tensor, b: Tensor) -> Tensor: ...


def _chunked(a: Tensor, b: Tensor, fn: _PairFn) -> Tensor:
    if a.shape[0] <= _PAIR_CHUNK:
        return fn(a, b)
    parts = [fn(a[i : i + _PAIR_CHUNK], b[i : i + _PAIR_CHUNK]) for i in range(0, a.shape[0], _PAIR_CHUNK)]
    return torch.cat(parts)


def _iou_bev_pairs(a: Tensor, b: Tensor) -> Tensor:
    inter = _intersection_bev(a, b)  # (P,)
    union = a[:, 3] * a[:, 4] + b[:, 3] * b[:, 4] - inter
    return _safe_ratio(inter, union)


def _iou_3d_pairs(a: Tensor, b: Tensor) -> Tensor:
    inter = _intersection_bev(a, b) * _z_overlap(a, b)  # (P,) cubic metres
    union = a[:, 3] * a[:, 4] * a[:, 5] + b[:, 3] * b[:, 4] * b[:, 5] - inter
    return _safe_ratio(inter, union)


def _check(a: Tensor, b: Tensor, aligned: bool) -> None:
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != 7 or b.shape[1] != 7:
        raise ValueError(f"expected (N, 7) and (M, 7) boxes, got {tuple(a.shape)} and {tuple(b.shape)}")
    if aligned and a.shape[0] != b.shape[0]:
        raise ValueError(f"aligned IoU needs as many boxes in a as in b, got {a.shape[0]} and {b.shape[0]}")
    if a.dtype != b.dtype or not a.is_floating_point():
        raise ValueError(f"boxes must share one floating dtype, got {a.dtype} and {b.dtype}")


def rotated_iou_bev_aligned(a: Tensor, b: Tensor) -> Tensor:
    """Pairwise BEV IoU of a[i] with b[i]: (N, 7), (N, 7) -> (N,). Differentiable with respect to both."""
    _check(a, b, aligned=True)
    return _chunked(a, b, _iou_bev_pairs)


def rotated_iou_3d_aligned(a: Tensor, b: Tensor) -> Tensor:
    """Pairwise 3D IoU of a[i] with b[i]: (N, 7), (N, 7) -> (N,). Differentiable with respect to both."""
    _check(a, b, aligned=True)
    return _chunked(a, b, _iou_3d_pairs)


def near_pairs(a: Tensor, b: Tensor | None = None) -> Iterator[tuple[Tensor, Tensor]]:
    """Index pairs whose circumscribed BEV circles overlap (necessary for a non-zero intersection).

    a (N, 7), b (M, 7) -> chunks (ia (P,), ib (P,)) int64 of all such pairs, each chunk from at most
    _PAIR_CHUNK candidates. With b None: each unordered pair of distinct boxes of a once, as ia < ib.
    Sweep along x over b's circles sorted by their left end (x - r): a row looks only at the circles whose
    left end lies within its reach. Self pairs: b's circles j after i in that order with left_j <= x_i + r_i
    (exactly the x-overlapping pairs); a against b: left ends in [x_a - r_a - 2 max r_b, x_a + r_a].
    """
    self_pairs = b is None
    b = a if b is None else b
    if a.shape[0] == 0 or b.shape[0] == 0:
        return
    radius_a, radius_b = 0.5 * torch.hypot(a[:, 3], a[:, 4]), 0.5 * torch.hypot(b[:, 3], b[:, 4])
    left_b, order_b = torch.sort((b[:, 0] - radius_b).contiguous())  # (M,)
    if self_pairs:  # rows in left-end order; look right only, so every unordered pair comes once
        rows_idx = order_b
        lo = torch.arange(1, a.shape[0] + 1, device=a.device)  # (N,)
    else:
        rows_idx = torch.arange(a.shape[0], device=a.device)
        lo = torch.searchsorted(left_b, a[:, 0] - radius_a - 2 * radius_b.max())
    hi = torch.searchsorted(left_b, a[rows_idx, 0] + radius_a[rows_idx], right=True)  # (N,)
    counts = (hi - lo).clamp_min(0)  # (N,) candidates of each row
    for r0, r1, total in _row_blocks(counts.cpu()):
        c = counts[r0:r1]
        local = torch.repeat_interleave(torch.arange(r1 - r0, device=a.device), c, output_size=total)  # (P,)
        starts = torch.cumsum(c, 0) - c  # (R,) first candidate of each row in this block
        k = torch.arange(total, device=a.device) - starts[local]  # (P,) rank within the row
        ia, ib = rows_idx[r0 + local], order_b[lo[r0 + local] + k]  # (P,), (P,)
        dx, dy = a[ia, 0] - b[ib, 0], a[ia, 1] - b[ib, 1]
        reach_p = radius_a[ia] + radius_b[ib]
        hit = dx * dx + dy * dy < reach_p * reach_p  # (P,)
        ia, ib = ia[hit], ib[hit]
        if self_pairs:
            ia, ib = torch.minimum(ia, ib), torch.maximum(ia, ib)
        yield ia, ib


def iou_bev_upper_bound(a: Tensor, b: Tensor) -> Tensor:
    """A cheap upper bound of the BEV IoU of aligned pairs: (P, 7), (P, 7) -> (P,).

    Each box lies inside its axis-aligned bounding rectangle, so the intersection is at most the overlap of
    those rectangles and at most the smaller area; IoU = I / (A + B - I) grows with I.
    """

    def half_extents(x: Tensor) -> tuple[Tensor, Tensor]:
        cos, sin = torch.cos(x[:, 6]).abs(), torch.sin(x[:, 6]).abs()
        return 0.5 * (x[:, 3] * cos + x[:, 4] * sin), 0.5 * (x[:, 3] * sin + x[:, 4] * cos)

    (hxa, hya), (hxb, hyb) = half_extents(a), half_extents(b)
    ox = torch.minimum(a[:, 0] + hxa, b[:, 0] + hxb) - torch.maximum(a[:, 0] - hxa, b[:, 0] - hxb)
    oy = torch.minimum(a[:, 1] + hya, b[:, 1] + hyb) - torch.maximum(a[:, 1] - hya, b[:, 1] - hyb)
    area_a, area_b = a[:, 3] * a[:, 4], b[:, 3] * b[:, 4]
    inter = torch.minimum(ox.clamp_min(0.0) * oy.clamp_min(0.0), torch.minimum(area_a, area_b))
    return _safe_ratio(inter, area_a + area_b - inter)


def _row_blocks(counts: Tensor) -> Iterator[tuple[int, int, int]]:
    """Split rows with (N,) CPU candidate counts into runs [r0, r1) of at most _PAIR_CHUNK candidates
    (a single larger row goes alone). Yields (r0, r1, candidates in the run); empty runs are skipped."""
    ends = torch.cumsum(counts, 0)  # (N,)
    n, r0 = counts.shape[0], 0
    while r0 < n:
        base = int(ends[r0 - 1]) if r0 > 0 else 0
        r1 = max(r0 + 1, int(torch.searchsorted(ends, base + _PAIR_CHUNK, right=True)))
        total = int(ends[r1 - 1]) - base
        if total > 0:
            yield r0, r1, total
        r0 = r1


def _all_pairs(a: Tensor, b: Tensor, fn: _PairFn) -> Tensor:
    """(N, 7), (M, 7) -> (N, M): `fn` on the pairs whose circumscribed circles overlap, 0 elsewhere.

    Works in chunks of pairs, so memory stays bounded (besides the output) for thousands of boxes.
    """
    out = a.new_zeros((a.shape[0], b.shape[0]))
    for ia, ib in near_pairs(a, b):
        out[ia, ib] = fn(a[ia], b[ib])
    return out


def rotated_iou_bev(a: Tensor, b: Tensor) -> Tensor:
    """BEV IoU of every box in a with every box in b: (N, 7), (M, 7) -> (N, M), dtype of the boxes."""
    _check(a, b, aligned=False)
    return _all_pairs(a, b, _iou_bev_pairs)


def rotated_iou_3d(a: Tensor, b: Tensor) -> Tensor:
    """3D IoU: BEV intersection x z overlap / union of volumes. (N, 7), (M, 7) -> (N, M)."""
    _check(a, b, aligned=False)
    return _all_pairs(a, b, _iou_3d_pairs)
