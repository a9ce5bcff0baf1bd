"""PillarNeXt-style residual 2D BEV backbone (the structure of OpenPCDet's BaseBEVResBackbone, as used by
Voxel Mamba's Waymo config and hence by PHiM).

Stage i: a BasicBlock with stride layer_strides[i] and a 1x1 conv + BN projection shortcut (as in
BaseBEVResBackbone, the first block of every stage projects, even when the shape is unchanged), then
layer_nums[i] identity-shortcut BasicBlocks. BasicBlock: 3x3 conv (stride s) -> BN -> ReLU -> 3x3 conv -> BN,
plus the shortcut, then ReLU. Each stage's output is brought back to the input resolution by a deblock
(ConvTranspose2d with kernel = stride = upsample_strides[i], or a 1x1 conv when that stride is 1) -> BN ->
ReLU with num_upsample_filters[i] channels; the deblocks' outputs are concatenated. Convs have no bias;
BN eps 1e-3, momentum 0.01.

Input sizes need not be divisible by the total stride: each deblock output is cropped (or zero-padded) to the
input's H x W, so the output always has the input's spatial size. All ops work in channels_last layout.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from model.config import BEVConfig

BN_EPS, BN_MOMENTUM = 1e-3, 0.01


def _bn(channels: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(channels, eps=BN_EPS, momentum=BN_MOMENTUM)


class BasicBlock(nn.Module):
    """Residual block: (B, c_in, H, W) -> (B, c_out, ceil(H / stride), ceil(W / stride))."""

    def __init__(self, c_in: int, c_out: int, stride: int = 1, project: bool = False):
        super().__init__()
        if not project and (c_in != c_out or stride != 1):
            raise ValueError("BasicBlock: an identity shortcut needs c_in == c_out and stride 1")
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False)
        self.bn1 = _bn(c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, padding=1, bias=False)
        self.bn2 = _bn(c_out)
        self.shortcut = (
            nn.Sequential(nn.Conv2d(c_in, c_out, 1, stride=stride, bias=False), _bn(c_out))
            if project
            else None
        )

    def forward(self, x: Tensor) -> Tensor:
        out = torch.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        identity = x if self.shortcut is None else self.shortcut(x)
        return torch.relu(out + identity)


def _deblock(c_in: int, c_out: int, stride: int) -> nn.Sequential:
    """Upsample by `stride` >= 1 to c_out channels: (B, c_in, h, w) -> (B, c_out, h * stride, w * stride)."""
    if stride == 1:
        up: nn.Module = nn.Conv2d(c_in, c_out, 1, bias=False)
    else:
        up = nn.ConvTranspose2d(c_in, c_out, stride, stride=stride, bias=False)
    return nn.Sequential(up, _bn(c_out), nn.ReLU(inplace=True))


def _fit(x: Tensor, height: int, width: int) -> Tensor:
    """Crop the bottom/right of (B, C, h, w), or zero-pad it, to (B, C, height, width)."""
    x = x[:, :, :height, :width]
    pad_h, pad_w = height - x.shape[2], width - x.shape[3]
    return F.pad(x, (0, pad_w, 0, pad_h)) if pad_h or pad_w else x


class BEVBackbone(nn.Module):
    """(B, in_channels, H, W) -> (B, out_channels, H, W), out_channels = sum(cfg.num_upsample_filters)."""

    def __init__(self, in_channels: int, cfg: BEVConfig):
        super().__init__()
        n = len(cfg.layer_nums)
        lengths = {len(cfg.layer_strides), len(cfg.num_filters), len(cfg.upsample_strides)}
        if lengths | {len(cfg.num_upsample_filters)} != {n}:
            raise ValueError(
                "BEVConfig: layer_nums, layer_strides, num_filters and the upsample lists differ in length"
            )
        if any(s < 1 for s in (*cfg.layer_strides, *cfg.upsample_strides)):
            raise ValueError("BEVConfig: layer_strides and upsample_strides must be >= 1")
        stages, deblocks, c_in = [], [], in_channels
        for i in range(n):
            c = cfg.num_filters[i]
            blocks = [BasicBlock(c_in, c, cfg.layer_strides[i], project=True)]
            blocks += [BasicBlock(c, c) for _ in range(cfg.layer_nums[i])]
            stages.append(nn.Sequential(*blocks))
            deblocks.append(_deblock(c, cfg.num_upsample_filters[i], cfg.upsample_strides[i]))
            c_in = c
        self.stages = nn.ModuleList(stages)
        self.deblocks = nn.ModuleList(deblocks)
        self.out_channels = sum(cfg.num_upsample_filters)

    def forward(self, x: Tensor) -> Tensor:
        """x: (B, C_in, H, W) -> (B, out_channels, H, W)."""
        height, width = x.shape[2], x.shape[3]
        ups = []
        for stage, deblock in zip(self.stages, self.deblocks, strict=True):
            x = stage(x)
            ups.append(_fit(deblock(x), height, width))
        return torch.cat(ups, dim=1)
