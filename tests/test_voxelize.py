"""Polar voxelizer + dynamic VFE against independent numpy / python-loop references."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import Tensor

from model.config import PolarGridConfig, VFEConfig, tiny
from model.geometry.sparse_tensor import linear_key
from model.layers.voxelize import PointsError, PolarVoxelizer, validate_points, voxel_max

GRID = tiny().grid  # r 1..52.2 (128 bins), theta 256 bins, z -3..3 (16 bins)
KITTI = Path("/work/shared/data/kitti_object/velodyne/000000.bin")


def make_voxelizer(grid: PolarGridConfig = GRID, vfe: VFEConfig | None = None, out: int = 8, seed: int = 0):
    """A voxelizer in eval mode with random, non-trivial BN statistics."""
    torch.manual_seed(seed)
    vox = PolarVoxelizer(grid, vfe or VFEConfig(point_features=4, hidden=(6,)), out)
    for layer in vox.layers:
        bn = layer.norm
        bn.running_mean.uniform_(-0.5, 0.5)
        bn.running_var.uniform_(0.5, 2.0)
        bn.weight.data.uniform_(0.5, 1.5)
        bn.bias.data.uniform_(-0.2, 0.2)
    return vox.eval()


def polar_points(n: int, seed: int, r: tuple[float, float], z: tuple[float, float]) -> Tensor:
    """(n, 4) float32 points uniform in r, theta, z ranges, random intensity."""
    g = np.random.default_rng(seed)
    rr = g.uniform(*r, n)
    tt = g.uniform(-math.pi, math.pi, n)
    pts = np.stack([rr * np.cos(tt), rr * np.sin(tt), g.uniform(*z, n), g.uniform(0, 1, n)], 1)
    return torch.from_numpy(pts.astype(np.float32))


# ---- validation --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_points_raise_points_error(bad: float) -> None:
    pts = torch.ones(20, 4)
    pts[17, 2] = bad
    pts[19, 0] = bad
    with pytest.raises(PointsError, match=r"points: 2 rows contain NaN or inf values \(row 17 first\)"):
        validate_points(pts)
    with pytest.raises(PointsError, match="points"):
        make_voxelizer()([torch.ones(5, 4), pts])


@pytest.mark.parametrize(
    ("pts", "needle"),
    [
        (torch.ones(10), "1-D"),
        (torch.ones(2, 10, 4), "3-D"),
        (torch.ones(10, 3), "3 columns"),
        (torch.ones(10, 4, dtype=torch.int32), "dtype"),
        (np.ones((10, 4), np.float32), "torch.Tensor"),
    ],
)
def test_bad_shape_or_dtype_raises_points_error(pts, needle: str) -> None:
    with pytest.raises(PointsError, match=needle) as err:
        validate_points(pts)
    assert str(err.value).startswith("points:")
    assert isinstance(err.value, ValueError)


def test_valid_points_pass() -> None:
    validate_points(torch.zeros(0, 4))
    validate_points(torch.randn(5, 6, dtype=torch.float64))
    validate_points(torch.full((4, 4), 3e38))  # finite, although their sum overflows


# ---- binning -----------------------------------------------------------------------------------------------


def test_every_kept_point_lies_inside_its_voxel() -> None:
    """One point per batch item, so an output voxel's batch index names its point; bounds in float64."""
    pts = polar_points(1500, seed=1, r=(0.5, 55.0), z=(-3.3, 3.3))
    st, stats = make_voxelizer()(list(pts.split(1)))
    b, ri, ti, zi = st.coords.numpy().T
    p = pts.numpy().astype(np.float64)[b]
    r, theta, z = np.hypot(p[:, 0], p[:, 1]), np.arctan2(p[:, 1], p[:, 0]), p[:, 2]
    tol = 1e-4
    g = GRID
    assert np.all(g.r_min + ri * g.r_size - tol <= r) and np.all(r < g.r_min + (ri + 1) * g.r_size + tol)
    assert np.all(-math.pi + ti * g.theta_size - tol <= theta)
    assert np.all(theta < -math.pi + (ti + 1) * g.theta_size + tol)
    assert np.all(g.z_min + zi * g.z_size - tol <= z) and np.all(z < g.z_min + (zi + 1) * g.z_size + tol)
    # every in-range point got exactly one voxel, every out-of-range point none
    q = pts.numpy().astype(np.float64)
    rq = np.hypot(q[:, 0], q[:, 1])
    inside = (rq >= g.r_min) & (rq < g.r_max) & (q[:, 2] >= g.z_min) & (q[:, 2] < g.z_max)
    assert np.array_equal(np.sort(b), np.flatnonzero(inside))
    assert stats.points_kept == inside.astype(int).tolist()
    assert stats.points_out_of_range == (~inside).astype(int).tolist()


def test_out_of_range_points_dropped_and_counted() -> None:
    kept = polar_points(50, seed=2, r=(2.0, 50.0), z=(-2.5, 2.5))
    out = torch.tensor(
        [
            [0.5, 0.0, 0.0, 0.1],  # r < r_min
            [0.0, -0.9, 0.0, 0.1],  # r < r_min
            [60.0, 0.0, 0.0, 0.1],  # r > r_max
            [-40.0, 40.0, 0.0, 0.1],  # r > r_max
            [10.0, 0.0, -3.5, 0.1],  # z < z_min
            [10.0, 0.0, 3.0, 0.1],  # z == z_max: half-open, dropped
            [10.0, 0.0, 7.0, 0.1],  # z > z_max
        ]
    )
    edge = torch.tensor([[10.0, 0.0, -3.0, 0.1], [0.0, 1.0, 0.0, 0.1]])  # z == z_min and r == r_min: kept
    items = [torch.cat([kept[:20], out, edge]), out[:3], kept[20:]]
    st, stats = make_voxelizer()(items)
    assert stats.points_in == [29, 3, 30]
    assert stats.points_out_of_range == [7, 3, 0]
    assert stats.points_kept == [22, 0, 30]
    assert st.batch_size == 3
    assert not (st.coords[:, 0] == 1).any()
    assert st.coords[:, 3].min() == 0  # the z == z_min point is in the lowest bin


def test_theta_wrap_is_seamless() -> None:
    n_t = GRID.theta_bins
    eps = 1e-4
    pts = torch.tensor(
        [
            [10 * math.cos(math.pi - eps), 10 * math.sin(math.pi - eps), 0.0, 0.5],  # just below +pi
            [10 * math.cos(-math.pi + eps), 10 * math.sin(-math.pi + eps), 0.0, 0.5],  # just above -pi
            [-10.0, 0.0, 0.0, 0.5],  # atan2(+0, -10) = +pi: clamped into the last bin
            [-10.0, -0.0, 0.0, 0.5],  # atan2(-0, -10) = -pi: first bin
            [10.0, 0.0, 0.0, 0.5],  # theta = 0: bin T / 2
        ]
    )
    st, _ = make_voxelizer()(list(pts.split(1)))
    assert st.coords[:, 0].tolist() == [0, 1, 2, 3, 4]
    assert st.coords[:, 2].tolist() == [n_t - 1, 0, n_t - 1, 0, n_t // 2]


# ---- empty input, sorting, dtypes --------------------------------------------------------------------------


@pytest.mark.parametrize("training", [False, True])
def test_empty_items_and_empty_batch(training: bool) -> None:
    vox = make_voxelizer().train(training)
    pts = polar_points(40, seed=3, r=(2.0, 50.0), z=(-2.5, 2.5))
    st, stats = vox([torch.zeros(0, 4), pts, torch.zeros(0, 4)])
    assert stats.points_in == [0, 40, 0] and stats.points_kept == [0, 40, 0]
    assert set(st.coords[:, 0].tolist()) == {1}
    st, stats = vox([torch.zeros(0, 4), torch.zeros(0, 5)])
    assert st.features.shape == (0, 8) and st.coords.shape == (0, 4) and st.batch_size == 2
    assert stats.points_kept == [0, 0]
    st, _ = vox([torch.tensor([[100.0, 0.0, 0.0, 0.0]])])  # nothing in range
    assert st.num_sites == 0 and st.spatial_shape == (GRID.r_bins, GRID.theta_bins, GRID.z_bins)
    st, _ = vox([pts[:1]])  # a single point, also in training mode
    assert st.num_sites == 1 and torch.isfinite(st.features).all()
    st, stats = vox([])  # no sectors at all
    assert st.batch_size == 0 and st.num_sites == 0 and stats.points_in == []


def test_rows_sorted_by_linear_key_and_unique() -> None:
    pts = [polar_points(3000, seed=s, r=(0.5, 55.0), z=(-3.3, 3.3)) for s in range(3)]
    st, _ = make_voxelizer()(pts)
    key = linear_key(st.coords, st.spatial_shape)
    assert torch.all(key[1:] > key[:-1])
    assert st.coords.dtype == torch.int64 and st.features.shape == (st.num_sites, 8)
    for col, size in zip((1, 2, 3), st.spatial_shape, strict=True):
        assert int(st.coords[:, col].min()) >= 0 and int(st.coords[:, col].max()) < size


def test_missing_feature_columns_are_zero_padded_and_extra_ignored() -> None:
    vox = make_voxelizer(vfe=VFEConfig(point_features=5, hidden=(6,)))
    pts4 = polar_points(300, seed=4, r=(2.0, 50.0), z=(-2.5, 2.5))
    pts5 = torch.cat([pts4, torch.zeros(300, 1)], 1)
    pts7 = torch.cat([pts5, torch.randn(300, 2)], 1)
    a, _ = vox([pts4])
    b, _ = vox([pts5])
    c, _ = vox([pts7.double()])
    assert torch.equal(a.coords, b.coords) and torch.equal(a.coords, c.coords)
    torch.testing.assert_close(a.features, b.features)
    torch.testing.assert_close(c.features, b.features)
    d, _ = vox([torch.cat([pts4, torch.ones(300, 1)], 1)])
    assert not torch.allclose(d.features, b.features)  # the 5th column is used


# ---- VFE ---------------------------------------------------------------------------------------------------


def clustered_points(seed: int) -> Tensor:
    """~200 points in a few coarse voxels (many points per voxel), on COARSE."""
    g = torch.Generator().manual_seed(seed)
    centres = torch.tensor([[3.0, 0.5, 0.5], [3.2, 0.6, -0.5], [7.0, -2.0, 1.0], [-5.0, 5.0, 0.2]])
    pts = centres[torch.randint(0, 4, (200,), generator=g)] + 0.4 * torch.randn(200, 3, generator=g)
    return torch.cat([pts, torch.rand(200, 1, generator=g)], 1)


COARSE = PolarGridConfig(r_bins=4, theta_bins=8, z_bins=2, r_min=1.0, r_max=9.0, z_min=-2.0, z_max=2.0)


def reference_point_features(grid: PolarGridConfig, pts: Tensor) -> dict[tuple[int, int, int], Tensor]:
    """Python loop, float64, following the module docstring: {(r, theta, z): (n_v, 13) VFE input}."""
    g = grid
    groups: dict[tuple[int, int, int], list[list[float]]] = {}
    for x, y, z, i in pts.double().tolist():
        r, t = math.hypot(x, y), math.atan2(y, x)
        if not (g.r_min <= r < g.r_max and g.z_min <= z < g.z_max):
            continue
        ri, ti = int((r - g.r_min) // g.r_size), min(int((t + math.pi) // g.theta_size), g.theta_bins - 1)
        zi = int((z - g.z_min) // g.z_size)
        centre = [
            r - (g.r_min + (ri + 0.5) * g.r_size),
            r * (t - (-math.pi + (ti + 0.5) * g.theta_size)),
            z - (g.z_min + (zi + 0.5) * g.z_size),
        ]
        groups.setdefault((ri, ti, zi), []).append([x, y, z, i, r, *centre, y / r, x / r])
    out = {}
    for key, rows in groups.items():
        f = torch.tensor(rows, dtype=torch.float64)  # (n_v, 10)
        out[key] = torch.cat([f, f[:, 5:8] - f[:, 5:8].mean(0)], 1)  # + cluster offsets
    return out


def reference_vfe(vox: PolarVoxelizer, pts: Tensor, training: bool) -> dict[tuple[int, int, int], Tensor]:
    """Concat -> Linear -> BN -> ReLU -> max per voxel, layer by layer; BN with running statistics (eval) or
    the batch statistics over all points (training)."""
    feats = reference_point_features(vox.grid, pts)
    keys = list(feats)
    for k, layer in enumerate(vox.layers):
        bn = layer.norm
        pre = [feats[key] @ layer.linear.weight.double().T for key in keys]
        if training:
            allp = torch.cat(pre)
            mean, var = allp.mean(0), allp.var(0, unbiased=False)
        else:
            mean, var = bn.running_mean.double(), bn.running_var.double()
        for key, h in zip(keys, pre, strict=True):
            h = torch.relu((h - mean) / torch.sqrt(var + bn.eps) * bn.weight.double() + bn.bias.double())
            m = h.max(0).values
            feats[key] = torch.cat([h, m.expand_as(h)], 1) if k < len(vox.layers) - 1 else m
    return feats


@pytest.mark.parametrize("training", [False, True])
@pytest.mark.parametrize("hidden", [(6,), (5, 7)])
def test_vfe_matches_python_loop_reference(hidden: tuple[int, ...], training: bool) -> None:
    vox = make_voxelizer(COARSE, VFEConfig(point_features=4, hidden=hidden)).train(training)
    pts = clustered_points(5)
    ref = reference_vfe(vox, pts, training)
    with torch.no_grad():
        st, _ = vox([pts])
    assert st.num_sites == len(ref) >= 4
    got = {tuple(c[1:].tolist()): f for c, f in zip(st.coords, st.features, strict=True)}
    assert set(got) == set(ref)
    for key, f in ref.items():
        torch.testing.assert_close(got[key].double(), f, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("training", [False, True])
def test_vfe_invariant_to_point_order(training: bool) -> None:
    vox = make_voxelizer(COARSE).train(training)
    pts = clustered_points(6)
    perm = torch.randperm(pts.shape[0], generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        a, _ = vox([pts])
        b, _ = vox([pts[perm]])
    assert torch.equal(a.coords, b.coords)
    torch.testing.assert_close(a.features, b.features, atol=1e-5, rtol=1e-5)


def test_training_mode_uses_batch_statistics_and_backprops() -> None:
    vox = make_voxelizer(COARSE).train()
    st, _ = vox([clustered_points(7), clustered_points(8)])
    st.features.square().sum().backward()
    for name, p in vox.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert vox.layers[0].linear.weight.grad.abs().sum() > 0


def test_voxel_max_gradient_matches_scatter_reduce() -> None:
    g = torch.Generator().manual_seed(0)
    x = torch.randn(50, 3, generator=g, dtype=torch.float64)
    vid = torch.tensor([0] * 5 + [1] * 10 + [2] * 35)
    x[5:15] = -1.0
    x[6:9, :2] = 2.0  # a three-way tie for the max of voxel 1 in channels 0 and 1
    x1 = x.clone().requires_grad_()
    x2 = x.clone().requires_grad_()
    w = torch.randn(3, 3, generator=g, dtype=torch.float64)
    ours = voxel_max(x1, vid, 3)
    ref = torch.zeros(3, 3, dtype=torch.float64).scatter_reduce(
        0, vid[:, None].expand(-1, 3), x2, "amax", include_self=False
    )
    torch.testing.assert_close(ours, ref)
    (ours * w).sum().backward()
    (ref * w).sum().backward()
    torch.testing.assert_close(x1.grad, x2.grad)
    torch.autograd.gradcheck(
        lambda t: voxel_max(t, vid, 3), (torch.randn(50, 3, dtype=torch.float64).requires_grad_(),)
    )


# ---- real data ---------------------------------------------------------------------------------------------


@pytest.mark.skipif(not KITTI.exists(), reason="KITTI sample not available")
def test_kitti_scan_voxelizes_per_quarter_sector() -> None:
    from model.sectors import load_kitti_bin, split_turn

    cfg = tiny()
    pts = load_kitti_bin(str(KITTI))
    sectors = split_turn(pts, 4)
    with torch.no_grad():
        st, stats = make_voxelizer(cfg.grid, cfg.vfe, cfg.backbone.d_model)(sectors)
    per_sector = torch.bincount(st.coords[:, 0], minlength=4).tolist()
    print("KITTI 000000 tiny voxels per quarter sector:", per_sector, "points kept:", stats.points_kept)
    assert stats.points_in == [s.shape[0] for s in sectors] and sum(stats.points_in) == pts.shape[0]
    t_per = cfg.grid.theta_bins // 4
    assert torch.equal(st.coords[:, 2] // t_per, st.coords[:, 0])  # sector k only fills its own theta bins
    # independent float64 count of occupied voxels and kept points
    p = pts.numpy().astype(np.float64)
    g = cfg.grid
    r, t, z = np.hypot(p[:, 0], p[:, 1]), np.arctan2(p[:, 1], p[:, 0]), p[:, 2]
    ok = (r >= g.r_min) & (r < g.r_max) & (z >= g.z_min) & (z < g.z_max)
    ti = np.minimum(np.floor((t + math.pi) / g.theta_size), g.theta_bins - 1)
    vox = np.stack([np.floor((r - g.r_min) / g.r_size), ti, np.floor((z - g.z_min) / g.z_size)], 1)[ok]
    assert abs(sum(stats.points_kept) - int(ok.sum())) <= 3
    assert abs(st.num_sites - len(np.unique(vox, axis=0))) <= 3
    assert min(per_sector) > 500 and torch.isfinite(st.features).all()
