"""The fixed-shape sparse convs and voxelizer (model/graph) against their eager rule-book twins."""

from __future__ import annotations

import math

import pytest
import torch
from test_voxelize import make_voxelizer
from torch import Tensor

from lidar.samples import KITTI_000000
from model.config import VFEConfig, paper, tiny
from model.geometry.rulebook import Plane
from model.geometry.sparse_tensor import SENTINEL, SparseTensor, linear_key
from model.graph.sites import Sites, compact_sorted, make_sites
from model.graph.sparse_conv import inverse_table, strided_sites, subm_table
from model.graph.voxelize import voxelize_fixed
from model.layers.sparse_conv import SparseConv2d, SparseInverseConv2d
from model.layers.voxelize import PolarVoxelizer
from model.ops.search import search
from model.ops.sort import sort_keys
from model.ops.table_conv import table_conv, table_conv_torch
from model.ops.table_conv_numba import _identity_prefix
from model.sectors import load_kitti_bin, split_turn

SHAPE = (12, 10, 7)  # (R, THETA, Z)
BATCH = 3


def random_sites(n: int, cap: int, seed: int, shape: tuple[int, int, int] = SHAPE) -> tuple[Sites, Tensor]:
    """n unique random sites over BATCH items in cap rows -> (Sites, (n, 4) coords in key order)."""
    g = torch.Generator().manual_seed(seed)
    n_r, n_t, n_z = shape
    flat = torch.randperm(BATCH * n_r * n_t * n_z, generator=g)[:n]  # (n,) unique cells
    coords = torch.stack(
        (flat // (n_r * n_t * n_z), flat // (n_t * n_z) % n_r, flat // n_z % n_t, flat % n_z), dim=1
    )
    keys, _ = torch.sort(linear_key(coords, shape))
    padded = torch.cat((keys, torch.full((cap - n,), SENTINEL)))  # (cap,)
    out, _, count = compact_sorted(padded, cap)
    sites = make_sites(out, shape, BATCH, count)
    return sites, sites.coords[:n]


def padded_features(n: int, cap: int, channels: int) -> Tensor:
    """(cap, C) features: random on the n real rows, huge values on the padding rows (they must not leak)."""
    return torch.cat((torch.randn(n, channels), torch.full((cap - n, channels), 1e6)))


def test_compact_sorted_dedups_pads_and_flags_overflow() -> None:
    keys = torch.tensor([3, 3, 5, 9, 9, 9, 12, SENTINEL, SENTINEL])
    out, row, count = compact_sorted(keys, 6)
    assert out.tolist() == [3, 5, 9, 12, SENTINEL, SENTINEL]
    assert row.tolist() == [0, 0, 1, 2, 2, 2, 3, 6, 6]
    assert int(count) == 4
    out, row, count = compact_sorted(keys, 2)
    assert out.tolist() == [3, 5]
    assert row.tolist() == [0, 0, 1, 2, 2, 2, 2, 2, 2]
    assert int(count) == 4


@pytest.mark.parametrize("n_keys", [0, 1, 40, 3000])
def test_search_kernel_is_searchsorted(n_keys: int) -> None:
    """The CPU kernel of the tables' lookups against torch.searchsorted: keys with repeats and SENTINEL
    padding, queries sorted, shifted (a table's rows), unsorted, below, between, on and past the keys."""
    g = torch.Generator().manual_seed(n_keys)
    keys = torch.randint(0, 5 * n_keys + 1, (n_keys,), generator=g).sort().values
    for padded in (keys, torch.cat((keys, torch.full((9,), SENTINEL)))):
        shifted = padded.unsqueeze(0) + torch.tensor([[-7], [0], [1], [13]])  # (4, n) nearly sorted rows
        shifted = torch.where(padded == SENTINEL, SENTINEL, shifted)
        wild = torch.randint(-20, 5 * n_keys + 20, (3, 257), generator=g)  # unsorted
        wild[0, ::5] = SENTINEL
        wild[1, ::7] = SENTINEL + 1  # past every key
        wild[2, :20] = padded[-1] if len(padded) else 0  # the largest key itself
        for queries in (shifted, wild, wild.sort(dim=1).values):
            got = search(padded, queries.contiguous(), fast=True)
            assert torch.equal(got, search(padded, queries, fast=False)), (n_keys, queries)


@pytest.mark.parametrize("n", [0, 1, 5000])
@pytest.mark.parametrize("top", [1, 2**11, 2**22, 2**33, SENTINEL + 5])
def test_sort_kernel_is_torch_stable_sort(n: int, top: int) -> None:
    """The radix sort kernel gives torch.sort(stable=True)'s values and order: duplicates, SENTINEL padding,
    keys of one to six passes (odd and even counts)."""
    g = torch.Generator().manual_seed(n + top % 97)
    keys = torch.randint(0, top, (n,), generator=g)
    keys[torch.rand(n, generator=g) < 0.3] = SENTINEL
    keys[: n // 10] = keys[n // 10 : 2 * (n // 10)]  # duplicates, some of them SENTINEL
    values, order = sort_keys(keys, fast=True)
    want_values, want_order = sort_keys(keys, fast=False)
    assert torch.equal(values, want_values) and torch.equal(order, want_order)


def test_sort_kernel_takes_negative_keys_through_torch() -> None:
    keys = torch.tensor([3, -1, SENTINEL, -7, 3, 0])
    values, order = sort_keys(keys, fast=True)
    assert values.tolist() == [-7, -1, 0, 3, 3, SENTINEL] and order.tolist() == [3, 1, 5, 0, 4, 2]


def test_sites_padding_rows() -> None:
    sites, coords = random_sites(40, 50, seed=1)
    assert sites.cap == 50 and int(sites.count) == 40 and not bool(sites.overflow)
    assert sites.valid.tolist() == [True] * 40 + [False] * 10
    assert torch.equal(sites.coords[40:], torch.tensor([[BATCH, 0, 0, 0]]).expand(10, 4))
    assert bool((coords[:, 1:] < torch.tensor(SHAPE)).all())


CONVS = [table_conv, table_conv_torch]  # on the CPU: the kernel over the entries naming a row; implicit GEMM


@pytest.mark.parametrize("conv_fn", CONVS)
@pytest.mark.parametrize("plane", [Plane.RZ, Plane.THETA_Z])
@pytest.mark.parametrize("kernel", [(3, 3), (3, 5), (3, 1)])
@pytest.mark.parametrize("n", [0, 1, 150])
def test_subm_conv_matches_rulebook_conv(conv_fn, plane: Plane, kernel: tuple[int, int], n: int) -> None:
    cap = n + 13
    sites, coords = random_sites(n, cap, seed=n + kernel[1])
    conv = SparseConv2d(5, 6, kernel, (1, 1), plane, subm=True, bias=True)
    x = padded_features(n, cap, 5)
    with torch.no_grad():
        ref, _ = conv(SparseTensor(x[:n], coords, SHAPE, BATCH))
        table = subm_table(sites, kernel, plane)
        out = conv_fn(x, table, conv.weight, conv.bias)
    assert table.shape == (cap, kernel[0] * kernel[1])
    assert bool((table[n:] == cap).all())  # padding rows read only the zero row
    torch.testing.assert_close(out[:n], ref.features, atol=1e-5, rtol=1e-5)


STRIDED = [
    (Plane.RZ, (3, 3), (2, 2)),
    (Plane.THETA_Z, (3, 3), (2, 2)),
    (Plane.RZ, (5, 5), (4, 4)),
    (Plane.THETA_Z, (5, 5), (4, 4)),
    (Plane.THETA_Z, (3, 1), (2, 1)),
    (Plane.RZ, (3, 1), (2, 1)),
]


@pytest.mark.parametrize("conv_fn", CONVS)
@pytest.mark.parametrize(("plane", "kernel", "stride"), STRIDED)
@pytest.mark.parametrize("n", [0, 7, 200])
def test_strided_conv_and_inverse_match_rulebook_convs(
    conv_fn, plane: Plane, kernel: tuple[int, int], stride: tuple[int, int], n: int
) -> None:
    cap = n + 11
    sites, coords = random_sites(n, cap, seed=3 * n + kernel[0])
    conv = SparseConv2d(4, 6, kernel, stride, plane, bias=True)
    inv = SparseInverseConv2d(6, 3, kernel, plane, bias=True)
    x = padded_features(n, cap, 4)
    with torch.no_grad():
        ref, rb = conv(SparseTensor(x[:n], coords, SHAPE, BATCH))
        ref_back = inv(ref, rb)
        out_sites, table = strided_sites(sites, kernel, stride, plane, out_cap=rb.num_out + 9)
        out = conv_fn(x, table, conv.weight, conv.bias)
        back = conv_fn(out, inverse_table(sites, out_sites, kernel, stride, plane), inv.weight, inv.bias)
    m = rb.num_out
    assert out_sites.spatial_shape == rb.out_shape
    assert int(out_sites.count) == m and not bool(out_sites.overflow)
    assert torch.equal(out_sites.coords[:m], rb.out_coords)
    assert torch.equal(out_sites.keys[:m], linear_key(rb.out_coords, rb.out_shape))
    assert bool((out_sites.keys[m:] == SENTINEL).all()) and bool((table[m:] == cap).all())
    torch.testing.assert_close(out[:m], ref.features, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(back[:n], ref_back.features, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("bias", [True, False])
def test_conv_kernel_equals_implicit_gemm_on_any_table(dtype: torch.dtype, bias: bool) -> None:
    """The CPU kernel (entries naming a row only) is the implicit GEMM for any table: empty rows, empty
    offsets, repeated input rows, an all-empty table."""
    g = torch.Generator().manual_seed(11)
    cap_in, cap_out, kk = 40, 30, 9
    x = torch.randn(cap_in, 5, generator=g, dtype=dtype)
    w = torch.randn(kk, 5, 7, generator=g, dtype=dtype)
    b = torch.randn(7, generator=g, dtype=dtype) if bias else None
    table = torch.randint(0, cap_in + 1, (cap_out, kk), generator=g)  # entry cap_in: none
    table[torch.rand(cap_out, kk, generator=g) < 0.6] = cap_in  # mostly empty, as in a real step
    table[3] = cap_in  # a row with no entry: the bias alone
    table[:, 4] = cap_in  # an offset with no entry
    table[5, :] = 2  # one input row through every offset
    for t in (table, torch.full_like(table, cap_in)):
        out = table_conv(x, t, w, b, fast=True)
        assert out.dtype == dtype and out.shape == (cap_out, 7)
        torch.testing.assert_close(out, table_conv_torch(x, t, w, b))
    empty = table_conv(x, torch.full_like(table, cap_in), w, b, fast=True)
    assert torch.equal(empty[0], b if bias else torch.zeros(7, dtype=dtype))


@pytest.mark.parametrize("n", [0, 17, 30])
def test_conv_kernel_centre_shortcut_equals_implicit_gemm(n: int) -> None:
    """A submanifold table's centre column (row o -> row o for the first n rows, none after) takes the
    addmm shortcut; a middle column that only looks so (a gap, a row past x's) takes the plain path: both
    are the implicit GEMM."""
    g = torch.Generator().manual_seed(12)
    cap_in, cap_out, kk = 30, 34, 9
    x = torch.randn(cap_in, 5, generator=g)
    w = torch.randn(kk, 5, 7, generator=g)
    b = torch.randn(7, generator=g)
    table = torch.randint(0, cap_in + 1, (cap_out, kk), generator=g)
    table[torch.rand(cap_out, kk, generator=g) < 0.6] = cap_in
    table[:, kk // 2] = cap_in
    table[:n, kk // 2] = torch.arange(n)
    gap = table.clone()
    gap[n + 1 :, kk // 2] = torch.arange(n + 1, cap_out).clamp_max(cap_in)  # identity after a hole
    assert _identity_prefix(table.numpy(), cap_in, kk // 2) == n  # the shortcut is taken
    assert _identity_prefix(gap.numpy(), cap_in, kk // 2) == (n if n + 1 >= cap_in else -1)
    for t in (table, gap):
        torch.testing.assert_close(table_conv(x, t, w, b, fast=True), table_conv_torch(x, t, w, b))


def test_strided_overflow_is_flagged_and_finite() -> None:
    sites, coords = random_sites(200, 220, seed=5)
    conv = SparseConv2d(4, 6, 3, (2, 2), Plane.RZ, bias=True)
    with torch.no_grad():
        ref, rb = conv(SparseTensor(torch.randn(200, 4), coords, SHAPE, BATCH))
        small, table = strided_sites(sites, 3, (2, 2), Plane.RZ, out_cap=rb.num_out - 5)
        out = table_conv(torch.randn(220, 4), table, conv.weight, conv.bias)
        inv_table = inverse_table(sites, small, 3, (2, 2), Plane.RZ)
    assert bool(small.overflow) and int(small.count) == rb.num_out
    assert torch.equal(small.coords, ref.coords[: small.cap])  # the first sites in key order are kept
    assert bool(torch.isfinite(out).all()) and bool((inv_table <= small.cap).all())


# ---- voxelizer ---------------------------------------------------------------------------------------------


def pad_points(sectors: list[Tensor], fill: float = math.nan) -> tuple[Tensor, Tensor]:
    """list of (N_b, C) -> (B, max N_b + 3, C) padded with `fill`, counts (B,) int64."""
    n = max(int(s.shape[0]) for s in sectors) + 3
    out = torch.full((len(sectors), n, sectors[0].shape[1]), fill)
    for b, s in enumerate(sectors):
        out[b, : s.shape[0]] = s
    return out, torch.tensor([int(s.shape[0]) for s in sectors])


def check_voxelizer(vox: PolarVoxelizer, sectors: list[Tensor]) -> None:
    """voxelize_fixed == vox.forward on the real rows (cap above the voxel count); overflow below it."""
    points, counts = pad_points(sectors)
    with torch.no_grad():
        ref, stats = vox(sectors)
    v = ref.num_sites
    sites, feats, kept, out_of_range = voxelize_fixed(vox, points, counts, v + 100)
    assert int(sites.count) == v and not bool(sites.overflow)
    assert torch.equal(sites.coords[:v], ref.coords)
    assert torch.equal(sites.keys[:v], linear_key(ref.coords, ref.spatial_shape))
    assert bool((sites.keys[v:] == SENTINEL).all()) and bool((feats[v:] == 0).all())
    torch.testing.assert_close(feats[:v], ref.features, atol=1e-4, rtol=1e-4)
    assert kept.tolist() == stats.points_kept and out_of_range.tolist() == stats.points_out_of_range
    small, feats, *_ = voxelize_fixed(vox, points, counts, max(v // 2, 1))
    assert bool(small.overflow) and int(small.count) == v and bool(torch.isfinite(feats).all())


@pytest.mark.samples
@pytest.mark.parametrize("config", [tiny, paper])
def test_voxelize_fixed_matches_voxelizer_on_kitti(config) -> None:
    cfg = config()
    vox = make_voxelizer(cfg.grid, cfg.vfe, 16)
    check_voxelizer(vox, split_turn(load_kitti_bin(str(KITTI_000000)), 4))


def test_voxelize_fixed_matches_voxelizer_with_out_of_range_points() -> None:
    vox = make_voxelizer(tiny().grid, VFEConfig(point_features=4, hidden=(6,)), 8)
    g = torch.Generator().manual_seed(2)
    sectors = []
    for n in (500, 0, 1, 900):
        r = torch.rand(n, generator=g) * 60.0  # r_max 52.2, r_min 1: some beyond, some inside
        t = (torch.rand(n, generator=g) * 2 - 1) * math.pi
        z = torch.rand(n, generator=g) * 8.0 - 4.0  # z in [-3, 3) is in range
        sectors.append(torch.stack((r * t.cos(), r * t.sin(), z, torch.rand(n, generator=g)), dim=1))
    sectors[3][:40] = sectors[3][40:80]  # duplicate points: voxels with several points
    check_voxelizer(vox, sectors)


def test_voxelize_fixed_needs_eval_mode() -> None:
    vox = make_voxelizer(tiny().grid, VFEConfig(), 8).train()
    with pytest.raises(ValueError, match="eval"):
        voxelize_fixed(vox, torch.zeros(1, 4, 4), torch.tensor([4]), 8)


# ---- torch.compile(fullgraph=True) -------------------------------------------------------------------------


def test_compiled_subm_conv_matches_eager() -> None:
    sites, _ = random_sites(150, 170, seed=7)
    conv = SparseConv2d(5, 6, 3, (1, 1), Plane.RZ, subm=True, bias=True)
    x = padded_features(150, 170, 5)

    def step(keys: Tensor, coords: Tensor, count: Tensor, x: Tensor, w: Tensor, b: Tensor) -> Tensor:
        s = Sites(keys, coords, SHAPE, BATCH, count)
        return table_conv(x, subm_table(s, (3, 3), Plane.RZ), w, b)

    compiled = torch.compile(step, fullgraph=True, dynamic=False)
    args = (sites.keys, sites.coords, sites.count, x, conv.weight.detach(), conv.bias.detach())
    torch.testing.assert_close(compiled(*args), step(*args), atol=1e-5, rtol=1e-5)


def test_compiled_voxelize_fixed_matches_eager() -> None:
    vox = make_voxelizer(tiny().grid, VFEConfig(point_features=4, hidden=(6,)), 8)
    g = torch.Generator().manual_seed(3)
    r = torch.rand(2, 1000, generator=g) * 50.0 + 1.5
    t = (torch.rand(2, 1000, generator=g) * 2 - 1) * math.pi
    points = torch.stack((r * t.cos(), r * t.sin(), torch.rand(2, 1000, generator=g) * 6 - 3, r / 50), dim=2)
    counts = torch.tensor([1000, 700])

    def step(points: Tensor, counts: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        sites, feats, kept, out = voxelize_fixed(vox, points, counts, 2048)
        return sites.keys, sites.count, feats, kept, out

    got = torch.compile(step, fullgraph=True, dynamic=False)(points, counts)
    want = step(points, counts)
    for a, b in zip(got[:2] + got[3:], want[:2] + want[3:], strict=True):
        assert torch.equal(a, b)
    torch.testing.assert_close(got[2], want[2], atol=1e-4, rtol=1e-4)
