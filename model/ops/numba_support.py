"""What the numba kernels (model/ops/*_numba.py) need around them: where they run, and the one dispatch rule
every op with a numba kernel follows (as `triton_support` for the Triton kernels)."""

from __future__ import annotations

import logging

import torch

log = logging.getLogger(__name__)
_announced: set[tuple[str, bool]] = set()  # (op, kernel) pairs logged so far


def numba_kernel(op: str, device: torch.device, fast: bool | None = None) -> bool:
    """Whether `op` runs its numba kernel on tensors of `device`: `fast` None (the default of every op's
    dispatch function) -> wherever it can run, i.e. on CPU tensors; False -> the plain-torch twin; True ->
    the kernel, which exists for CPU tensors only. The first choice of each op is logged (outside a traced
    region: the fixed-shape step calls the ops under torch.compile(fullgraph=True))."""
    use = device.type == "cpu" if fast is None else fast
    if use and device.type != "cpu":
        raise RuntimeError(f"{op}: the numba kernel runs on CPU tensors only, got {device}")
    if not torch.compiler.is_compiling() and (op, use) not in _announced:
        _announced.add((op, use))
        log.info("%s: %s", op, "numba" if use else "torch")
    return use
