"""The fixed-shape polar->BEV scatter-mean: its CPU kernel, its plain twin and the eager module agree."""

from __future__ import annotations

import pytest
import torch

from model.config import tiny
from model.geometry.sparse_tensor import SparseTensor
from model.graph.bev import dense_cell_table, polar_to_bev
from model.layers.polar_bev import PolarToBEV


def _rows(to_bev: PolarToBEV, b: int, length: int, channels: int, dtype: torch.dtype, seed: int):
    """b streams of `length` rows: random columns (some repeated, some near the grid's edge), the first
    60 % valid, huge features on the padding rows (they must not leak)."""
    g = torch.Generator().manual_seed(seed)
    grid = to_bev.grid
    r = torch.randint(0, grid.r_bins, (b, length), generator=g)
    theta = torch.randint(0, grid.theta_bins, (b, length), generator=g)
    r[:, :10] = grid.r_bins - 1  # the outermost ring feeds the most cells, or none past the map
    theta[:, 10:20] = theta[:, :1]  # several rows in one column
    valid = torch.arange(length)[None, :] < int(0.6 * length)
    valid = valid.expand(b, length).clone()
    feats = torch.randn(b, length, channels, generator=g, dtype=dtype)
    feats = torch.where(valid[..., None], feats, torch.full_like(feats, 1e6))
    return feats, r, theta, valid


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cpu_kernel_matches_twin_and_eager(dtype: torch.dtype):
    cfg = tiny()
    to_bev = PolarToBEV(cfg.grid, cfg.bev)
    table = dense_cell_table(to_bev)
    feats, r, theta, valid = _rows(to_bev, 2, 4096, 8, dtype, seed=0)
    fast = polar_to_bev(to_bev, table, feats, r, theta, valid, fast=True)  # the numba kernel
    twin = polar_to_bev(to_bev, table, feats, r, theta, valid, fast=False)  # model.ops.bev_mean_torch
    assert fast.shape == twin.shape == (2, 8, cfg.bev.ny, cfg.bev.nx) and fast.dtype == dtype
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(fast, twin, rtol=tol, atol=tol)
    batch = torch.arange(2)[:, None].expand_as(r)
    coords = torch.stack((batch, r, theta, torch.zeros_like(r)), -1)[valid]  # (n, 4)
    shape = (cfg.grid.r_bins, cfg.grid.theta_bins, cfg.grid.z_bins)
    eager = to_bev(SparseTensor(feats[valid], coords, shape, 2))
    torch.testing.assert_close(fast, eager, rtol=tol, atol=tol)
    assert fast.abs().max() < 1e3 and (fast != 0).any()  # no padding row leaked; something was scattered


def test_no_valid_row_gives_zeros():
    cfg = tiny()
    to_bev = PolarToBEV(cfg.grid, cfg.bev)
    feats, r, theta, valid = _rows(to_bev, 1, 64, 4, torch.float32, seed=1)
    out = polar_to_bev(to_bev, dense_cell_table(to_bev), feats, r, theta, torch.zeros_like(valid))
    assert out.shape == (1, 4, cfg.bev.ny, cfg.bev.nx) and not out.any()
