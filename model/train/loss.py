"""CenterPoint losses for the head's outputs (as OpenPCDet's CenterHead with an IoU branch and IoU loss).

- heatmap: CenterNet's penalty-reduced focal loss (alpha 2, beta 4), normalised by the number of centres;
- regression: L1 on (offset x, offset y, z, log l, log w, log h, and the two regressed rot channels) at the
  centre cells: (sin yaw, cos yaw), or (sin 2 yaw, cos 2 yaw) plus a direction logit under binary
  cross-entropy (weight `direction_weight`, counted in the `reg` part) for the axis_direction heading code;
- IoU branch: L1 between the predicted IoU and 2 * IoU(decoded box, target) - 1 (the box detached);
- IoU loss: 1 - 3D rotated IoU of the decoded box with its target (gradients into the box regression).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from model.config import BEVConfig, HeadingCode
from model.geometry.boxes import rotated_iou_3d_aligned
from model.layers.head import HeadOutput, decoded_boxes, encode_yaw, gather_cells, regression_at
from model.layers.head_targets import BEVTargets


@dataclass(frozen=True)
class LossConfig:
    heatmap_weight: float = 1.0
    reg_weight: float = 2.0
    iou_branch_weight: float = 1.0
    iou_loss_weight: float = 1.0
    code_weights: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0)
    direction_weight: float = 0.2  # axis_direction heading only (SECOND's direction classifier: 0.2)


@dataclass(frozen=True)
class LossParts:
    total: Tensor
    heatmap: float
    reg: float
    iou_branch: float
    iou_loss: float
    mean_iou: float  # mean 3D IoU of the decoded boxes at the target cells


def focal_loss(logits: Tensor, target: Tensor) -> Tensor:
    """logits, target (B, K, H, W); target 1 exactly at centres -> summed loss / max(centres, 1)."""
    logits = logits.float()
    pos = target.eq(1.0)
    log_p, log_not_p = F.logsigmoid(logits), F.logsigmoid(-logits)
    p = torch.sigmoid(logits)
    pos_loss = (log_p * (1 - p) ** 2)[pos].sum()
    neg_loss = (log_not_p * p**2 * (1 - target) ** 4)[~pos].sum()
    return -(pos_loss + neg_loss) / pos.sum().clamp(min=1)


def center_loss(
    out: HeadOutput, targets: list[BEVTargets], bev: BEVConfig, heading: HeadingCode, cfg: LossConfig
) -> LossParts:
    """Head outputs of B predictions and their B targets -> the weighted loss and its parts."""
    dev = out.heatmap.device
    _, _, h, w = out.heatmap.shape
    hm_target = torch.from_numpy(np.stack([t.heatmap for t in targets])).to(dev)  # (B, K, H, W)
    hm = focal_loss(out.heatmap, hm_target)
    flat = torch.from_numpy(np.concatenate([t.index + i * h * w for i, t in enumerate(targets)])).to(dev)
    n = int(flat.numel())
    if n == 0:
        total = cfg.heatmap_weight * hm + _all_outputs(out)
        return LossParts(total, float(hm.detach()), 0.0, 0.0, 0.0, 0.0)
    reg_target = torch.from_numpy(np.concatenate([t.reg for t in targets])).to(dev)  # (T, 8)
    box_target = torch.from_numpy(np.concatenate([t.boxes for t in targets])).to(dev)  # (T, 7)
    reg = regression_at(out, flat)  # (T, 6 + R)
    rot_target, direction = encode_yaw(box_target[:, 6], heading)  # (T, 2), (T,) or None
    reg_target = torch.cat([reg_target[:, :6], rot_target], 1)  # (T, 8): yaw part in the head's code
    weights = reg.new_tensor(cfg.code_weights)
    reg_loss = ((reg[:, :8] - reg_target).abs() * weights).sum() / n
    if direction is not None:
        reg_loss = reg_loss + cfg.direction_weight * F.binary_cross_entropy_with_logits(reg[:, 8], direction)
    boxes = decoded_boxes(reg, flat, w, h, bev, heading)  # (T, 7)
    iou = rotated_iou_3d_aligned(boxes, box_target).clamp(0.0, 1.0)  # (T,)
    iou_pred = gather_cells(out.iou, flat)[:, 0]  # (T,)
    iou_branch = (iou_pred - (2 * iou.detach() - 1)).abs().mean()
    iou_loss = (1 - iou).mean()
    total = (
        cfg.heatmap_weight * hm
        + cfg.reg_weight * reg_loss
        + cfg.iou_branch_weight * iou_branch
        + cfg.iou_loss_weight * iou_loss
    )
    return LossParts(
        total,
        float(hm.detach()),
        float(reg_loss.detach()),
        float(iou_branch.detach()),
        float(iou_loss.detach()),
        float(iou.detach().mean()),
    )


def _all_outputs(out: HeadOutput) -> Tensor:
    """A zero that depends on every output, so every parameter gets a (zero) gradient (DDP needs that)."""
    return sum(t.sum() for t in (out.offset, out.z, out.log_dim, out.rot, out.iou)) * 0.0
