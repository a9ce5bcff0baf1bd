"""The sparse convs' gather -> matmul -> scatter-add in plain torch: the reference twin of the fused Triton
kernel (`model.ops.sparse_conv_triton`); `model.ops.sparse_conv.gather_mm_scatter` picks one."""

from __future__ import annotations

from torch import Tensor


def gather_mm_scatter_torch(
    src: Tensor,
    weight: Tensor,
    src_idx: Tensor,
    dst_idx: Tensor,
    ptr: tuple[int, ...],
    n_dst: int,
    identity_offset: int | None = None,
) -> Tensor:
    """dst[dst_idx[j]] += src[src_idx[j]] @ weight[k] for every pair j of offset k: one gather and one matmul
    per kernel offset (each gathered block stays in cache for its matmul). Contract: `gather_mm_scatter`."""
    ident = identity_offset
    # products are cast back to src's dtype: under autocast they come out in bf16, the sums stay float32
    out = src.new_zeros(n_dst, weight.shape[2]) if ident is None else (src @ weight[ident]).to(src.dtype)
    for k in range(weight.shape[0]):
        lo, hi = ptr[k], ptr[k + 1]
        if hi > lo and k != ident:
            out.index_add_(0, dst_idx[lo:hi], (src.index_select(0, src_idx[lo:hi]) @ weight[k]).to(src.dtype))
    if src_idx.numel() == 0:  # keep the graph connected to the inputs and weights for empty inputs
        out = out + src.sum() * weight.sum() * 0.0
    return out
