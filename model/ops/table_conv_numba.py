"""The sparse convs over neighbour tables as a CPU kernel that multiplies only the table's entries naming a
row, a torch custom op: the fast twin of `model.ops.table_conv.table_conv_torch` (the implicit GEMM).

The implicit GEMM multiplies every (row, kernel offset) entry of a table, and most are empty: in a `tiny`
step on KITTI 9-36 % name a row, so it does three to ten times the FLOPs the conv needs. Here one pass
(numba) gathers the input rows of the entries naming a row, offset by offset; per offset one matmul by
that offset's weight (aten, both threads); one pass adds the products to the bias. The output
keeps its fixed shape (cap_out, C_out); only the work inside varies with the data, which on the CPU costs
no wait. A submanifold conv's centre offset maps row o to row o for every site (the sites fill the first
rows): where the table's middle column is that prefix, its products are one addmm straight from x into
the output (which starts as the bias), with no gather or add (a fifth of a `tiny` step's entries). On CUDA
the implicit GEMM stays: there the entry count would be a data-dependent size (a host sync, or one more
capacity). The sums run in float32 (float64 for float64 features) and come back in the
features' dtype.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor


@numba.njit(cache=True, nogil=True)
def _identity_prefix(table, none, k):  # pragma: no cover - compiled
    """n if table[o, k] == o for o < n and none for o >= n (a submanifold conv's centre offset), else -1."""
    n = 0
    while n < min(table.shape[0], none) and table[n, k] == n:  # none = cap_in: o < cap_in is a row of x
        n += 1
    for o in range(n, table.shape[0]):
        if table[o, k] != none:
            return -1
    return n


@numba.njit(cache=True, nogil=True)
def _gather_pairs(table, none, x, skip, rows, outs, ends):  # pragma: no cover - compiled
    """table (cap_out, KK) int64, `none` its entry for no row, x (cap_in, C), `skip` an offset to leave out
    (-1: none). Lists the entries naming a row, offset by offset: writes rows[p] = x[the input row], outs[p]
    = the output row, ends[k] = the end of offset k's entries; returns their count P."""
    cap_out, kk = table.shape
    p = 0
    for k in range(kk):
        if k != skip:
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
def _add_rows(y, outs, out):  # pragma: no cover - compiled
    """out[outs[p]] += y[p] for every p: y (P, C), outs (P,) int64, out (cap_out, C)."""
    for p in range(y.shape[0]):
        o = outs[p]
        for c in range(y.shape[1]):
            out[o, c] += y[p, c]


@torch.library.custom_op("phim::table_conv", mutates_args=(), device_types="cpu")
def table_conv_numba(x: Tensor, table: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
    """`table_conv`'s contract: x (cap_in, C_in), table (cap_out, KK) in [0, cap_in] (cap_in: none), weight
    (KK, C_in, C_out), bias (C_out,) or None -> (cap_out, C_out) in x's dtype."""
    cap_out, kk = table.shape
    cd = torch.float64 if x.dtype == torch.float64 else torch.float32
    t, xc = table.contiguous().numpy(), x.to(cd).contiguous()  # (cap_out, KK), (cap_in, C_in)
    w = weight.to(cd)  # (KK, C_in, C_out)
    b = torch.zeros(w.shape[2], dtype=cd) if bias is None else bias.to(cd)  # (C_out,)
    centre = kk // 2 if kk % 2 else -1
    n = _identity_prefix(t, x.shape[0], centre) if centre >= 0 else -1  # rows o < n: x[o] through centre
    out = torch.empty(cap_out, w.shape[2], dtype=cd)  # (cap_out, C_out)
    if n >= 0:
        torch.addmm(b, xc[:n], w[centre], out=out[:n])
        out[n:] = b
    else:
        out[:] = b
    skip = centre if n >= 0 else -1
    rows = torch.empty(cap_out * kk, x.shape[1], dtype=cd)  # (cap_out * KK, C_in): the first P used
    outs = np.empty(cap_out * kk, dtype=np.int64)
    ends = np.empty(kk, dtype=np.int64)
    p = _gather_pairs(t, x.shape[0], xc.numpy(), skip, rows.numpy(), outs, ends)
    y = rows.new_empty(p, w.shape[2])  # (P, C_out)
    first = 0
    for k, end in enumerate(ends.tolist()):  # numpy: no device to wait for
        if end > first:
            torch.mm(rows[first:end], w[k], out=y[first:end])
        first = end
    _add_rows(y.numpy(), outs[:p], out.numpy())
    return out.to(x.dtype)


@table_conv_numba.register_fake
def _(x, table, weight, bias):
    return x.new_empty(table.shape[0], weight.shape[2])
