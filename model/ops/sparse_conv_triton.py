"""Gather -> matmul -> scatter of a sparse conv in one Triton launch (CUDA): the fast twin of
`sparse_conv_torch.gather_mm_scatter_torch`.

The rule book's pairs are grouped by kernel offset. They are cut into blocks of BLOCK_P pairs that never
straddle two offsets (a table made on the host from the offsets' pair counts, which the host already
holds); one program per (block, output-channel tile) gathers its source rows, multiplies them by its
offset's weight (float32 in, float32 sums: input_precision "ieee", no tf32) and adds the products to the
destination rows with atomic adds. Atomic adds sum in no fixed order, so results can differ from the torch
path and from run to run in the last bits. The identity offset, if any, is one dense matmul before.

Backward recomputes through the torch path, as the Triton scan does.
"""

from __future__ import annotations

import numpy as np
import torch
import triton
import triton.language as tl
from torch import Tensor

from model.ops.sparse_conv_torch import gather_mm_scatter_torch
from model.ops.triton_support import grads_by_recompute

BLOCK_P = 64  # pairs per program


@triton.jit
def _gms_kernel(
    src_ptr, w_ptr, out_ptr,  # (N_src, C_in), (KK, C_in, C_out), (n_dst, C_out)
    src_idx_ptr, dst_idx_ptr,  # (P,) pairs grouped by offset
    blk_k_ptr, blk_lo_ptr, blk_hi_ptr,  # (NB,) each block's offset and pair range
    C_in, C_out,
    BLOCK_P: tl.constexpr, BLOCK_CI: tl.constexpr, BLOCK_CO: tl.constexpr,
):  # fmt: skip
    b = tl.program_id(0)
    co = tl.program_id(1) * BLOCK_CO + tl.arange(0, BLOCK_CO)  # (BCO,)
    k = tl.load(blk_k_ptr + b).to(tl.int64)
    lo = tl.load(blk_lo_ptr + b)
    hi = tl.load(blk_hi_ptr + b)
    p = lo + tl.arange(0, BLOCK_P)  # (BP,)
    pm = p < hi
    si = tl.load(src_idx_ptr + p, mask=pm, other=0).to(tl.int64)
    di = tl.load(dst_idx_ptr + p, mask=pm, other=0).to(tl.int64)
    com = co < C_out
    acc = tl.zeros((BLOCK_P, BLOCK_CO), dtype=tl.float32)
    for c0 in range(0, C_in, BLOCK_CI):
        ci = c0 + tl.arange(0, BLOCK_CI)  # (BCI,)
        cim = ci < C_in
        x = tl.load(src_ptr + si[:, None] * C_in + ci[None, :], mask=pm[:, None] & cim[None, :], other=0.0)
        w_off = k * C_in * C_out + ci[:, None] * C_out + co[None, :]
        w = tl.load(w_ptr + w_off, mask=cim[:, None] & com[None, :], other=0.0)
        acc += tl.dot(x, w, input_precision="ieee")
    tl.atomic_add(out_ptr + di[:, None] * C_out + co[None, :], acc, mask=pm[:, None] & com[None, :])


def _block_table(ptr: tuple[int, ...], skip: int | None, device: torch.device) -> Tensor:
    """(3, NB) int64: offset, first pair, end pair of every block of at most BLOCK_P pairs of one offset."""
    bounds = np.asarray(ptr, dtype=np.int64)
    counts = np.diff(bounds)  # (KK,)
    if skip is not None:
        counts[skip] = 0
    n_blocks = (counts + BLOCK_P - 1) // BLOCK_P  # (KK,)
    k = np.repeat(np.arange(counts.size), n_blocks)  # (NB,)
    first_block = np.cumsum(n_blocks) - n_blocks  # (KK,)
    lo = bounds[k] + (np.arange(k.size) - first_block[k]) * BLOCK_P
    hi = np.minimum(lo + BLOCK_P, bounds[k + 1])
    return torch.from_numpy(np.stack([k, lo, hi])).to(device)  # one host-to-device copy


def _launch(src: Tensor, weight: Tensor, src_idx: Tensor, dst_idx: Tensor, ptr, out: Tensor, skip) -> None:
    table = _block_table(ptr, skip, src.device)
    n_blocks = table.shape[1]
    if n_blocks == 0:
        return
    c_in, c_out = weight.shape[1], weight.shape[2]
    block_co = max(16, min(128, triton.next_power_of_2(c_out)))
    block_ci = max(16, min(32, triton.next_power_of_2(c_in)))
    grid = (n_blocks, triton.cdiv(c_out, block_co))
    _gms_kernel[grid](
        src, weight, out, src_idx, dst_idx, table[0], table[1], table[2], c_in, c_out,
        BLOCK_P=BLOCK_P, BLOCK_CI=block_ci, BLOCK_CO=block_co, num_warps=4,
    )  # fmt: skip


class TritonGatherMMScatter(torch.autograd.Function):
    """Forward on the Triton kernel; backward through the torch path, recomputed."""

    @staticmethod
    def forward(ctx, src, weight, src_idx, dst_idx, ptr, n_dst, ident):  # type: ignore[override]
        ctx.save_for_backward(src, weight, src_idx, dst_idx)
        ctx.ptr, ctx.n_dst, ctx.ident = ptr, n_dst, ident
        src_c, w_c = src.contiguous(), weight.detach().contiguous()
        out = src_c.new_zeros(n_dst, w_c.shape[2]) if ident is None else (src_c @ w_c[ident]).to(src.dtype)
        _launch(src_c, w_c, src_idx.contiguous(), dst_idx.contiguous(), ptr, out, ident)
        return out

    @staticmethod
    def backward(ctx, g_out):  # type: ignore[override]
        src, weight, src_idx, dst_idx = ctx.saved_tensors

        def twin(src, weight):
            return gather_mm_scatter_torch(src, weight, src_idx, dst_idx, ctx.ptr, ctx.n_dst, ctx.ident)

        g_src, g_w = grads_by_recompute(twin, (src, weight), g_out)
        return g_src, g_w, None, None, None, None, None


def gather_mm_scatter_triton(
    src: Tensor, weight: Tensor, src_idx: Tensor, dst_idx: Tensor, ptr, n_dst: int, ident: int | None
) -> Tensor:
    """Same contract as `sparse_conv_torch.gather_mm_scatter_torch`, for float32 CUDA tensors."""
    return TritonGatherMMScatter.apply(src, weight, src_idx, dst_idx, ptr, n_dst, ident)
