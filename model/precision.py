"""Inference precision (`model.config.Precision`): the context a streaming step's forward runs under.

FP32 runs as written. BF16 runs under torch.autocast(dtype=torch.bfloat16): matmuls, linears and convs take
bf16-rounded inputs (float32 weights cast on the fly) and accumulate in float32; elementwise ops keep their
input dtype. The parts that must stay float32 do so by construction: the selective scan computes its
recurrence in float32 (`model.ops.scan_torch.compute_dtype`, autocast off inside `model.ops.scan`), the
sparse convs' scatter-add sums in the features' dtype (float32), the head's maps are cast to float32 before
decoding, and the Mamba states keep float32.
"""

from __future__ import annotations

import contextlib
import logging

import torch

from model.config import Precision

log = logging.getLogger(__name__)

AUTOCAST_DEVICES = ("cpu", "cuda")


def check_precision(precision: Precision, device: torch.device) -> None:
    """ValueError if `precision` cannot run on `device`; a logged warning where it runs but slowly (bf16 on
    a CPU: meant for CUDA, and slow on CPUs without AMX)."""
    if precision is Precision.FP32:
        return
    if device.type not in AUTOCAST_DEVICES:
        raise ValueError(f"precision {precision.value}: runs on cpu or cuda, not on {device}")
    if device.type == "cuda" and not torch.cuda.is_bf16_supported():
        raise ValueError(f"precision {precision.value}: {torch.cuda.get_device_name(device)} has no bfloat16")
    if device.type == "cpu":
        log.warning(
            "precision %s on the CPU: meant for CUDA; slower than fp32 on CPUs without AMX", precision.value
        )


def autocast(precision: Precision, device: torch.device) -> contextlib.AbstractContextManager:
    """The context a forward runs under: nothing for FP32, torch.autocast to bfloat16 for BF16."""
    if precision is Precision.FP32:
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=torch.bfloat16)
