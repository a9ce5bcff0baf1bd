"""A sparse conv over a neighbour table (the fixed-shape step's convs, `model.graph.sparse_conv`): the numba
kernel that multiplies only the entries naming a row (`model.ops.table_conv_numba`, CPU tensors) or its
plain-torch twin, the implicit GEMM (also the CUDA path: there the entry count would be a data-dependent
size); the dispatch rule is `numba_support.numba_kernel`'s. tests/test_graph_sparse.py holds them equal."""

from __future__ import annotations

import torch
from torch import Tensor

from model.ops.numba_support import numba_kernel
from model.ops.table_conv_numba import table_conv_numba


def table_conv_torch(x: Tensor, table: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
    """`table_conv`'s contract as the implicit GEMM: one gather and one matmul over every entry."""
    cap_out, kk = table.shape
    c_in, c_out = weight.shape[1], weight.shape[2]
    ext = torch.cat((x, x.new_zeros(1, c_in)))  # (cap_in + 1, C_in)
    cols = ext.index_select(0, table.view(-1)).view(cap_out, kk * c_in)  # (cap_out, KK * C_in)
    w = weight.reshape(kk * c_in, c_out)
    return cols @ w if bias is None else torch.addmm(bias, cols, w)


def table_conv(
    x: Tensor, table: Tensor, weight: Tensor, bias: Tensor | None, fast: bool | None = None
) -> Tensor:
    """x (cap_in, C_in), table (cap_out, KK) with entries in [0, cap_in], weight (KK, C_in, C_out), bias
    (C_out,) or None -> (cap_out, C_out): out[o] = sum_k weight[k]^T x[table[o, k]] (+ bias), where
    x[cap_in] is a zero row (cap_in: no input row). `fast`: see `numba_kernel`."""
    if numba_kernel("table_conv", x.device, fast):
        return table_conv_numba(x, table, weight, bias)
    return table_conv_torch(x, table, weight, bias)
