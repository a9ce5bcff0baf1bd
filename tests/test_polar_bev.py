"""Polar -> Cartesian BEV mapping (independent numpy geometry) and the residual BEV backbone."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import Tensor

from model.config import BEVConfig, PolarGridConfig, paper, tiny
from model.geometry.sparse_tensor import SparseTensor, linear_key
from model.layers.bev_backbone import BasicBlock, BEVBackbone
from model.layers.polar_bev import PolarToBEV


def sparse(
    coords: list[list[int]] | Tensor, feats: Tensor, grid: PolarGridConfig, batch: int = 1
) -> SparseTensor:
    c = torch.as_tensor(coords, dtype=torch.int64).reshape(-1, 4)
    shape = (grid.r_bins, grid.theta_bins, grid.z_bins)
    order = torch.argsort(linear_key(c, shape))
    return SparseTensor(feats[order], c[order], shape, batch)


def cell_of(x: float, y: float, bev: BEVConfig) -> tuple[int, int]:
    """(row, col) of the BEV cell containing Cartesian (x, y)."""
    return math.floor((y - bev.y_min) / bev.cell), math.floor((x - bev.x_min) / bev.cell)


def column_centre_xy(grid: PolarGridConfig, ri: int, ti: int) -> tuple[float, float]:
    r = grid.r_min + (ri + 0.5) * grid.r_size
    t = -math.pi + (ti + 0.5) * grid.theta_size
    return r * math.cos(t), r * math.sin(t)


@pytest.fixture(scope="module")
def paper_bev() -> PolarToBEV:
    cfg = paper()
    return PolarToBEV(cfg.grid, cfg.bev)


@pytest.fixture(scope="module")
def tiny_bev() -> PolarToBEV:
    cfg = tiny()
    return PolarToBEV(cfg.grid, cfg.bev)


def test_no_holes_in_a_far_band(paper_bev: PolarToBEV) -> None:
    """One voxel in every (r, theta) column of the 60-74 m band: each BEV cell centred in it has data."""
    grid, bev = paper_bev.grid, paper_bev.bev
    r_lo, r_hi = math.ceil((60.0 - grid.r_min) / grid.r_size), math.floor((74.0 - grid.r_min) / grid.r_size)
    ri, ti = torch.meshgrid(torch.arange(r_lo, r_hi), torch.arange(grid.theta_bins), indexing="ij")
    n = ri.numel()
    coords = torch.stack(
        [torch.zeros(n, dtype=torch.int64), ri.flatten(), ti.flatten(), (ri.flatten() * 7) % 32], 1
    )
    out = paper_bev(sparse(coords, torch.ones(n, 2), grid))  # (1, 2, ny, nx)
    yc = bev.y_min + (np.arange(bev.ny) + 0.5) * bev.cell
    xc = bev.x_min + (np.arange(bev.nx) + 0.5) * bev.cell
    r = np.hypot(xc[None, :], yc[:, None])  # (ny, nx)
    band = (r >= grid.r_min + r_lo * grid.r_size) & (r < grid.r_min + r_hi * grid.r_size)
    assert band.sum() > 20000
    filled = out[0, 0].numpy() != 0
    assert filled[band].all(), f"{(~filled[band]).sum()} empty cells in the band"
    torch.testing.assert_close(out[0, 0][torch.from_numpy(filled)], torch.ones(int(filled.sum())))
    assert not filled[
        r < grid.r_min + r_lo * grid.r_size - 2 * bev.cell
    ].any()  # nothing well inside the band


def test_two_voxels_in_one_column_are_averaged(tiny_bev: PolarToBEV) -> None:
    grid, bev = tiny_bev.grid, tiny_bev.bev
    a, b = torch.tensor([1.0, -2.0, 4.0]), torch.tensor([3.0, 6.0, 0.0])
    out = tiny_bev(sparse([[0, 40, 77, 2], [0, 40, 77, 9]], torch.stack([a, b]), grid))
    row, col = cell_of(*column_centre_xy(grid, 40, 77), bev)
    torch.testing.assert_close(out[0, :, row, col], (a + b) / 2)
    filled = out[0].abs().sum(0) != 0
    assert filled.sum() >= 1
    torch.testing.assert_close(out[0][:, filled], ((a + b) / 2)[:, None].expand(3, int(filled.sum())))


@pytest.mark.parametrize(("ri", "ti"), [(0, 0), (5, 128), (60, 31), (127, 255), (100, 64), (33, 200)])
def test_single_voxel_lands_in_the_cell_of_its_centre(tiny_bev: PolarToBEV, ri: int, ti: int) -> None:
    grid, bev = tiny_bev.grid, tiny_bev.bev
    x, y = column_centre_xy(grid, ri, ti)  # x = r cos(theta), y = r sin(theta)
    feat = torch.tensor([[2.5, -1.0]])
    out = tiny_bev(sparse([[0, ri, ti, 3]], feat, grid))
    row, col = cell_of(x, y, bev)
    if 0 <= row < bev.ny and 0 <= col < bev.nx:
        torch.testing.assert_close(out[0, :, row, col], feat[0])
    else:  # the column centre is outside the square BEV map (corners of the polar disc): nothing lands
        assert (out == 0).all()


def test_batch_items_do_not_mix(tiny_bev: PolarToBEV) -> None:
    grid = tiny_bev.grid
    feats = torch.tensor([[1.0], [10.0], [100.0]])
    out = tiny_bev(sparse([[0, 50, 10, 0], [1, 50, 10, 0], [1, 20, 100, 5]], feats, grid, batch=3))
    assert out.shape == (3, 1, tiny_bev.bev.ny, tiny_bev.bev.nx)
    assert set(out[0].unique().tolist()) == {0.0, 1.0}
    assert set(out[1].unique().tolist()) == {0.0, 10.0, 100.0}
    assert (out[2] == 0).all()


def reference_bev(x: SparseTensor, grid: PolarGridConfig, bev: BEVConfig) -> np.ndarray:
    """Dense numpy reference of the documented mapping: a cell averages the voxels of (a) the columns whose
    centre lies in it and (b) the column containing its centre."""
    yc = bev.y_min + (np.arange(bev.ny) + 0.5) * bev.cell
    xc = bev.x_min + (np.arange(bev.nx) + 0.5) * bev.cell
    xx, yy = np.meshgrid(xc, yc)  # (ny, nx)
    r, t = np.hypot(xx, yy), np.arctan2(yy, xx)
    cell_ri = np.floor((r - grid.r_min) / grid.r_size)
    cell_ti = np.minimum(np.floor((t + math.pi) / grid.theta_size), grid.theta_bins - 1)
    cell_ok = (r >= grid.r_min) & (r < grid.r_max)
    c = x.features.shape[1]
    total = np.zeros((x.batch_size, bev.ny, bev.nx, c))
    count = np.zeros((x.batch_size, bev.ny, bev.nx))
    for (b, ri, ti, _), f in zip(x.coords.tolist(), x.features.double().numpy(), strict=True):
        mask = cell_ok & (cell_ri == ri) & (cell_ti == ti)  # (b)
        row, col = cell_of(*column_centre_xy(grid, ri, ti), bev)  # (a)
        if 0 <= row < bev.ny and 0 <= col < bev.nx:
            mask[row, col] = True
        total[b][mask] += f
        count[b][mask] += 1
    return (total / np.maximum(count, 1)[..., None]).transpose(0, 3, 1, 2)


def test_matches_dense_reference_on_random_voxels(tiny_bev: PolarToBEV) -> None:
    grid, bev = tiny_bev.grid, tiny_bev.bev
    g = torch.Generator().manual_seed(0)
    n = 400
    coords = torch.stack(
        [
            torch.randint(0, 2, (n,), generator=g),
            torch.randint(0, 12, (n,), generator=g) * 10
            + torch.randint(0, 3, (n,), generator=g),  # near + far
            torch.randint(0, grid.theta_bins, (n,), generator=g),
            torch.randint(0, grid.z_bins, (n,), generator=g),
        ],
        1,
    )
    keys = linear_key(coords, (grid.r_bins, grid.theta_bins, grid.z_bins))
    coords = coords[np.unique(keys.numpy(), return_index=True)[1]]  # drop duplicate sites
    x = sparse(coords, torch.randn(coords.shape[0], 3, generator=g, dtype=torch.float64), grid, batch=2)
    got = tiny_bev(x)
    np.testing.assert_allclose(got.numpy(), reference_bev(x, grid, bev), rtol=1e-10, atol=1e-12)


def test_empty_input_gradients_and_memory_layout(tiny_bev: PolarToBEV) -> None:
    grid, bev = tiny_bev.grid, tiny_bev.bev
    empty = sparse(torch.zeros(0, 4), torch.zeros(0, 5), grid, batch=2)
    out = tiny_bev(empty)
    assert out.shape == (2, 5, bev.ny, bev.nx) and (out == 0).all()
    feats = torch.randn(2, 4, requires_grad=True)
    out = tiny_bev(sparse([[0, 3, 4, 0], [0, 120, 9, 1]], feats, grid))
    assert out.is_contiguous(memory_format=torch.channels_last)
    out.sum().backward()
    assert feats.grad is not None and (feats.grad > 0).all()
    with pytest.raises(ValueError, match="spatial_shape"):
        tiny_bev(SparseTensor(torch.zeros(0, 1), torch.zeros(0, 4, dtype=torch.int64), (64, 128, 8), 1))


# ---- BEV backbone ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "in_channels", "size"),
    [("tiny", 32, (128, 128)), ("tiny", 32, (117, 117)), ("tiny", 32, (33, 50)), ("paper", 128, (37, 29))],
)
def test_backbone_output_keeps_input_size(name: str, in_channels: int, size: tuple[int, int]) -> None:
    cfg = tiny() if name == "tiny" else paper()
    net = BEVBackbone(in_channels, cfg.bev)
    assert net.out_channels == sum(cfg.bev.num_upsample_filters)
    with torch.no_grad():
        out = net.eval()(torch.randn(1, in_channels, *size))
    assert out.shape == (1, net.out_channels, *size)
    assert torch.isfinite(out).all() and (out >= 0).all()  # every deblock ends in a ReLU


def test_backbone_structure_follows_config() -> None:
    cfg = paper().bev
    net = BEVBackbone(128, cfg)
    for stage, n_extra, c in zip(net.stages, cfg.layer_nums, cfg.num_filters, strict=True):
        blocks = list(stage)
        assert len(blocks) == 1 + n_extra and all(isinstance(b, BasicBlock) for b in blocks)
        assert blocks[0].shortcut is not None and all(b.shortcut is None for b in blocks[1:])
        assert blocks[0].conv2.out_channels == c
    strides = [stage[0].conv1.stride[0] for stage in net.stages]
    assert strides == list(cfg.layer_strides)
    bns = [m for m in net.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    assert all(m.eps == 1e-3 and m.momentum == 0.01 for m in bns)


def test_backbone_backward_and_channels_last() -> None:
    cfg = tiny().bev
    net = BEVBackbone(32, cfg)
    x = torch.randn(2, 32, 45, 31, requires_grad=True)
    net(x).square().mean().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()
    assert all(p.grad is not None for p in net.parameters())
    net = net.eval().to(memory_format=torch.channels_last)
    with torch.no_grad():
        a = net(x.detach().contiguous(memory_format=torch.channels_last))
        b = net(x.detach())
    torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)


def test_backbone_rejects_inconsistent_config() -> None:
    cfg = tiny().bev
    bad = BEVConfig(**{**cfg.__dict__, "num_filters": (32,)})
    with pytest.raises(ValueError, match="length"):
        BEVBackbone(32, bad)
