"""Sparse plane convs against dense F.conv2d / F.conv_transpose2d references; decomposed down/up sampling."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from torch import Tensor

from model.geometry.rulebook import Plane, as_kernel, conv_out_shape
from model.geometry.sparse_tensor import SparseTensor, linear_key, to_dense
from model.layers.decomposed import DecomposedDown, DecomposedUp
from model.layers.sparse_conv import SparseConv2d, SparseInverseConv2d

SHAPE = (12, 20, 6)  # (R, THETA, Z)
BATCH = 2


def random_sparse(
    shape: tuple[int, int, int], batch: int, density: float, channels: int, seed: int, dtype=torch.float64
) -> SparseTensor:
    """Random unique sites in linear_key order with random features."""
    g = torch.Generator().manual_seed(seed)
    n_r, n_t, n_z = shape
    mask = torch.rand(batch, n_r, n_t, n_z, generator=g) < density
    coords = mask.nonzero()  # (N, 4) batch, r, theta, z
    coords = coords[torch.argsort(linear_key(coords, shape))]
    feats = torch.randn(coords.shape[0], channels, generator=g, dtype=dtype)
    return SparseTensor(feats, coords, shape, batch)


def fold(dense: Tensor, plane: Plane) -> Tensor:
    """(B, C, R, T, Z) -> (B * fold, C, A0, A1) with the plane's axes last."""
    b, c, n_r, n_t, n_z = dense.shape
    if plane is Plane.RZ:
        return dense.permute(0, 3, 1, 2, 4).reshape(b * n_t, c, n_r, n_z)
    return dense.permute(0, 2, 1, 3, 4).reshape(b * n_r, c, n_t, n_z)


def unfold(planes: Tensor, plane: Plane, batch: int) -> Tensor:
    """Inverse of `fold`: (B * fold, C, A0, A1) -> (B, C, R, T, Z)."""
    bf, c, a0, a1 = planes.shape
    x = planes.reshape(batch, bf // batch, c, a0, a1)
    if plane is Plane.RZ:
        return x.permute(0, 2, 3, 1, 4)
    return x.permute(0, 2, 1, 3, 4)


def dense_weight(weight: Tensor, kernel: tuple[int, int], transposed: bool) -> Tensor:
    """(K0*K1, Cin, Cout) -> (Cout, Cin, K0, K1) for conv2d or (Cin, Cout, K0, K1) for conv_transpose2d."""
    w = weight.detach().reshape(*kernel, *weight.shape[1:])  # (K0, K1, Cin, Cout)
    return w.permute(2, 3, 0, 1) if transposed else w.permute(3, 2, 0, 1)


def at_sites(dense: Tensor, coords: Tensor) -> Tensor:
    """(B, C, R, T, Z) -> (N, C) at coords."""
    b, r, t, z = coords.unbind(1)
    return dense[b, :, r, t, z]


def dense_conv(x: SparseTensor, conv: SparseConv2d) -> tuple[Tensor, Tensor]:
    """Dense reference: (B, Cout, R', T', Z') values and the (B, R', T', Z') reachable-site mask."""
    k, s = conv.kernel, conv.stride
    pad = (k[0] // 2, k[1] // 2)
    w = dense_weight(conv.weight, k, transposed=False)
    out = F.conv2d(fold(to_dense(x), conv.plane), w, stride=s, padding=pad)
    occ = fold(to_dense(x.replace(torch.ones(x.num_sites, 1, dtype=x.features.dtype))), conv.plane)
    reach = F.conv2d(occ, torch.ones(1, 1, *k, dtype=occ.dtype), stride=s, padding=pad) > 0
    return unfold(out, conv.plane, x.batch_size), unfold(reach, conv.plane, x.batch_size)[:, 0]


def assert_sorted_unique(coords: Tensor, shape: tuple[int, int, int]) -> None:
    keys = linear_key(coords, shape)
    assert bool((keys[1:] > keys[:-1]).all())


CASES = [
    *[(p, k, s) for p in Plane for k in (3, 5) for s in ((2, 2), (3, 3), (4, 4), (2, 1), (1, 3), (1, 1))],
    *[(p, k, s) for p in Plane for k in ((3, 1), (5, 3), (1, 3)) for s in ((2, 1), (2, 2), (1, 1))],
]


@pytest.mark.parametrize(("plane", "kernel", "stride"), CASES)
def test_strided_conv_matches_dense(plane: Plane, kernel: int | tuple[int, int], stride: tuple[int, int]):
    torch.manual_seed(0)
    x = random_sparse(SHAPE, BATCH, 0.15, 3, seed=sum(as_kernel(kernel)) + 10 * stride[0] + stride[1])
    conv = SparseConv2d(3, 4, kernel, stride, plane, bias=True).double()
    y, rb = conv(x)
    ref, reach = dense_conv(x, conv)
    assert y.spatial_shape == tuple(ref.shape[2:]) == conv_out_shape(SHAPE, kernel, stride, plane)
    assert y.batch_size == BATCH
    assert_sorted_unique(y.coords, y.spatial_shape)
    ref_sites = reach.nonzero()  # (b, r, t, z) lexicographic; bring into linear_key order
    ref_sites = ref_sites[torch.argsort(linear_key(ref_sites, y.spatial_shape))]
    assert torch.equal(y.coords, ref_sites) and y.num_sites > 0
    ref_vals = at_sites(ref, y.coords) + conv.bias.detach()
    torch.testing.assert_close(y.features, ref_vals)
    assert rb.num_pairs == rb.offset_ptr[-1] and len(rb.offset_ptr) == math.prod(as_kernel(kernel)) + 1


@pytest.mark.parametrize("plane", list(Plane))
@pytest.mark.parametrize("kernel", [3, 5, (3, 1), (1, 5), (5, 3)])
def test_subm_conv_matches_dense(plane: Plane, kernel: int | tuple[int, int]) -> None:
    torch.manual_seed(1)
    x = random_sparse(SHAPE, BATCH, 0.2, 3, seed=sum(as_kernel(kernel)))
    conv = SparseConv2d(3, 5, kernel, (1, 1), plane, subm=True).double()
    y, rb = conv(x)
    assert torch.equal(y.coords, x.coords) and y.spatial_shape == SHAPE
    ref, _ = dense_conv(x, conv)
    torch.testing.assert_close(y.features, at_sites(ref, x.coords))
    centre = math.prod(as_kernel(kernel)) // 2
    assert rb.offset_ptr[centre + 1] - rb.offset_ptr[centre] == x.num_sites


def test_subm_conv_unsorted_input() -> None:
    """Rows in any order: the output keeps the input's row order and values."""
    torch.manual_seed(2)
    x = random_sparse(SHAPE, BATCH, 0.2, 3, seed=7)
    perm = torch.randperm(x.num_sites)
    xp = SparseTensor(x.features[perm], x.coords[perm], SHAPE, BATCH)
    conv = SparseConv2d(3, 4, 3, (1, 1), Plane.THETA_Z, subm=True).double()
    y, _ = conv(x)
    yp, _ = conv(xp)
    assert torch.equal(yp.coords, x.coords[perm])
    torch.testing.assert_close(yp.features, y.features[perm])


def dense_inverse(y: SparseTensor, inv: SparseInverseConv2d, stride: tuple[int, int], in_shape) -> Tensor:
    """Dense transposed conv back to in_shape: (B, Cout, R, T, Z)."""
    k = inv.kernel
    pad = (k[0] // 2, k[1] // 2)
    folded = fold(to_dense(y), inv.plane)
    lengths = [in_shape[ax - 1] for ax in inv.plane.axes]
    out_pad = [
        L - ((o - 1) * s - 2 * p + ki)
        for L, o, s, p, ki in zip(lengths, folded.shape[2:], stride, pad, k, strict=True)
    ]
    w = dense_weight(inv.weight, k, transposed=True)
    out = F.conv_transpose2d(folded, w, stride=stride, padding=pad, output_padding=tuple(out_pad))
    assert list(out.shape[2:]) == lengths
    return unfold(out, inv.plane, y.batch_size)


@pytest.mark.parametrize(("plane", "kernel", "stride"), CASES)
def test_inverse_conv_matches_dense(plane: Plane, kernel: int | tuple[int, int], stride: tuple[int, int]):
    torch.manual_seed(3)
    x = random_sparse(SHAPE, BATCH, 0.15, 3, seed=100 + sum(as_kernel(kernel)) + stride[0])
    _, rb = SparseConv2d(3, 4, kernel, stride, plane).double()(x)
    y = SparseTensor(torch.randn(rb.num_out, 4, dtype=torch.float64), rb.out_coords, rb.out_shape, BATCH)
    inv = SparseInverseConv2d(4, 2, kernel, plane, bias=True).double()
    z = inv(y, rb)
    assert torch.equal(z.coords, x.coords) and z.spatial_shape == SHAPE and z.batch_size == BATCH
    ref = dense_inverse(y, inv, stride, SHAPE)
    torch.testing.assert_close(z.features, at_sites(ref, x.coords) + inv.bias.detach())


@pytest.mark.parametrize("plane", list(Plane))
def test_inverse_of_subm_is_transposed_subm(plane: Plane) -> None:
    x = random_sparse(SHAPE, BATCH, 0.2, 3, seed=11)
    _, rb = SparseConv2d(3, 3, 5, (1, 1), plane, subm=True).double()(x)
    y = x.replace(torch.randn(x.num_sites, 3, dtype=torch.float64))
    inv = SparseInverseConv2d(3, 2, 5, plane).double()
    z = inv(y, rb)
    assert torch.equal(z.coords, x.coords)
    ref = dense_inverse(y, inv, (1, 1), SHAPE)
    torch.testing.assert_close(z.features, at_sites(ref, x.coords))


@pytest.mark.parametrize("plane", list(Plane))
@pytest.mark.parametrize("subm", [False, True])
def test_slices_do_not_interact(plane: Plane, subm: bool) -> None:
    """Changing one voxel changes outputs only in its own batch and its own slice of the folded axis."""
    x = random_sparse(SHAPE, BATCH, 0.3, 2, seed=5)
    conv = SparseConv2d(2, 2, 5, (1, 1) if subm else (2, 2), plane, subm=subm).double()
    y0, _ = conv(x)
    j = x.num_sites // 2
    feats = x.features.clone()
    feats[j] += 10.0
    y1, _ = conv(x.replace(feats))
    changed = (y1.features - y0.features).abs().sum(1) > 0
    fold_ax = plane.fold_axis
    assert changed.any()
    assert bool((y0.coords[changed, 0] == x.coords[j, 0]).all())
    assert bool((y0.coords[changed, fold_ax] == x.coords[j, fold_ax]).all())


@pytest.mark.parametrize(
    ("kernel", "stride", "tz_z"), [(3, 1, 1), (3, 2, 1), (5, 4, 1), (3, 3, 3), (5, 2, 5)]
)
def test_decomposed_round_trip(kernel: int, stride: int, tz_z: int) -> None:
    torch.manual_seed(4)
    shape = (24, 30, 8)
    x = random_sparse(shape, BATCH, 0.05, 8, seed=stride, dtype=torch.float32)
    x = x.replace(x.features.requires_grad_())
    down, up = DecomposedDown(8, kernel, stride, tz_z), DecomposedUp(8, kernel, stride, tz_z)
    y, ctx = down(x)
    assert_sorted_unique(y.coords, y.spatial_shape)
    if stride == 1:
        assert torch.equal(y.coords, x.coords)
    else:
        expect = (-(-shape[0] // stride), -(-shape[1] // stride), -(-shape[2] // stride))
        assert y.spatial_shape == expect and y.num_sites > 0
    z = up(y, ctx)
    assert torch.equal(z.coords, x.coords) and z.spatial_shape == shape and z.batch_size == BATCH
    assert z.features.shape == (x.num_sites, 8)
    z.features.square().sum().backward()
    assert x.features.grad is not None and x.features.grad.abs().sum() > 0
    for p in [*down.parameters(), *up.parameters()]:
        assert p.grad is not None and torch.isfinite(p.grad).all()


@pytest.mark.parametrize("stride", [1, 2])
def test_decomposed_empty_and_single_site(stride: int) -> None:
    down, up = DecomposedDown(4, 3, stride, 1), DecomposedUp(4, 3, stride, 1)
    for n in (0, 1):
        coords = torch.tensor([[1, 3, 4, 2]], dtype=torch.int64)[:n]
        x = SparseTensor(torch.randn(n, 4, requires_grad=True), coords, (10, 10, 4), 2)
        y, ctx = down(x)
        assert (y.num_sites == n) if stride == 1 else (y.num_sites >= n)  # a strided conv may dilate
        z = up(y, ctx)
        assert torch.equal(z.coords, coords) and z.features.shape == (n, 4)
        z.features.sum().backward()
    assert torch.isfinite(down.bn_rz.running_mean).all() and torch.isfinite(up.bn_rz.running_var).all()


def test_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="submanifold"):
        SparseConv2d(2, 2, 3, (2, 2), Plane.RZ, subm=True)
    with pytest.raises(ValueError, match="odd kernel"):
        DecomposedDown(4, 4, 2, 1)
    x = random_sparse(SHAPE, BATCH, 0.1, 2, seed=1)
    _, rb = SparseConv2d(2, 2, 3, (2, 2), Plane.RZ)(x.replace(x.features.float()))
    with pytest.raises(ValueError, match="rule book"):
        SparseInverseConv2d(2, 2, 3, Plane.THETA_Z)(x.replace(x.features.float()), rb)
