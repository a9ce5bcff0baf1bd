"""Polar -> Cartesian BEV scatter-mean of fixed shape: the twin of `model.layers.polar_bev.PolarToBEV`.

The eager module expands every voxel to its (voxel, cell) pairs with a CSR table whose pair count depends on
the data. Here the table is dense: (R * THETA, D) cells per column, D = the largest number of cells a column
feeds (3 in `tiny`, 4 in `paper`), -1 where a column feeds fewer; the scatter-mean over it is an op
(`model.ops.bev_mean`: a numba kernel on the CPU, its tensor-op twin elsewhere). Each cell is the mean of the
features of the (voxel, cell) pairs landing in it, as in the eager module.
"""

from __future__ import annotations

import torch
from torch import Tensor

from model.layers.polar_bev import PolarToBEV
from model.ops.bev_mean import bev_mean


def dense_cell_table(to_bev: PolarToBEV) -> Tensor:
    """The module's CSR table -> (R * THETA, D) int64 cell ids, -1 past a column's own cells."""
    col_ptr, cells = to_bev.col_ptr, to_bev.cells  # (R * THETA + 1,), (P,)
    degree = col_ptr.diff()  # (R * THETA,)
    width = int(degree.max()) if degree.numel() else 0  # built once, on the host
    slot = torch.arange(width, device=cells.device)  # (D,)
    pos = (col_ptr[:-1, None] + slot[None, :]).clamp_max(max(cells.numel() - 1, 0))  # (R * THETA, D)
    return torch.where(slot[None, :] < degree[:, None], cells[pos], -1)


def polar_to_bev(
    to_bev: PolarToBEV,
    table: Tensor,
    feats: Tensor,
    r: Tensor,
    theta: Tensor,
    valid: Tensor,
    fast: bool | None = None,
) -> Tensor:
    """feats (B, L, C), r and theta (B, L) int64 polar column of each row, valid (B, L) bool; `table` from
    `dense_cell_table(to_bev)` -> (B, C, ny, nx) channels_last, equal to `to_bev` over the valid rows
    (`model.ops.bev_mean`; `fast`: its kernel or its twin)."""
    column = r * to_bev.grid.theta_bins + theta  # (B, L)
    out = bev_mean(feats, column, valid, table, to_bev.bev.ny, to_bev.bev.nx, fast)  # (B, ny, nx, C)
    return out.permute(0, 3, 1, 2)
