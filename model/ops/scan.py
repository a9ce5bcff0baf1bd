"""Selective scan dispatch: one entry point over the implementations of `ScanImpl`.

The plain-torch twins (reference loop, chunked) live in `model.ops.scan_torch`, the Triton kernels in
`model.ops.scan_triton` (CUDA only, imported on first use), the numba kernels in `model.ops.scan_numba` (CPU
only); every fast path is held to the reference by tests/test_scan.py and tests/test_cuda.py. The contract
is `scan_torch`'s module docstring.
"""

from __future__ import annotations

import logging

import torch
from torch import Tensor

from model.config import ScanImpl
from model.ops.scan_numba import selective_scan_numba
from model.ops.scan_torch import check_inputs, selective_scan_chunked, selective_scan_ref
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
    cu_seqlens: Tensor,
    h0: Tensor | None = None,
    impl: ScanImpl = ScanImpl.AUTO,
    chunk_size: int = 32,
) -> tuple[Tensor, Tensor]:
    """Dispatch to the implementation `impl`; see the module docstring for the contract. Autocast is off
    inside: the recurrence runs in float32 (`scan_torch.compute_dtype`) whatever region it is called in."""
    impl = resolve_scan(impl, u.device)
    if not scan_available(impl, u.device):
        raise RuntimeError(
            f"selective scan implementation {impl.value!r} is not available on {u.device} "
            "(triton needs a CUDA device, the triton package and a C compiler: gcc, clang or $CC; "
            "numba the CPU)"
        )
    if impl not in _announced:
        _announced.add(impl)
        log.info("selective scan implementation: %s", impl.value)
    with torch.autocast(u.device.type, enabled=False):
        if impl is ScanImpl.REFERENCE:
            return selective_scan_ref(u, delta, A, B, C, cu_seqlens, h0)
        if impl is ScanImpl.CHUNKED:
            return selective_scan_chunked(u, delta, A, B, C, cu_seqlens, h0, chunk_size)
        if impl is ScanImpl.NUMBA:
            return selective_scan_numba(u, delta, A, B, C, cu_seqlens, h0)
        from model.ops.scan_triton import selective_scan_triton

        check_inputs(u, delta, A, B, C, cu_seqlens, h0)
        return selective_scan_triton(u, delta, A, B, C, cu_seqlens, h0, chunk_size)
