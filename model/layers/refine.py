"""The box refiner: a second stage that corrects each detected box from the raw points around it.

The first stage sees the scene through 0.4 m x 1.4 degree polar voxels with 32 channels; its boxes find the
objects but are too loose for 3D IoU 0.7 (docs/model-card.md). The refiner reads the points themselves:
for each box, the points inside the box grown by its class's `RefineConfig.grow`, in the box's own frame
(centre at the origin, x along its yaw), `RefineConfig.points` of them picked evenly in firing order
(repeated when fewer).
A PointNet (a shared per-point MLP, max-pooled, with the box's class, log size, score, point count and
range; with `RefineConfig.context` a second per-point layer reading each point with the pooled feature)
predicts a residual (dx, dy, dz in the box frame, log size ratios, yaw change on the axis), the refined
box's 3D IoU and, with `RefineConfig.flip`, whether the box points the wrong way (the detector's
direction comes from 0.8 m BEV cells; the points can tell a car's front from its back). With
`RefineConfig.stages` > 1 the refiners run in turn (a cascade: each reads the points around the boxes the
one before it refined, with that one's score). The refined score is score^(1 - a) * iou^a
(`RefineConfig.iou_weight`), as the head's IoU rectification: the detector's score and the last stage's IoU.
At work the boxes of the classes `RefineConfig.mirror` names are read twice, as they are and as their mirror
images (y -> -y in the box's frame), and each stage's two outputs averaged (`mirrored_mean`).

`box_points` finds the points inside the grown boxes (`grown_boxes`) through a grid index of 1 m cells: a
numba kernel on the CPU (`model.ops.box_points_numba`), tensor ops elsewhere (`box_points_torch`);
`box_points_reference`, the plain twin, tests every point against every box. tests/test_refine.py holds
them equal.
"""

from __future__ import annotations

import functools
import math
import os
from concurrent.futures import ThreadPoolExecutor

import torch
from torch import Tensor, nn

from model.config import RefineConfig
from model.geometry.boxes import Detections
from model.geometry.nms import class_nms
from model.ops.box_points_numba import REACH, SLACK, box_points_cpu, grid_cells
from model.ops.numba_support import numba_kernel

_CELL = 1.0  # metres: the grid index's cells
_CONTEXT = 64  # channels of the context layer's per-point hidden layer (`RefineConfig.context`)
_EPS = 1e-3  # metres around a box's bounding rectangle


def to_box_frame(points: Tensor, boxes: Tensor) -> Tensor:
    """points (T, 3), boxes (T, 7), row by row -> (T, 3) each point in its box's frame."""
    c, s = torch.cos(boxes[:, 6]), torch.sin(boxes[:, 6])
    d = points - boxes[:, :3]
    return torch.stack((c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]), 1)


def _pick(box: Tensor, local: Tensor, num_boxes: int, p: int) -> tuple[Tensor, Tensor]:
    """The points inside the boxes as rows (box, box-frame coords), sorted by box then firing order ->
    (B, P, 3) box-frame points picked evenly (zeros for a box with none) and (B,) counts."""
    counts = torch.bincount(box, minlength=num_boxes)  # (B,)
    first = torch.cumsum(counts, 0) - counts  # (B,)
    j = torch.arange(p, device=local.device)
    rank = torch.div(j[None, :] * counts[:, None], p, rounding_mode="floor")  # (B, P)
    rows = (first[:, None] + rank).clamp(max=max(local.shape[0] - 1, 0))
    picked = local[rows] if local.shape[0] else local.new_zeros(num_boxes, p, 3)
    return torch.where(counts[:, None, None] > 0, picked, torch.zeros_like(picked)), counts


def grown_boxes(boxes: Tensor, labels: Tensor, cfg: RefineConfig) -> Tensor:
    """boxes (B, 7) of classes labels (B,) -> (B, 7) the same boxes, l, w, h grown by their class's
    `cfg.grow`: the outlines the refiner reads the points of."""
    grow = torch.tensor(cfg.grow, dtype=boxes.dtype, device=boxes.device)[labels.long()]  # (B, 3)
    return torch.cat((boxes[:, :3], boxes[:, 3:6] + grow, boxes[:, 6:]), 1)


def box_points_reference(points: Tensor, boxes: Tensor, p: int) -> tuple[Tensor, Tensor]:
    """points (N, >=3), boxes (B, 7) -> (B, p, 3) points in each box, box frame, and (B,) counts: every
    point against every box."""
    b, n = boxes.shape[0], points.shape[0]
    box = torch.arange(b, device=points.device).repeat_interleave(n)
    point = torch.arange(n, device=points.device).repeat(b)
    return _inside(points, boxes, box, point, p)


def box_points(points: Tensor, boxes: Tensor, p: int, fast: bool | None = None) -> tuple[Tensor, Tensor]:
    """`box_points_reference`'s result: by a numba kernel (`model.ops.box_points_numba`) or by tensor ops
    (`box_points_torch`), as `fast` says (`numba_kernel`: None, the kernel on CPU tensors)."""
    if numba_kernel("box_points", points.device, fast):
        return box_points_cpu(points, boxes, p, _CELL, _EPS)
    return box_points_torch(points, boxes, p)


def box_points_torch(points: Tensor, boxes: Tensor, p: int) -> tuple[Tensor, Tensor]:
    """`box_points_reference`'s result through the kernel's grid index (`box_points_numba`: 1 m cells
    over the boxes' rectangles, at most `MAX_SIDE` a side; one sort of the points by cell):
    each box tests the points of the cells under its outline's bounding rectangle, one contiguous run
    of the sorted points per column of cells. Safe for any values, as the kernel."""
    b, dev = boxes.shape[0], points.device
    none = torch.zeros(0, dtype=torch.int64, device=dev)
    if b == 0 or points.shape[0] == 0:
        return _inside(points, boxes, none, none, p)
    rect = _rectangles(boxes)  # (B, 4) float64
    x, y = points[:, 0].double(), points[:, 1].double()  # (N,) each
    span = torch.cat((rect[:, :2].amin(0).clamp(min=-REACH), rect[:, 2:].amax(0).clamp(max=REACH)))
    x0, y0, x1, y1 = span.tolist()  # the rectangles' span, finite (one wait on the device)
    if not (x0 <= x1 and y0 <= y1):  # no rectangle holds a finite point
        return _inside(points, boxes, none, none, p)
    cell, w, h = grid_cells(x0, y0, x1, y1, _CELL)
    in_grid = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)  # a float test before any integer
    key = torch.where(in_grid, _index(x, x0, cell, w) * h + _index(y, y0, cell, h), w * h)  # (N,)
    key, order = torch.sort(key, stable=True)  # points outside the grid last
    lo_x, lo_y = _index(rect[:, 0], x0, cell, w), _index(rect[:, 1], y0, cell, h)  # (B,) each
    hi_x, hi_y = _index(rect[:, 2], x0, cell, w), _index(rect[:, 3], y0, cell, h)
    columns = (hi_x - lo_x + 1).clamp_(min=0)  # (B,) none for a box of negative size
    box = torch.arange(b, device=dev).repeat_interleave(columns)  # (C,) one row per column of cells
    ix = lo_x[box] + torch.arange(int(columns.sum()), device=dev) - (torch.cumsum(columns, 0) - columns)[box]
    start = torch.searchsorted(key, ix * h + lo_y[box])  # (C,)
    count = (torch.searchsorted(key, ix * h + hi_y[box], right=True) - start).clamp_(min=0)
    first = torch.cumsum(count, 0) - count
    run = torch.arange(int(count.sum()), device=dev) - first.repeat_interleave(count)
    point = order[start.repeat_interleave(count) + run]  # (T,)
    return _inside(points, boxes, box.repeat_interleave(count), point, p)


def _rectangles(boxes: Tensor) -> Tensor:
    """boxes (B, 7) -> (B, 4) float64 lo_x, lo_y, hi_x, hi_y: each box's bounding rectangle, as the
    kernel's (`box_points_numba._rectangles`: widened by _EPS and SLACK, a NaN bound unbounded)."""
    bx = boxes.double()
    half_l, half_w = bx[:, 3] / 2, bx[:, 4] / 2
    c, s = torch.cos(bx[:, 6]).abs(), torch.sin(bx[:, 6]).abs()
    extent = torch.stack((c * half_l + s * half_w, s * half_l + c * half_w), 1) * (1 + SLACK) + _EPS  # (B, 2)
    lo, hi = bx[:, :2] - extent, bx[:, :2] + extent
    return torch.cat((lo.nan_to_num(nan=-math.inf), hi.nan_to_num(nan=math.inf)), 1)


def _index(v: Tensor, origin: float, cell: float, n: int) -> Tensor:
    """`box_points_numba._index` of each value: the cell in [0, n) of a grid from `origin`, clamped as a
    float."""
    return ((v - origin) / cell).nan_to_num_(nan=0.0).clamp_(0, n - 1).floor_().long()


def _inside(points: Tensor, boxes: Tensor, box: Tensor, point: Tensor, p: int) -> tuple[Tensor, Tensor]:
    """Candidate (box, point index) rows (T,) -> `_pick` of those inside the box, by box then firing
    order."""
    local = to_box_frame(points[point, :3], boxes[box])  # (T, 3)
    keep = (local.abs() <= boxes[box, 3:6] / 2).all(1)
    box, point, local = box[keep], point[keep], local[keep]
    order = torch.argsort(box * points.shape[0] + point)
    return _pick(box[order], local[order], boxes.shape[0], p)


class BoxRefiner(nn.Module):
    """One stage of the refiner; `next_stage` the one after it (`RefineConfig.stages`), or None."""

    def __init__(self, num_classes: int, cfg: RefineConfig, stage: int = 1):
        super().__init__()
        self.cfg = cfg
        self.num_classes = num_classes
        w = cfg.hidden
        self.point = nn.Sequential(nn.Linear(6, 64), nn.ReLU(), nn.Linear(64, w), nn.ReLU())
        if cfg.context:  # Linear(cat(point, pooled)) split in two: the pooled part once per box
            self.context_point = nn.Linear(w, _CONTEXT)
            self.context_box = nn.Linear(w, _CONTEXT, bias=False)
            self.context_out = nn.Sequential(nn.ReLU(), nn.Linear(_CONTEXT, w), nn.ReLU())
        pooled = 2 * w if cfg.context else w
        self.out = nn.Sequential(
            nn.Linear(pooled + num_classes + 6, 128),
            nn.ReLU(),
            nn.Linear(128, 64),
            nn.ReLU(),
            nn.Linear(64, 9 if cfg.flip else 8),
        )
        self.next_stage = BoxRefiner(num_classes, cfg, stage + 1) if stage < cfg.stages else None

    def chain(self) -> list[BoxRefiner]:
        """This stage and every one after it, in order."""
        return [self, *(self.next_stage.chain() if self.next_stage is not None else [])]

    def forward(self, local: Tensor, counts: Tensor, boxes: Tensor, scores: Tensor, labels: Tensor) -> Tensor:
        """This stage alone: local (B, P, 3) box-frame points, counts (B,), boxes (B, 7), scores (B,),
        labels (B,) -> (B, 8 or 9): the residual (dx, dy, dz, dlog l, dlog w, dlog h, dyaw), the refined
        box's IoU logit and, with `cfg.flip`, the logit that the box points the wrong way."""
        half = boxes[:, None, 3:6] / 2  # (B, 1, 3)
        h = self.point(torch.cat((local, local / half), 2))  # (B, P, W)
        f = h.amax(1)  # (B, W)
        if self.cfg.context:
            c = self.context_out(self.context_point(h) + self.context_box(f)[:, None])  # (B, P, W)
            f = torch.cat((f, c.amax(1)), 1)  # (B, 2W)
        onehot = nn.functional.one_hot(labels, self.num_classes).to(boxes.dtype)
        g = torch.cat(
            (
                onehot,
                torch.log(boxes[:, 3:6]),
                scores[:, None],
                torch.log1p(counts.to(boxes.dtype))[:, None] / 5,
                torch.hypot(boxes[:, 0], boxes[:, 1])[:, None] / 50,
            ),
            1,
        )  # (B, K + 6)
        return self.out(torch.cat((f, g), 1))


def apply_residual(boxes: Tensor, res: Tensor) -> Tensor:
    """boxes (B, 7), residuals (B, >=7) as `BoxRefiner` predicts them -> refined boxes (B, 7)."""
    c, s = torch.cos(boxes[:, 6]), torch.sin(boxes[:, 6])
    x = boxes[:, 0] + c * res[:, 0] - s * res[:, 1]
    y = boxes[:, 1] + s * res[:, 0] + c * res[:, 1]
    dims = boxes[:, 3:6] * torch.exp(res[:, 3:6])
    centre = torch.stack((x, y, boxes[:, 2] + res[:, 2]), 1)
    return torch.cat((centre, dims, (boxes[:, 6] + res[:, 6])[:, None]), 1)


def apply_output(boxes: Tensor, out: Tensor, cfg: RefineConfig) -> Tensor:
    """boxes (B, 7) and the refiner's output (B, 8 or 9) -> the refined boxes (B, 7): the residual, then a
    half turn where the flip logit is above 0 (`cfg.flip`)."""
    refined = apply_residual(boxes, out)
    if cfg.flip:
        refined[:, 6] += math.pi * (out[:, 8] > 0).to(refined.dtype)
    return refined


def residual_target(boxes: Tensor, truth: Tensor) -> Tensor:
    """boxes (B, 7) and their true boxes (B, 7) -> (B, 7) the residual `apply_residual` turns one into the
    other (yaw on the axis: the change in (-pi/2, pi/2], the box's direction kept)."""
    d = to_box_frame(truth[:, :3], boxes)
    dims = torch.log(truth[:, 3:6].clamp(min=1e-3) / boxes[:, 3:6])
    dyaw = torch.remainder(truth[:, 6] - boxes[:, 6] + math.pi / 2, math.pi) - math.pi / 2
    return torch.cat((d, dims, dyaw[:, None]), 1)


# boxes per PointNet forward on a CPU, where its (boxes x points, hidden) activations then stay in cache
_CPU_CHUNK = 160


@torch.no_grad()
def refine(refiner: BoxRefiner, det: Detections, points: Tensor) -> Detections:
    """A prediction's detections and the raw points (N, >=3) of the sectors it covers -> the refined
    detections, re-sorted by their refined score (on det's device)."""
    return refine_many(refiner, [det], [points])[0]


@torch.no_grad()
def refine_many(
    refiner: BoxRefiner,
    dets: list[Detections],
    points: list[Tensor],
    stages: int | None = None,
    mirror: bool = True,
) -> list[Detections]:
    """Several predictions (a batch's streams), each with the raw points (N_i, >=3) of the sectors it
    covers -> each refined as `refine` would, by the first `stages` stages of the chain (None: all). Per
    stage the points are looked up where they lie (the host, in a server: no copy of them, no wait on a
    device), then one PointNet forward runs over every box of the batch on the refiner's device (on a CPU
    in chunks of `_CPU_CHUNK` boxes: 1,040 boxes took 1.5-1.75x as long in one forward as in chunks of
    160), and with `mirror` one more over the boxes of the classes `RefineConfig.mirror` names, read as
    their mirror images (`mirrored_mean`; mirror=False: each box read once, as the stages are fitted)."""
    dev = next(refiner.parameters()).device
    sizes = [len(d) for d in dets]
    if sum(sizes) == 0:
        return list(dets)
    some = [i for i, d in enumerate(dets) if len(d)]  # the streams with boxes
    boxes = torch.cat([d.boxes for d in dets]).to(dev)  # (T, 7) T: the batch's boxes
    detected = torch.cat([d.scores for d in dets]).to(dev)  # (T,)
    labels = torch.cat([d.labels for d in dets]).to(dev)  # (T,)
    scores = detected
    for stage in refiner.chain()[:stages]:
        cfg = stage.cfg
        per_stream = grown_boxes(boxes, labels, cfg).split(sizes)
        looked = box_points_many(
            [points[i] for i in some], [per_stream[i].to(points[i].device) for i in some], cfg.points
        )
        local = torch.cat([lc[0] for lc in looked]).to(dev)  # (T, P, 3)
        counts = torch.cat([lc[1] for lc in looked]).to(dev)  # (T,)
        out = refiner_forward(stage, local, counts, boxes, scores, labels)  # (T, 8 or 9)
        if mirror and any(cfg.mirror):
            out = mirrored_mean(stage, out, local, counts, boxes, scores, labels)
        boxes = apply_output(boxes, out, cfg)
        a = cfg.iou_weight
        scores = detected.pow(1 - a) * torch.sigmoid(out[:, 7]).pow(a)
    last = stages is None or stages >= len(refiner.chain())
    nms_iou = refiner.cfg.nms_iou if last else None  # after the last stage only
    split = zip(boxes.split(sizes), scores.split(sizes), labels.split(sizes), dets, strict=True)
    return [_sorted(b, s, lab, nms_iou).to(d.boxes.device) for b, s, lab, d in split]


def refiner_forward(
    refiner: BoxRefiner, local: Tensor, counts: Tensor, boxes: Tensor, scores: Tensor, labels: Tensor
) -> Tensor:
    """`BoxRefiner.forward` over T boxes (its inputs on the refiner's device) -> (T, 8 or 9): one forward,
    or on a CPU one per `_CPU_CHUNK` boxes."""
    if local.device.type != "cpu" or boxes.shape[0] <= _CPU_CHUNK:
        return refiner(local, counts, boxes, scores, labels)
    parts = zip(*(x.split(_CPU_CHUNK) for x in (local, counts, boxes, scores, labels)), strict=True)
    return torch.cat([refiner(*part) for part in parts])


def mirrored_mean(
    refiner: BoxRefiner,
    out: Tensor,
    local: Tensor,
    counts: Tensor,
    boxes: Tensor,
    scores: Tensor,
    labels: Tensor,
) -> Tensor:
    """`refiner_forward`'s output out (T, 8 or 9) on the inputs that follow it -> the same, where a box's
    class is one `RefineConfig.mirror` names averaged with the output on the box's mirror image: its points
    with y -> -y in its frame, an object as seen from its other side, and that output's dy and dyaw (the
    values odd in y) turned back."""
    which = labels.new_tensor(refiner.cfg.mirror, dtype=torch.bool)[labels].nonzero()[:, 0]  # (M,)
    if which.numel() == 0:
        return out
    y = local.new_tensor([1.0, -1.0, 1.0])
    seen = refiner_forward(
        refiner, local[which] * y, counts[which], boxes[which], scores[which], labels[which]
    )
    seen[:, [1, 6]] = -seen[:, [1, 6]]  # dy, dyaw back in the box's own frame
    return out.index_put((which,), (out[which] + seen) / 2)


def box_points_many(points: list[Tensor], boxes: list[Tensor], p: int) -> list[tuple[Tensor, Tensor]]:
    """`box_points` of each (points, boxes) pair; on the CPU on torch's threads at once (the numba kernel
    releases the GIL: 8 KITTI turns' lookups took 0.53-0.68x as long on 2 threads as one after another)."""
    threads = torch.get_num_threads()
    if len(points) > 1 and threads > 1 and all(p.device.type == "cpu" for p in points):
        return list(_pool(threads).map(lambda pts, b: box_points(pts, b, p), points, boxes))
    return [box_points(pts, b, p) for pts, b in zip(points, boxes, strict=True)]


@functools.cache
def _pool(workers: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(workers, thread_name_prefix="refine-lookup")


os.register_at_fork(after_in_child=_pool.cache_clear)  # a forked child has none of the pool's threads


def _sorted(boxes: Tensor, scores: Tensor, labels: Tensor, nms_iou: tuple[float, ...] | None) -> Detections:
    """One stream's refined boxes (T, 7), scores and labels (T,) -> sorted by score, after a class-specific
    NMS with `nms_iou` where given (`class_nms`: 0.3 ms for 200 boxes on the 2-core machine)."""
    if nms_iou is not None:
        keep = class_nms(boxes, scores, labels, nms_iou, len(boxes), len(boxes))  # sorted by score
        return Detections(boxes[keep], scores[keep], labels[keep])
    order = torch.argsort(scores, descending=True, stable=True)
    return Detections(boxes[order], scores[order], labels[order])


def refine_streams(
    refiner: BoxRefiner | None,
    dets: list[Detections],
    buffered: list[tuple[Tensor, ...]],
    new: list[Tensor],
    keep: int,
) -> tuple[list[Detections], list[tuple[Tensor, ...]]]:
    """A streaming step's detections per stream, each stream's buffered sectors' points (x, y, z) and its new
    sector's points -> the detections refined on those points (`refine_many`: one PointNet forward for the
    batch), and the points each stream buffers for its next step (the last `keep` sectors'; nothing without
    a refiner, whose detections pass unchanged)."""
    if refiner is None:
        return list(dets), [() for _ in dets]
    # x, y, z copied out of each new sector (N, C >= 4): the buffer holds 3 columns, not the caller's whole
    # tensor, and torch.cat of contiguous (N, 3) sectors takes a fifth of the time it takes of column views
    sectors = [(*b, n[:, :3].contiguous()) for b, n in zip(buffered, new, strict=True)]
    refined = refine_many(refiner, dets, [torch.cat(s) for s in sectors])
    return refined, [s[-keep:] if keep else () for s in sectors]
