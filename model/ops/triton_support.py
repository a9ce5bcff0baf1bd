"""What the Triton kernels (model/ops/*_triton.py) need around them: whether they can run here, and the
backward they borrow from their plain-torch twins."""

from __future__ import annotations

import importlib.util
import os
import shutil
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor


def triton_available(device: torch.device) -> bool:
    """Whether the Triton kernels can run on `device`: CUDA, the triton package, and a C compiler (Triton
    builds each kernel's launcher with one at first use; slim images often lack it)."""
    return device.type == "cuda" and _triton_installed()


def _triton_installed() -> bool:
    """Looked up once per process (the sparse convs and scans ask on every call), at import: a plain global
    then, which torch.compile reads as a constant where the fixed-shape step dispatches its scan."""
    return _INSTALLED


def has_c_compiler() -> bool:
    """$CC, gcc or clang on the PATH: the compilers Triton looks for."""
    return any(shutil.which(c) for c in (os.environ.get("CC", ""), "gcc", "clang") if c)


_INSTALLED = importlib.util.find_spec("triton") is not None and has_c_compiler()


def grads_by_recompute(fn: Callable[..., Any], inputs: Sequence[Tensor | None], grad_out: Any) -> list:
    """Backward of a fast forward without its own: run `fn(*inputs)` (its plain-torch twin) again under
    autograd and return the gradients of `inputs` (None for those that need none)."""
    leaves = [None if t is None else t.detach().requires_grad_(t.requires_grad) for t in inputs]
    wrt = [t for t in leaves if t is not None and t.requires_grad]
    if not wrt:
        return [None] * len(leaves)
    with torch.enable_grad():
        grads = iter(torch.autograd.grad(fn(*leaves), wrt, grad_out, allow_unused=True))
    return [next(grads) if t is not None and t.requires_grad else None for t in leaves]
