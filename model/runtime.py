"""Process-level tuning for CPU inference, applied by the command-line entry points; device choice; the
recompute-backward helper of the Triton kernels."""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import importlib.util
import logging
import os
import shutil
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

log = logging.getLogger(__name__)

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def tune_malloc() -> bool:
    """Keep large temporaries on glibc's heap instead of mmap/munmap per call (page faults each time).

    Same effect as MALLOC_MMAP_THRESHOLD_ / MALLOC_TRIM_THRESHOLD_ in the environment. Returns whether it
    applied (False on a libc without mallopt).
    """
    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        ok = libc.mallopt(_M_MMAP_THRESHOLD, 32 * 1024 * 1024) and libc.mallopt(_M_TRIM_THRESHOLD, 1 << 30)
    except (OSError, AttributeError):
        return False
    log.debug("mallopt applied: %s", bool(ok))
    return bool(ok)


def pick_device(name: str) -> torch.device:
    """'auto' -> cuda if available else cpu; otherwise the named device, which must exist."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device {name!r} requested but CUDA is not available")
    return dev


def triton_available(device: torch.device) -> bool:
    """Whether the Triton kernels (model/*_triton.py) can run on `device`: CUDA, the triton package, and a
    C compiler (Triton builds each kernel's launcher with one at first use; slim images often lack it)."""
    return device.type == "cuda" and _triton_installed()


@functools.cache
def _triton_installed() -> bool:  # looked up once per process: the sparse convs and scans ask on every call
    return importlib.util.find_spec("triton") is not None and has_c_compiler()


def has_c_compiler() -> bool:
    """$CC, gcc or clang on the PATH: the compilers Triton looks for."""
    return any(shutil.which(c) for c in (os.environ.get("CC", ""), "gcc", "clang") if c)


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
