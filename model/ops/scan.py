"""Selective scan dispatch: one entry point over the four implementations of `ScanImpl`, for both engines.

Every implementation scans a segmented pack (`model.ops.segments.Segments`: the fixed-shape step's padded
packs) or packed sequences with initial states (cu_seqlens: the eager layers), one the special case of the
other. The plain-torch twins (reference loop, chunked) live in `model.ops.scan_torch`, the Triton kernels in
`model.ops.scan_triton` (CUDA only, imported on first use), the numba kernels in `model.ops.scan_numba` (CPU
only); the fast ones are torch custom ops with their backward, so torch.compile calls them as one op and
training differentiates through them. Every fast path is held to the reference by tests/test_scan.py,
tests/test_graph_mamba.py, tests/test_ops_scan_triton.py and tests/test_cuda.py. The contract is
`scan_torch`'s module docstring.
"""

from __future__ import annotations

import logging

import torch
from torch import Tensor

from model.config import ScanImpl
from model.ops.scan_numba import selective_scan_numba
from model.ops.scan_torch import compute_dtype, selective_scan_chunked, selective_scan_ref
from model.ops.segments import Segments
from model.ops.triton_support import triton_available

log = logging.getLogger(__name__)
_announced: set[ScanImpl] = set()


def scan_available(impl: ScanImpl, device: torch.device) -> bool:
    """Whether `impl` can run on `device`: TRITON needs CUDA and the triton package, NUMBA the CPU."""
    if impl is ScanImpl.TRITON:
        return triton_available(device)
    return device.type == "cpu" if impl is ScanImpl.NUMBA else True


def resolve_scan(impl: ScanImpl, device: torch.device) -> ScanImpl:
    """AUTO -> TRITON where it is available, NUMBA on the CPU, else CHUNKED; any other choice stays."""
    if impl is not ScanImpl.AUTO:
        return impl
    for fast in (ScanImpl.TRITON, ScanImpl.NUMBA):
        if scan_available(fast, device):
            return fast
    return ScanImpl.CHUNKED


def selective_scan(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    seqs: Tensor | Segments,
    h0: Tensor | None = None,
    impl: ScanImpl = ScanImpl.AUTO,
    chunk_size: int = 32,
) -> tuple[Tensor, Tensor]:
    """Dispatch to the implementation `impl`; seqs: cu_seqlens (S + 1,) or Segments; see the module docstring
    for the contract. Autocast is off inside: the recurrence runs in float32 (`scan_torch.compute_dtype`)
    whatever region it is called in. The Triton kernels compute in float32: float64 inputs (tests) run the
    chunked twin there."""
    impl = resolve_scan(impl, u.device)
    if not scan_available(impl, u.device):
        raise RuntimeError(
            f"selective scan implementation {impl.value!r} is not available on {u.device} "
            "(triton needs a CUDA device, the triton package and a C compiler: gcc, clang or $CC; "
            "numba the CPU)"
        )
    if impl is ScanImpl.TRITON and compute_dtype(u, delta, A, B, C) == torch.float64:
        impl = ScanImpl.CHUNKED
    if not torch.compiler.is_compiling() and impl not in _announced:
        _announced.add(impl)
        log.info("selective scan implementation: %s", impl.value)
    with torch.autocast(u.device.type, enabled=False):
        if impl is ScanImpl.REFERENCE:
            return selective_scan_ref(u, delta, A, B, C, seqs, h0)
        if impl is ScanImpl.CHUNKED:
            return selective_scan_chunked(u, delta, A, B, C, seqs, h0, chunk_size)
        if impl is ScanImpl.NUMBA:
            return selective_scan_numba(u, delta, A, B, C, seqs, h0)
        from model.ops.scan_triton import selective_scan_triton

        return selective_scan_triton(u, delta, A, B, C, seqs, h0)
