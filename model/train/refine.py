"""Training the box refiner (model.layers.refine) on a trained, frozen detector's own boxes.

1. `proposals`: the detector's full-turn detections on simulated scans (for a later stage of the cascade,
   `RefineConfig.stages`: as the stages before it refined them), each with the raw points around it
   (`box_points`, as serving reads them) and its best-overlapping true box of the same class.
2. `fit`: the refiner learns the residual to that true box where the 3D IoU is at least `MATCH_IOU` (L1
   plus 1 - IoU of the refined box; with `RefineConfig.flip` also whether it points the wrong way) and, on
   every box, the refined box's IoU (binary cross-entropy; 0 for a box on no object).
The detector's weights do not change: the refiner is trained after it (`phim train-refiner`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from lidar.types import LabeledScan
from model.config import RefineConfig
from model.detector import PHiM
from model.eval.metrics import iou_matrix
from model.eval.runner import scan_sectors
from model.geometry.boxes import rotated_iou_3d_aligned
from model.layers.head import decode
from model.layers.phim_block import StreamLayout
from model.layers.refine import (
    BoxRefiner,
    apply_residual,
    box_points,
    grown_boxes,
    refine_many,
    residual_target,
)

log = logging.getLogger(__name__)

MATCH_IOU = 0.3  # a box with at least this 3D IoU with a true box of its class learns the residual to it
# the flip logit's loss against the residual's (`RefineConfig.flip`): at 1.0 it takes AP from the residual,
# at 0.25 it learns the flips and the AP stays (docs/model-card.md, "The box refiner's recipe")
FLIP_WEIGHT = 0.25


@dataclass
class Proposals:
    local: Tensor  # (B, P, 3) points in each box's frame
    counts: Tensor  # (B,) points inside each grown box
    boxes: Tensor  # (B, 7) the detector's boxes
    scores: Tensor  # (B,)
    labels: Tensor  # (B,)
    truth: Tensor  # (B, 7) the best-overlapping true box of the same class (zeros: none)
    iou: Tensor  # (B,) its 3D IoU with the box

    @staticmethod
    def cat(parts: list[Proposals]) -> Proposals:
        return Proposals(*(torch.cat([getattr(p, f) for p in parts]) for f in FIELDS))

    def take(self, idx: Tensor) -> Proposals:
        return Proposals(*(getattr(self, f)[idx] for f in FIELDS))

    def __len__(self) -> int:
        return int(self.scores.shape[0])


FIELDS = tuple(Proposals.__dataclass_fields__)


@torch.inference_mode()
def scan_proposals(
    model: PHiM, cfg: RefineConfig, scan: LabeledScan, refined: int = 0, every_cell: Sequence[bool] = ()
) -> Proposals:
    """The detector's full-turn boxes on one scan, after the model's first `refined` refiner stages, with
    their points and their true boxes. The boxes are the heatmaps' local maxima, and every cell of a class
    whose `every_cell` is true (what `RefineConfig.every_cell` makes the refiner read at work)."""
    n = model.cfg.sectors_per_turn
    sectors = scan_sectors(scan, model.cfg.vfe.point_features, n)
    enc = model.encode(sectors, StreamLayout.single_stream(n, model.device), model.init_states(1))
    det = decode(model.predict([enc.sectors]), model.cfg.head, model.cfg.bev, every_cell)[0]
    points = torch.cat(sectors)
    if refined and model.refiner is not None:
        det = refine_many(model.refiner, [det], [points], stages=refined, mirror=False)[0]
    local, counts = box_points(points, grown_boxes(det.boxes, det.labels, cfg), cfg.points)
    gt = scan.gt
    iou = np.zeros((len(det), len(gt)), np.float32)
    if len(det) and len(gt):
        same = det.labels.numpy()[:, None] == gt.labels[None, :]
        iou = np.where(same, iou_matrix(det.boxes.numpy(), gt.boxes), 0.0)
    best = iou.argmax(1) if len(gt) else np.zeros(len(det), np.int64)
    truth = torch.from_numpy(gt.boxes[best]) if len(gt) else torch.zeros(len(det), 7)
    best_iou = torch.from_numpy(iou[np.arange(len(det)), best]) if len(gt) else torch.zeros(len(det))
    return Proposals(local, counts, det.boxes, det.scores, det.labels, truth.float(), best_iou.float())


def proposals(
    model: PHiM,
    cfg: RefineConfig,
    source: Callable[[int], LabeledScan],
    scans: range,
    refined: int = 0,
    every_cell: Sequence[bool] = (),
) -> Proposals:
    """`scan_proposals` of scans source(i) for i in `scans`, in order."""
    model.eval()
    t0 = time.perf_counter()
    parts = []
    for i in scans:
        parts.append(scan_proposals(model, cfg, source(i), refined, every_cell))
        if len(parts) % 100 == 0:
            boxes = sum(map(len, parts))
            log.info("proposals: %d scans, %d boxes, %.0f s", len(parts), boxes, time.perf_counter() - t0)
    return Proposals.cat(parts)


def refiner_loss(refiner: BoxRefiner, p: Proposals) -> Tensor:
    """L1 and 1 - IoU of the residual on the matched boxes (and, with `RefineConfig.flip`, the flip logit's
    binary cross-entropy: does the true box point the other way), BCE of the IoU logit on all of them."""
    out = refiner(p.local, p.counts, p.boxes, p.scores, p.labels)  # (B, 8 or 9)
    pos = p.iou >= MATCH_IOU
    iou_target = torch.zeros_like(p.scores)
    loss = out.sum() * 0.0
    if pos.any():
        res = out[pos, :7]
        loss = loss + (res - residual_target(p.boxes[pos], p.truth[pos])).abs().sum(1).mean()
        iou = rotated_iou_3d_aligned(apply_residual(p.boxes[pos], res), p.truth[pos]).clamp(0.0, 1.0)
        loss = loss + (1 - iou).mean()
        iou_target[pos] = iou.detach()
        if refiner.cfg.flip:
            backwards = (torch.cos(p.truth[pos, 6] - p.boxes[pos, 6]) < 0).to(out.dtype)
            flip = nn.functional.binary_cross_entropy_with_logits(out[pos, 8], backwards)
            loss = loss + FLIP_WEIGHT * flip
    return loss + nn.functional.binary_cross_entropy_with_logits(out[:, 7], iou_target)


def fit(
    refiner: BoxRefiner, data: Proposals, epochs: int, lr: float, batch: int = 512, seed: int = 0
) -> None:
    """One-cycle AdamW over `epochs` passes of `data` in shuffled batches."""
    gen = torch.Generator().manual_seed(seed)
    per_epoch = max(len(data) // batch, 1)
    opt = torch.optim.AdamW(refiner.parameters(), lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, lr, total_steps=epochs * per_epoch)
    refiner.train()
    for epoch in range(epochs):
        perm = torch.randperm(len(data), generator=gen)
        total = 0.0
        for b in range(per_epoch):
            idx = perm[b * batch : (b + 1) * batch]
            loss = refiner_loss(refiner, data.take(idx))
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += float(loss.detach())
        log.info("refiner epoch %d: loss %.4f", epoch, total / per_epoch)
    refiner.eval()
