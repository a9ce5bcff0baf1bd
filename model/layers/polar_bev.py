"""Polar -> Cartesian BEV mapping with height compression (paper Sec. 3.4).

Every polar voxel's feature goes to the Cartesian BEV cells of its (r, theta) column, and all features landing
in one BEV cell (over all heights and all columns mapped there) are averaged; cells without data are zero.

Which cells a column feeds is a static table, built once from the two grids: the union of
    (a) column -> the BEV cell containing the column's centre (r_c cos theta_c, r_c sin theta_c), and
    (b) BEV cell -> the column containing the cell's centre.
(b) leaves no holes where polar columns are wider than BEV cells (far away: a 0.0134 rad column is ~1 m wide
at 75 m, a paper BEV cell 0.32 m), and (a) keeps every column's data where columns are narrower (near the
sensor, many columns share a cell). A BEV cell whose centre lies in a column holding data is never empty.

The table is CSR by column id r * THETA + theta (non-persistent buffers, so it follows .to(device)); at run
time voxels are expanded to their (voxel, cell) pairs and summed into a flat (B * ny * nx, C) buffer.

BEV layout (B, C, ny, nx): row = y index, column = x index; cell (row, col) covers
x in [x_min + col * cell, x_min + (col + 1) * cell) and y in [y_min + row * cell, y_min + (row + 1) * cell).
The returned tensor is a (B, C, ny, nx) view in channels_last memory layout.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from model.config import BEVConfig, PolarGridConfig
from model.geometry.sparse_tensor import BATCH, THETA, SparseTensor
from model.geometry.sparse_tensor import R as R_AX


def _column_centre_cells(grid: PolarGridConfig, bev: BEVConfig) -> tuple[Tensor, Tensor]:
    """(a): -> (column ids, cell ids) of the BEV cell containing each polar column's centre."""
    ri = torch.arange(grid.r_bins, dtype=torch.int64)
    ti = torch.arange(grid.theta_bins, dtype=torch.int64)
    r = grid.r_min + (ri.double() + 0.5) * grid.r_size  # (R,)
    theta = -math.pi + (ti.double() + 0.5) * grid.theta_size  # (T,)
    x = r[:, None] * torch.cos(theta)[None, :]  # (R, T)
    y = r[:, None] * torch.sin(theta)[None, :]
    col = torch.floor((x - bev.x_min) / bev.cell).long()
    row = torch.floor((y - bev.y_min) / bev.cell).long()
    inside = (col >= 0) & (col < bev.nx) & (row >= 0) & (row < bev.ny)
    column = ri[:, None] * grid.theta_bins + ti[None, :]  # (R, T)
    return column[inside], (row * bev.nx + col)[inside]


def _cell_centre_columns(grid: PolarGridConfig, bev: BEVConfig) -> tuple[Tensor, Tensor]:
    """(b): -> (column ids, cell ids) of the polar column containing each BEV cell's centre."""
    row = torch.arange(bev.ny, dtype=torch.int64)
    col = torch.arange(bev.nx, dtype=torch.int64)
    y = bev.y_min + (row.double() + 0.5) * bev.cell  # (ny,)
    x = bev.x_min + (col.double() + 0.5) * bev.cell  # (nx,)
    yy, xx = torch.meshgrid(y, x, indexing="ij")  # (ny, nx)
    r = torch.hypot(xx, yy)
    theta = torch.atan2(yy, xx)
    ri = torch.floor((r - grid.r_min) / grid.r_size).long()
    ti = torch.floor((theta + math.pi) / grid.theta_size).long().clamp(0, grid.theta_bins - 1)
    inside = (r >= grid.r_min) & (r < grid.r_max)
    ri = ri.clamp(0, grid.r_bins - 1)
    cell = row[:, None] * bev.nx + col[None, :]  # (ny, nx)
    return (ri * grid.theta_bins + ti)[inside], cell[inside]


def column_cell_table(grid: PolarGridConfig, bev: BEVConfig) -> tuple[Tensor, Tensor]:
    """-> CSR (col_ptr (R * THETA + 1,), cells (P,)) int64: column c feeds cells[col_ptr[c] : col_ptr[c + 1]].

    Column id = r * THETA + theta; cell id = row * nx + col.
    """
    col_a, cell_a = _column_centre_cells(grid, bev)
    col_b, cell_b = _cell_centre_columns(grid, bev)
    n_cells = bev.nx * bev.ny
    pair = torch.sort(torch.cat([col_a * n_cells + cell_a, col_b * n_cells + cell_b])).values
    distinct = torch.ones_like(pair, dtype=torch.bool)
    distinct[1:] = pair[1:] != pair[:-1]
    pair = pair[distinct]  # sorted unique (column, cell) pairs
    column, cells = pair // n_cells, pair % n_cells
    counts = torch.bincount(column, minlength=grid.r_bins * grid.theta_bins)
    col_ptr = torch.zeros(counts.shape[0] + 1, dtype=torch.int64)
    torch.cumsum(counts, 0, out=col_ptr[1:])
    return col_ptr, cells


class PolarToBEV(nn.Module):
    """SparseTensor on the polar grid (any number of heights) -> dense (B, C, ny, nx) Cartesian BEV map."""

    col_ptr: Tensor
    cells: Tensor

    def __init__(self, grid: PolarGridConfig, bev: BEVConfig):
        super().__init__()
        self.grid = grid
        self.bev = bev
        col_ptr, cells = column_cell_table(grid, bev)
        self.register_buffer("col_ptr", col_ptr, persistent=False)  # (R * THETA + 1,)
        self.register_buffer("cells", cells, persistent=False)  # (P,)

    def forward(self, x: SparseTensor) -> Tensor:
        """x: features (N, C), coords (N, 4) on the (R, THETA, *) grid -> (B, C, ny, nx), channels_last."""
        n_r, n_t = self.grid.r_bins, self.grid.theta_bins
        if tuple(x.spatial_shape[:2]) != (n_r, n_t):
            raise ValueError(f"PolarToBEV: spatial_shape {x.spatial_shape}; expected ({n_r}, {n_t}, Z)")
        ny, nx, c = self.bev.ny, self.bev.nx, x.features.shape[1]
        feats, coords = x.features, x.coords
        column = coords[:, R_AX] * n_t + coords[:, THETA]  # (N,)
        start = self.col_ptr.index_select(0, column)  # (N,)
        degree = self.col_ptr.index_select(0, column + 1) - start  # (N,) cells fed by each voxel
        first = torch.cumsum(degree, 0) - degree  # (N,) each voxel's first pair
        n_pairs = int(first[-1] + degree[-1]) if column.numel() else 0
        voxel = torch.repeat_interleave(degree, output_size=n_pairs)  # (P,) voxel of each pair
        pos = torch.repeat_interleave(start - first, degree, output_size=n_pairs)
        pos += torch.arange(n_pairs, device=column.device)  # (P,) index into self.cells
        cell = self.cells.index_select(0, pos) + coords[:, BATCH].index_select(0, voxel) * (ny * nx)  # (P,)
        count = torch.bincount(cell, minlength=x.batch_size * ny * nx)  # (B * ny * nx,) pairs per cell
        weight = count.index_select(0, cell).to(feats.dtype).reciprocal_()  # (P,) 1 / pairs in its cell
        pair_feats = feats.index_select(0, voxel) * weight[:, None]  # (P, C)
        mean = feats.new_zeros(x.batch_size * ny * nx, c).index_add_(0, cell, pair_feats)  # (B * ny * nx, C)
        return mean.view(x.batch_size, ny, nx, c).permute(0, 3, 1, 2)  # (B, C, ny, nx)
