"""The fixed-shape step's polar -> BEV scatter-mean (`model.graph.bev`): the numba kernel
(`model.ops.bev_mean_numba`, CPU tensors) or its plain-torch twin, `bev_mean_torch`; the dispatch rule is
`numba_support.numba_kernel`'s. tests/test_graph_bev.py holds them equal (and to the eager module)."""

from __future__ import annotations

import torch
from torch import Tensor

from model.graph.sites import scatter_sum
from model.ops.bev_mean_numba import bev_mean_numba
from model.ops.numba_support import numba_kernel


def bev_mean_torch(feats: Tensor, column: Tensor, valid: Tensor, table: Tensor, ny: int, nx: int) -> Tensor:
    """`bev_mean`'s contract in tensor ops: the scatter runs once per table column d over all rows; a row
    that is padding, or a missing (column, d) entry, goes to a dump cell past the map."""
    b, length, c = feats.shape
    n_cells = b * ny * nx
    column = column.clamp(0, table.shape[0] - 1)  # (B, L)
    cell = table.index_select(0, column.reshape(-1)).view(b, length, -1)  # (B, L, D)
    batch_base = torch.arange(b, device=feats.device).view(b, 1, 1) * (ny * nx)
    cell = torch.where(valid[..., None] & (cell >= 0), cell + batch_base, n_cells).view(-1, cell.shape[2])
    count = torch.zeros(n_cells + 1, dtype=feats.dtype, device=feats.device)  # pairs per cell, + the dump
    scatter_sum(count, cell.reshape(-1), torch.ones_like(cell, dtype=feats.dtype).reshape(-1))
    inv = count.clamp_min(1.0).reciprocal_()  # (B * ny * nx + 1,)
    rows = feats.reshape(b * length, c)  # (B * L, C)
    total = feats.new_zeros(n_cells + 1, c)
    for d in range(cell.shape[1]):  # a few table columns: one scatter pass each
        idx = cell[:, d]  # (B * L,)
        scatter_sum(total, idx, rows * inv.index_select(0, idx)[:, None])
    return total[:n_cells].view(b, ny, nx, c)


def bev_mean(
    feats: Tensor, column: Tensor, valid: Tensor, table: Tensor, ny: int, nx: int, fast: bool | None = None
) -> Tensor:
    """feats (B, L, C), column (B, L) int64 (r * THETA + theta), valid (B, L) bool, table (R * THETA, D) int64
    cell ids, -1 past a column's cells (`model.graph.bev.dense_cell_table`) -> (B, ny, nx, C) in feats'
    dtype: each cell the mean of the valid rows whose column feeds it, zero where none does. `fast`: see
    `numba_kernel`."""
    if numba_kernel("bev_mean", feats.device, fast):
        return bev_mean_numba(feats, column, valid, table, ny, nx)
    return bev_mean_torch(feats, column, valid, table, ny, nx)
