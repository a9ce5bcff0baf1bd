"""Sparse conv gather -> matmul -> scatter-add dispatch: the fused Triton kernel where it can run, else the
plain-torch twin (tests/test_sparse_conv.py and tests/test_cuda.py hold them to each other)."""

from __future__ import annotations

import logging

import torch
from torch import Tensor

from model.ops.sparse_conv_torch import gather_mm_scatter_torch
from model.ops.triton_support import triton_available

log = logging.getLogger(__name__)
_announced: set[bool] = set()  # which gather_mm_scatter paths have been logged


def gather_mm_scatter(
    src: Tensor,
    weight: Tensor,
    src_idx: Tensor,
    dst_idx: Tensor,
    ptr: tuple[int, ...],
    n_dst: int,
    identity_offset: int | None = None,
    fused: bool | None = None,
) -> Tensor:
    """dst[dst_idx[j]] += src[src_idx[j]] @ weight[k] for every pair j of offset k.

    src (N_src, C_in), weight (KK, C_in, C_out), src_idx / dst_idx (P,) -> (n_dst, C_out). The pairs of
    `identity_offset`, if given, must be (i, i) for every row (N_src == n_dst): that offset is one matmul.
    Gathering per offset keeps each gathered block in cache for its matmul.

    `fused` (None: wherever it can run, i.e. float32 on CUDA with Triton): one Triton launch for all offsets
    (model/ops/sparse_conv_triton.py) instead of `gather_mm_scatter_torch`, its plain-torch twin. The log
    says which runs.
    """
    if fused is None:
        fused = triton_available(src.device) and src.dtype == weight.dtype == torch.float32
    fused = fused and src_idx.numel() > 0  # no pairs: nothing to launch
    if fused not in _announced:
        _announced.add(fused)
        log.info("sparse conv gather-matmul-scatter: %s", "triton" if fused else "torch")
    if fused:
        from model.ops.sparse_conv_triton import gather_mm_scatter_triton

        return gather_mm_scatter_triton(src, weight, src_idx, dst_idx, ptr, n_dst, identity_offset)
    return gather_mm_scatter_torch(src, weight, src_idx, dst_idx, ptr, n_dst, identity_offset)
