"""Polar -> Cartesian BEV scatter-mean of fixed shape: the twin of `model.layers.polar_bev.PolarToBEV`.

The eager module expands every voxel to its (voxel, cell) pairs with a CSR table whose pair count depends on
the data. Here the table is dense: (R * THETA, D) cells per column, D = the largest number of cells a column
feeds (3 in `tiny`, 4 in `paper`), -1 where a column feeds fewer. The scatter runs once per table column d
over all rows; a row that is padding, or a missing (column, d) entry, goes to a dump cell past the map.
Each cell is the mean of the features of the (voxel, cell) pairs landing in it, as in the eager module.
On the CPU the step runs the same through a kernel (`polar_to_bev`, `model.graph.bev_cpu.bev_mean`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from model.graph.bev_cpu import bev_mean
from model.graph.sites import scatter_sum
from model.layers.polar_bev import PolarToBEV


def dense_cell_table(to_bev: PolarToBEV) -> Tensor:
    """The module's CSR table -> (R * THETA, D) int64 cell ids, -1 past a column's own cells."""
    col_ptr, cells = to_bev.col_ptr, to_bev.cells  # (R * THETA + 1,), (P,)
    degree = col_ptr.diff()  # (R * THETA,)
    width = int(degree.max()) if degree.numel() else 0  # built once, on the host
    slot = torch.arange(width, device=cells.device)  # (D,)
    pos = (col_ptr[:-1, None] + slot[None, :]).clamp_max(max(cells.numel() - 1, 0))  # (R * THETA, D)
    return torch.where(slot[None, :] < degree[:, None], cells[pos], -1)


def polar_to_bev_fixed(
    to_bev: PolarToBEV, table: Tensor, feats: Tensor, r: Tensor, theta: Tensor, valid: Tensor
) -> Tensor:
    """feats (B, L, C), r and theta (B, L) int64 polar column of each row, valid (B, L) bool; `table` from
    `dense_cell_table(to_bev)` -> (B, C, ny, nx) channels_last, equal to `to_bev` over the valid rows."""
    b, length, c = feats.shape
    ny, nx = to_bev.bev.ny, to_bev.bev.nx
    n_cells = b * ny * nx
    column = (r * to_bev.grid.theta_bins + theta).clamp(0, table.shape[0] - 1)  # (B, L)
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
    return total[:n_cells].view(b, ny, nx, c).permute(0, 3, 1, 2)  # (B, C, ny, nx)


def polar_to_bev(
    to_bev: PolarToBEV, table: Tensor, feats: Tensor, r: Tensor, theta: Tensor, valid: Tensor
) -> Tensor:
    """`polar_to_bev_fixed`, through the CPU kernel on CPU tensors."""
    if feats.device.type != "cpu":
        return polar_to_bev_fixed(to_bev, table, feats, r, theta, valid)
    column = r * to_bev.grid.theta_bins + theta  # (B, L)
    return bev_mean(feats, column, valid, table, to_bev.bev.ny, to_bev.bev.nx).permute(0, 3, 1, 2)
