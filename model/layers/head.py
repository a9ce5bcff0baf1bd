"""CenterPoint detection head (as OpenPCDet's CenterHead with an IoU branch) and box decoding.

BEV layout: tensors are (B, C, ny, nx); row r is the y index, column c the x index. Cell (r, c) covers
x in [x_min + c * cell, x_min + (c + 1) * cell) and y in [y_min + r * cell, y_min + (r + 1) * cell).
A box whose centre falls in that cell is predicted there with

    x = bev.x_min + (c + offset_x) * bev.cell,   y = bev.y_min + (r + offset_y) * bev.cell,

so the offset is in cells, in [0, 1) for a centre inside the cell, measured from the cell's lower-left
(min x, min y) corner. z is the box centre in metres, log_dim the log of (l, w, h) in metres, rot the yaw
as `HeadConfig.heading` encodes it (`encode_yaw` / `decode_yaw`), iou the predicted 3D IoU mapped to [-1, 1]
(training target 2 * iou - 1).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from model.config import BEVConfig, HeadConfig, HeadingCode
from model.geometry.boxes import Detections
from model.geometry.nms import class_nms
from model.ops.nms_numba import class_nms_batch_cpu
from model.ops.numba_support import numba_kernel

HEATMAP_PRIOR_BIAS = -2.19  # log(0.1 / 0.9): initial heatmap probability about 0.1, as CenterPoint
MAX_LOG_DIM = 4.0  # exp(4) = 55 m: keeps early, untrained dims finite (decoding at target cells)


@dataclass
class HeadOutput:
    heatmap: Tensor  # (B, K, H, W) logits, K classes
    offset: Tensor  # (B, 2, H, W) sub-cell centre offset in cells (x, y), from the cell's lower-left corner
    z: Tensor  # (B, 1, H, W) box centre z, metres
    log_dim: Tensor  # (B, 3, H, W) log of (l, w, h) in metres
    rot: Tensor  # (B, R, H, W) sin_cos: (sin yaw, cos yaw); axis_direction: (sin 2yaw, cos 2yaw, dir logit)
    iou: Tensor  # (B, 1, H, W) predicted IoU in [-1, 1] before rectification (target 2 * iou - 1)


def rot_channels(code: HeadingCode) -> int:
    return 2 if code is HeadingCode.SIN_COS else 3


def _axis(sin2: Tensor, cos2: Tensor) -> Tensor:
    return 0.5 * torch.atan2(sin2, cos2)  # the box axis as an angle in [-pi/2, pi/2]


def decode_yaw(rot: Sequence[Tensor], code: HeadingCode) -> Tensor:
    """The head's rot channels (R tensors of one shape) -> yaw in radians (same shape)."""
    if code is HeadingCode.SIN_COS:
        sin, cos = rot
        return torch.atan2(sin, cos)
    sin2, cos2, direction = rot
    axis = _axis(sin2, cos2)
    turned = torch.where(axis > 0, axis - math.pi, axis + math.pi)  # the other way along the axis
    return torch.where(direction >= 0, axis, turned)


def encode_yaw(yaw: Tensor, code: HeadingCode) -> tuple[Tensor, Tensor | None]:
    """yaw (T,) -> the regressed rot targets (T, 2) and, for axis_direction, the direction targets (T,) in
    {0, 1} (1: yaw is the axis angle `decode_yaw` computes, 0: the opposite way)."""
    if code is HeadingCode.SIN_COS:
        return torch.stack([torch.sin(yaw), torch.cos(yaw)], 1), None
    sin2, cos2 = torch.sin(2 * yaw), torch.cos(2 * yaw)
    direction = (torch.cos(yaw - _axis(sin2, cos2)) > 0).to(yaw.dtype)
    return torch.stack([sin2, cos2], 1), direction


def _conv_bn_relu(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


def _branch(cin: int, hidden: int, cout: int, convs: int) -> nn.Sequential:
    """(convs - 1) x [3x3 conv + BN + ReLU] then a plain 3x3 conv with bias to `cout` channels."""
    layers: list[nn.Module] = []
    c = cin
    for _ in range(convs - 1):
        layers.append(_conv_bn_relu(c, hidden))
        c = hidden
    layers.append(nn.Conv2d(c, cout, 3, padding=1, bias=True))
    return nn.Sequential(*layers)


class CenterHead(nn.Module):
    """Shared 3x3 conv + BN + ReLU, then one separate branch per output. (B, C, H, W) -> HeadOutput."""

    def __init__(self, in_channels: int, cfg: HeadConfig) -> None:
        super().__init__()
        if cfg.head_convs < 1:
            raise ValueError("head_convs must be >= 1 (the last conv is the output layer)")
        self.cfg = cfg
        ch, hid, n = cfg.shared_channels, cfg.head_channels, cfg.head_convs
        self.shared = _conv_bn_relu(in_channels, ch)
        self.heatmap = _branch(ch, hid, len(cfg.class_names), n)
        self.offset = _branch(ch, hid, 2, n)
        self.z = _branch(ch, hid, 1, n)
        self.log_dim = _branch(ch, hid, 3, n)
        self.rot = _branch(ch, hid, rot_channels(cfg.heading), n)
        self.iou = _branch(ch, hid, 1, n)
        self._init_weights()

    def _init_weights(self) -> None:
        for branch in (self.offset, self.z, self.log_dim, self.rot, self.iou):
            for m in branch.modules():
                if isinstance(m, nn.Conv2d):
                    nn.init.kaiming_normal_(m.weight)
                    if m.bias is not None:
                        nn.init.zeros_(m.bias)
        last = self.heatmap[-1]
        assert isinstance(last, nn.Conv2d) and last.bias is not None
        nn.init.constant_(last.bias, HEATMAP_PRIOR_BIAS)

    def branches(self) -> tuple[nn.Sequential, ...]:
        """The six output branches in HeadOutput's field order."""
        return (self.heatmap, self.offset, self.z, self.log_dim, self.rot, self.iou)

    def forward(self, bev: Tensor) -> HeadOutput:
        """bev (B, C, H, W) -> HeadOutput with maps of the same H, W.

        Every branch starts with a 3x3 conv on the same input, so those six convs run as one conv with
        their weights stacked (one pass over the input instead of six; `forward_per_branch` is the twin).
        The maps are float32 under autocast too (decoding bf16 maps would tie neighbouring heatmap peaks).
        """
        x = self.shared(bev)  # (B, shared_channels, H, W)
        entries = [_entry_conv(b) for b in self.branches()]
        bias = [c.bias if c.bias is not None else c.weight.new_zeros(c.out_channels) for c in entries]
        y = F.conv2d(x, torch.cat([c.weight for c in entries]), torch.cat(bias), padding=1)  # (B, sum, H, W)
        parts = y.split([c.out_channels for c in entries], dim=1)
        maps = (_after_entry(b, p) for b, p in zip(self.branches(), parts, strict=True))
        return HeadOutput(*(m.float() for m in maps))  # float32 maps under autocast too: decoding needs them

    def forward_per_branch(self, bev: Tensor) -> HeadOutput:
        """The same as `forward`, each branch on its own (the plain form, for parity tests)."""
        x = self.shared(bev)
        return HeadOutput(*(b(x).float() for b in self.branches()))


def _entry_conv(branch: nn.Sequential) -> nn.Conv2d:
    first = branch[0]
    conv = first[0] if isinstance(first, nn.Sequential) else first
    assert isinstance(conv, nn.Conv2d)
    return conv


def _after_entry(branch: nn.Sequential, y: Tensor) -> Tensor:
    """Run `branch` on `y`, the output of its entry conv: the rest of its first layer, then the others."""
    first = branch[0]
    if isinstance(first, nn.Sequential):  # conv + BN + ReLU
        y = first[1:](y)
    return branch[1:](y)


def local_maxima(hm: Tensor) -> Tensor:
    """(B, K, H, W) -> bool, true where a cell is >= its 8 neighbours: the same as
    `max_pool2d(hm, 3, stride=1, padding=1) == hm`, in 8 shifted comparisons (faster on CPU)."""
    h, w = hm.shape[-2:]
    padded = F.pad(hm, (1, 1, 1, 1), value=float("-inf"))  # (B, K, H + 2, W + 2)
    peak = torch.ones_like(hm, dtype=torch.bool)
    for dy in range(3):
        for dx in range(3):
            if dy != 1 or dx != 1:
                peak &= hm >= padded[..., dy : dy + h, dx : dx + w]
    return peak


@dataclass
class Candidates:
    """Top-k peaks of a batch, before score filtering and NMS."""

    boxes: Tensor  # (B, T, 7) float32
    scores: Tensor  # (B, T) rectified scores
    labels: Tensor  # (B, T) int64
    heat: Tensor  # (B, T) the peak's heatmap score (the threshold's); 0 where top-k ran out of local maxima


def peak_candidates(
    out: HeadOutput, cfg: HeadConfig, bev: BEVConfig, every_cell: Sequence[bool] = ()
) -> Candidates:
    """Local maxima of the class heatmaps (every cell of a class whose `every_cell` is true), the top
    cfg.pre_nms_top_k over all classes, decoded to boxes."""
    hm = torch.sigmoid(out.heatmap.float())  # (B, K, H, W)
    b, k, h, w = hm.shape
    peak = local_maxima(hm)  # (B, K, H, W)
    for c in (c for c, every in enumerate(every_cell) if every):  # device fills: no host copy in a graph
        peak[:, c] = True
    hm = torch.where(peak, hm, torch.zeros_like(hm))
    top = min(cfg.pre_nms_top_k, k * h * w)
    heat, flat = torch.topk(hm.reshape(b, k * h * w), top, dim=1)  # (B, T)
    labels = torch.div(flat, h * w, rounding_mode="floor")  # (B, T)
    pix = flat - labels * (h * w)  # (B, T) index into H * W
    row = torch.div(pix, w, rounding_mode="floor")
    col = pix - row * w
    reg = torch.cat((out.offset, out.z, out.log_dim, out.rot, out.iou), dim=1).float()  # (B, 7 + R, H, W)
    c = reg.shape[1]
    reg = torch.gather(reg.reshape(b, c, h * w), 2, pix[:, None, :].expand(b, c, top))  # (B, 7 + R, T)
    off_x, off_y, z, log_l, log_w, log_h, *rot, iou = reg.unbind(1)  # each (B, T)
    x = bev.x_min + (col.float() + off_x) * bev.cell
    y = bev.y_min + (row.float() + off_y) * bev.cell
    dims = torch.exp(torch.stack((log_l, log_w, log_h), dim=-1))  # (B, T, 3)
    yaw = decode_yaw(rot, cfg.heading)
    boxes = torch.cat((torch.stack((x, y, z), dim=-1), dims, yaw[..., None]), dim=-1)  # (B, T, 7)
    alpha = heat.new_tensor(cfg.iou_rectifier)[labels]  # (B, T)
    iou01 = ((iou + 1.0) * 0.5).clamp(0.0, 1.0)
    scores = heat.pow(1.0 - alpha) * iou01.pow(alpha)  # (B, T)
    return Candidates(boxes, scores, labels, heat)


@torch.no_grad()
def decode(
    out: HeadOutput, cfg: HeadConfig, bev: BEVConfig, every_cell: Sequence[bool] = ()
) -> list[Detections]:
    """Head maps -> one Detections per batch item (float32 boxes, rectified scores, class labels).

    Steps: sigmoid heatmap; keep 3x3 local maxima (every cell of a class whose `every_cell` is true); top
    cfg.pre_nms_top_k over all classes and cells; dims = exp(log_dim), yaw = `decode_yaw`; score =
    hm^(1 - a_c) * ((iou + 1) / 2)^a_c with a_c = cfg.iou_rectifier[c]; drop peaks whose heatmap score
    (before the rectification, as CenterPoint and OpenPCDet do) is below cfg.score_threshold;
    class-specific rotated NMS with cfg.nms_iou on the rectified scores; keep the cfg.post_nms_top_k best.
    Detections are sorted by descending score.
    """
    return select_detections(peak_candidates(out, cfg, bev, every_cell), cfg)


def select_detections(cand: Candidates, cfg: HeadConfig, fast: bool | None = None) -> list[Detections]:
    """The score threshold and class-specific NMS of `decode`, per batch item, on the candidates' device:
    the whole batch in one numba kernel call (`model.ops.nms_numba.class_nms_batch_cpu`: a batch of 32 KITTI
    streams in 1.0 ms against 5.3 item by item), or `select_detections_plain`, its twin, as `fast` says
    (`numba_kernel`: None, the kernel on CPU tensors)."""
    if not numba_kernel("class_nms_batch", cand.boxes.device, fast):
        return select_detections_plain(cand, cfg)
    valid = _peaks(cand.heat, cfg)  # (B, T)
    flat, counts = class_nms_batch_cpu(
        cand.boxes, cand.scores, cand.labels, valid, cfg.nms_iou, cfg.pre_nms_top_k, cfg.post_nms_top_k
    )
    parts = (x.flatten(0, 1)[flat].split(counts.tolist()) for x in (cand.boxes, cand.scores, cand.labels))
    return [Detections(b, s, lab) for b, s, lab in zip(*parts, strict=True)]


def _peaks(heat: Tensor, cfg: HeadConfig) -> Tensor:
    """The candidates that are peaks (heat 0: top-k ran out) at or above the heatmap score threshold."""
    return (heat > 0) & (heat >= cfg.score_threshold)


def select_detections_plain(cand: Candidates, cfg: HeadConfig) -> list[Detections]:
    """`select_detections` item by item with `class_nms` (the reference twin)."""
    result = []
    for i in range(cand.boxes.shape[0]):
        ok = _peaks(cand.heat[i], cfg)  # (T,)
        boxes, scores, labels = cand.boxes[i][ok], cand.scores[i][ok], cand.labels[i][ok]
        keep = class_nms(boxes, scores, labels, cfg.nms_iou, cfg.pre_nms_top_k, cfg.post_nms_top_k)
        result.append(Detections(boxes[keep], scores[keep], labels[keep]))
    return result


# ---- reading the maps at given cells (the training loss and `phim diagnose`) ---------------------------


def gather_cells(maps: Tensor, flat: Tensor) -> Tensor:
    """maps (B, C, H, W), flat (T,) indices into B * H * W -> (T, C)."""
    b, c, h, w = maps.shape
    return maps.permute(0, 2, 3, 1).reshape(b * h * w, c).index_select(0, flat).float()


def regression_at(out: HeadOutput, flat: Tensor) -> Tensor:
    """The regression channels (offset, z, log dims, rot) at flat cells (T,) -> (T, 6 + R)."""
    return gather_cells(torch.cat([out.offset, out.z, out.log_dim, out.rot], 1), flat)


def decoded_boxes(
    reg: Tensor, flat: Tensor, width: int, height: int, bev: BEVConfig, heading: HeadingCode
) -> Tensor:
    """reg (T, 6 + R) predicted at flat cells (T,) -> (T, 7) boxes, decoded as `decode` does."""
    pix = flat % (width * height)
    row, col = pix // width, pix % width
    x = bev.x_min + (col.float() + reg[:, 0]) * bev.cell
    y = bev.y_min + (row.float() + reg[:, 1]) * bev.cell
    dims = torch.exp(reg[:, 3:6].clamp(max=MAX_LOG_DIM))
    yaw = decode_yaw(reg[:, 6:].unbind(1), heading)
    return torch.cat([torch.stack([x, y, reg[:, 2]], 1), dims, yaw[:, None]], 1)
