"""The voxelizer's CPU kernels (model/ops/voxelize_numba.py) against their torch twins in
model/graph/voxelize.py: the same keys, voxel rows, counts and stats exactly, the same features."""

from __future__ import annotations

import math

import pytest
import torch
from test_voxelize import make_voxelizer
from torch import Tensor

from lidar.samples import KITTI_000000
from model.config import paper, tiny
from model.geometry.sparse_tensor import SENTINEL
from model.graph.voxelize import group_torch, point_keys_torch
from model.layers.voxelize import PolarVoxelizer
from model.ops.voxelize_numba import grid_args, group_sorted, point_keys
from model.sectors import load_kitti_bin, split_turn


def padded(sectors: list[Tensor], extra: int = 64) -> tuple[Tensor, Tensor]:
    """(B, Np, C) with garbage on the padding rows (it must not matter), counts (B,)."""
    n = max(int(s.shape[0]) for s in sectors) + extra
    out = torch.full((len(sectors), n, sectors[0].shape[1]), 1e3)
    for b, s in enumerate(sectors):
        out[b, : s.shape[0]] = s
    return out, torch.tensor([int(s.shape[0]) for s in sectors])


def check_twins(vox: PolarVoxelizer, points: Tensor, counts: Tensor) -> None:
    want = point_keys_torch(vox, points, counts)
    got = point_keys(points, counts, vox.point_features, *grid_args(vox.grid))
    key, base, kept, out = want
    assert torch.equal(got[0], key) and torch.equal(got[2], kept) and torch.equal(got[3], out)
    assert bool((key != SENTINEL).any()), "no point kept: the check below means nothing"
    torch.testing.assert_close(got[1][:, key != SENTINEL], base[:, key != SENTINEL], rtol=0, atol=0)
    sorted_key, order = torch.sort(key, stable=True)
    sites = int((sorted_key[1:] != sorted_key[:-1]).sum())  # about the distinct real keys
    for cap in (sites + 50, max(sites // 2, 1)):  # holds them all; overflows
        keys, vid, count, feats = group_torch(vox, sorted_key, order, base, cap)
        g_keys, g_vid, g_count, g_feats = group_sorted(sorted_key, order, base, cap)
        assert torch.equal(g_keys, keys) and torch.equal(g_vid, vid) and int(g_count) == int(count)
        rows = vid < cap  # the points of voxels that fit (the dump row's are cut off)
        torch.testing.assert_close(g_feats[:, rows], feats[:, rows], rtol=1e-6, atol=1e-6)


@pytest.mark.samples
@pytest.mark.parametrize("config", [tiny, paper])  # paper: 5 point features from 4-column KITTI points
def test_kernels_equal_twins_on_kitti(config) -> None:
    cfg = config()
    sectors = split_turn(load_kitti_bin(str(KITTI_000000)), 4)
    check_twins(make_voxelizer(cfg.grid, cfg.vfe, 16), *padded(sectors))


def test_kernels_equal_twins_out_of_range_empty_and_repeated() -> None:
    vox = make_voxelizer(tiny().grid)
    g = torch.Generator().manual_seed(4)
    sectors = []
    for n in (700, 0, 1, 900):
        r = torch.rand(n, generator=g) * 60.0  # r in [1, 52.2) and z in [-3, 3) are in range
        t = (torch.rand(n, generator=g) * 2 - 1) * math.pi
        z = torch.rand(n, generator=g) * 8.0 - 4.0
        sectors.append(torch.stack((r * t.cos(), r * t.sin(), z, torch.rand(n, generator=g)), dim=1))
    sectors[3][:40] = sectors[3][40:80]  # repeated points: voxels with several points
    sectors[0][:5, :2] = torch.tensor([[-10.0, 0.0]])  # theta = +pi: the seam, clamped into the last bin
    check_twins(vox, *padded(sectors))
