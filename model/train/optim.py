"""The optimizer: AdamW with weight decay on weight matrices and kernels only.

No decay on biases, on normalisation scales (LayerNorm, BatchNorm: every 1-D parameter) and on the
parameters a layer marks `_no_weight_decay` (Mamba's A_log and D, model/layers/mamba.py): decaying A_log
pulls every state's A = -exp(A_log) toward -1, erasing the spread of time scales its initialisation gives
(A = -1 .. -n), and D toward no skip connection; that regularises the recurrence itself, not the fit (Mamba
keeps both out of decay). The paper's recipe: AdamW, weight decay 0.05 (TrainConfig.weight_decay).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn


def decays(p: nn.Parameter) -> bool:
    """Whether weight decay applies to `p`: a matrix or kernel (2-D and up) not marked `_no_weight_decay`."""
    return p.ndim >= 2 and not getattr(p, "_no_weight_decay", False)


def param_groups(model: nn.Module, weight_decay: float) -> list[dict[str, Any]]:
    """Two AdamW groups: the parameters that decay (with `weight_decay`), the others (0)."""
    params = [p for p in model.parameters() if p.requires_grad]
    return [
        {"params": [p for p in params if decays(p)], "weight_decay": weight_decay},
        {"params": [p for p in params if not decays(p)], "weight_decay": 0.0},
    ]


def make_optimizer(model: nn.Module, lr: float, weight_decay: float) -> torch.optim.AdamW:
    return torch.optim.AdamW(param_groups(model, weight_decay), lr=lr)
