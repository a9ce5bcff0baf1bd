"""The sparse convs over neighbour tables as a CPU kernel that multiplies only the table's entries naming a
row, a torch custom op: the fast twin of `model.graph.sparse_conv.conv_gemm` (the implicit GEMM).

The implicit GEMM multiplies every (row, kernel offset) entry of a table, and most are empty: in a `tiny`
step on KITTI 9-36 % name a row, so it does three to ten times the FLOPs the conv needs. Here one pass
(numba) gathers the input rows of the entries naming a row, offset by offset; per offset one matmul by
that offset's weight (aten, both threads); one pass writes the bias and adds the products. The output
keeps its fixed shape (cap_out, C_out); only the work inside varies with the data, which on the CPU costs
no wait. On CUDA the implicit GEMM stays: there the entry count would be a data-dependent size (a host
sync, or one more capacity). The sums run in float32 (float64 for float64 features) and come back in the
features' dtype.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor


@numba.njit(cache=True, nogil=True)
def _gather_pairs(table, none, x, rows, outs, ends):  # pragma: no cover - compiled
    """table (cap_out, KK) int64, `none` its entry for no row, x (cap_in, C). Lists the entries naming a row,
    offset by offset: writes rows[p] = x[the input row], outs[p] = the output row, ends[k] = the end of
    offset k's entries; returns their count P."""
    cap_out, kk = table.shape
    p = 0
    for k in range(kk):
        for o in range(cap_out):
            i = table[o, k]
            if i != none:
                for c in range(x.shape[1]):  # an explicit loop: numba's row assignment is slower
                    rows[p, c] = x[i, c]
                outs[p] = o
                p += 1
        ends[k] = p
    return p


@numba.njit(cache=True, nogil=True)
def _add_rows(y, outs, bias, out):  # pragma: no cover - compiled
    """out[o] = bias for every row, then out[outs[p]] += y[p] for every p: y (P, C), outs (P,) int64, bias
    (C,), out (cap_out, C)."""
    for o in range(out.shape[0]):
        for c in range(out.shape[1]):
            out[o, c] = bias[c]
    for p in range(y.shape[0]):
        o = outs[p]
        for c in range(y.shape[1]):
            out[o, c] += y[p, c]


@torch.library.custom_op("phim::conv_pairs", mutates_args=(), device_types="cpu")
def conv_pairs(x: Tensor, table: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
    """`conv_gemm`'s contract: x (cap_in, C_in), table (cap_out, KK) in [0, cap_in] (cap_in: none), weight
    (KK, C_in, C_out), bias (C_out,) or None -> (cap_out, C_out) in x's dtype."""
    cap_out, kk = table.shape
    cd = torch.float64 if x.dtype == torch.float64 else torch.float32
    rows = torch.empty(cap_out * kk, x.shape[1], dtype=cd)  # (cap_out * KK, C_in): the first P used
    outs = np.empty(cap_out * kk, dtype=np.int64)
    ends = np.empty(kk, dtype=np.int64)
    n = _gather_pairs(
        table.contiguous().numpy(), x.shape[0], x.to(cd).contiguous().numpy(), rows.numpy(), outs, ends
    )
    w = weight.to(cd)
    y = rows.new_empty(n, w.shape[2])  # (P, C_out)
    first = 0
    for k, end in enumerate(ends.tolist()):  # numpy: no device to wait for
        if end > first:
            torch.mm(rows[first:end], w[k], out=y[first:end])
        first = end
    b = torch.zeros(w.shape[2], dtype=cd) if bias is None else bias.to(cd).contiguous()  # (C_out,)
    out = torch.empty(cap_out, w.shape[2], dtype=cd)  # (cap_out, C_out)
    _add_rows(y.numpy(), outs[:n], b.numpy(), out.numpy())
    return out.to(x.dtype)


@conv_pairs.register_fake
def _(x, table, weight, bias):
    return x.new_empty(table.shape[0], weight.shape[2])
