"""One training forward: a batch of scans, each encoded as one stream, predicted at every buffer fill level.

`TrainStep` is a module whose forward returns the loss, so DDP can wrap it (DDP syncs gradients through
`forward`; the detector's own entry points are `encode` and `predict`).
"""

from __future__ import annotations

import torch
from torch import nn

from model.detector import PHiM
from model.layers.phim_block import StreamLayout
from model.train.data import TrainSample
from model.train.loss import LossConfig, LossParts, center_loss


class TrainStep(nn.Module):
    def __init__(self, model: PHiM, loss: LossConfig):
        super().__init__()
        self.model = model
        self.loss_cfg = loss

    def forward(self, batch: list[TrainSample]) -> LossParts:
        m = self.model
        dev = m.device
        points = [p.to(dev, non_blocking=True) for s in batch for p in s.sectors]  # B * S sectors
        per_scan = [len(s.sectors) for s in batch]
        stream = torch.repeat_interleave(
            torch.arange(len(batch), device=dev), torch.tensor(per_scan, device=dev)
        )
        enc = m.encode(points, StreamLayout(stream, len(batch)), m.init_states(len(batch)))
        scenes, targets, first = [], [], 0
        for s, n in zip(batch, per_scan, strict=True):
            own = enc.sectors[first : first + n]
            scenes += [own[: k + 1] for k in range(n)]  # fill levels 0 .. n-1 buffered sectors
            targets += s.targets
            first += n
        out = m.predict(scenes)
        return center_loss(out, targets, m.cfg.bev, m.cfg.head.heading, self.loss_cfg)
