"""Pure-torch sparse 2D convolutions applied on one plane of the 3D polar grid.

A `Plane` names the two spatial axes the 2D kernel slides over; the remaining spatial axis is folded into the
batch, so sites in different batches or different slices of that third axis never interact.

Semantics match a dense convolution restricted to active sites (as spconv). A kernel is (K0, K1): K0 along
the plane's first axis, K1 along its second (an int K means (K, K)); padding p_i = K_i // 2; kernel index
k = (k0, k1), flat index k0 * K1 + k1.
- strided conv: output extent floor((L + 2p - K) / s) + 1 per plane axis; output sites are the positions o
  reached by an active input at o * s - p + k; out[o] = sum_k W_k^T x[o * s - p + k] (+ bias).
- submanifold conv: output sites are exactly the input sites, same formula with s = 1.
- inverse conv: the transposed conv on a rule book's input sites: out[i] = sum_(i, o, k) W'_k^T y[o].

Rule books are built from sorted int64 site keys (`linear_key`, order (batch, theta, r, z)) with a sort
(strided) or `torch.searchsorted` (submanifold); a conv is gather -> matmul per kernel offset -> index_add.
Every output tensor keeps its rows sorted by `linear_key`. Input coordinates must be unique.
"""

from __future__ import annotations

import enum
import itertools
import logging
import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from model.runtime import triton_available
from model.sparse_tensor import BATCH, THETA, SparseTensor, Z, linear_key
from model.sparse_tensor import R as R_AX

log = logging.getLogger(__name__)
_announced: set[bool] = set()  # which gather_mm_scatter paths have been logged


class Plane(enum.Enum):
    """The two coordinate columns the kernel slides over (first, second) and the column folded into batch."""

    RZ = (R_AX, Z, THETA)  # convolve over (r, z); theta folds into the batch
    THETA_Z = (THETA, Z, R_AX)  # convolve over (theta, z); r folds into the batch

    @property
    def axes(self) -> tuple[int, int]:
        """Coordinate columns of the plane's first and second axis."""
        return self.value[0], self.value[1]

    @property
    def fold_axis(self) -> int:
        """Coordinate column folded into the batch."""
        return self.value[2]


@dataclass(frozen=True)
class Rulebook:
    """(input row, output row) pairs grouped by kernel offset; reusable (reversed) by the inverse conv."""

    in_idx: Tensor  # (P,) int64 rows of the conv's input
    out_idx: Tensor  # (P,) int64 rows of the conv's output
    offset_ptr: tuple[int, ...]  # (K0*K1 + 1,) pairs of flat kernel offset k are [ptr[k], ptr[k+1])
    kernel: tuple[int, int]
    plane: Plane
    in_coords: Tensor  # (N, 4) int64 input sites, sorted by linear_key
    in_shape: tuple[int, int, int]  # (R, THETA, Z) of the input grid
    out_coords: Tensor  # (M, 4) int64 output sites, sorted by linear_key
    out_shape: tuple[int, int, int]  # (R, THETA, Z) of the output grid
    batch_size: int
    identity_offset: int | None = None  # offset whose pairs are (i, i) for every row (submanifold centre)

    @property
    def num_in(self) -> int:
        return int(self.in_coords.shape[0])

    @property
    def num_out(self) -> int:
        return int(self.out_coords.shape[0])

    @property
    def num_pairs(self) -> int:
        return int(self.in_idx.shape[0])


def _key_strides(shape: tuple[int, int, int]) -> tuple[int, int, int, int]:
    """Key increment per unit step of each coordinate column (batch, r, theta, z), see `linear_key`."""
    n_r, n_t, n_z = shape
    return n_t * n_r * n_z, n_z, n_r * n_z, 1


def as_kernel(kernel: int | tuple[int, int]) -> tuple[int, int]:
    """An int K means (K, K); both extents must be >= 1."""
    k = (kernel, kernel) if isinstance(kernel, int) else (int(kernel[0]), int(kernel[1]))
    if min(k) < 1:
        raise ValueError(f"kernel extents must be >= 1, got {kernel}")
    return k


def conv_out_shape(
    shape: tuple[int, int, int], kernel: int | tuple[int, int], stride: tuple[int, int], plane: Plane
) -> tuple[int, int, int]:
    """Grid extent after a strided conv: floor((L + 2p - K) / s) + 1 on each plane axis."""
    out = list(shape)
    for ax, k, s in zip(plane.axes, as_kernel(kernel), stride, strict=True):
        out[ax - 1] = (shape[ax - 1] + 2 * (k // 2) - k) // s + 1
        if out[ax - 1] < 1:
            raise ValueError(f"grid extent {shape[ax - 1]} too small for kernel {kernel}")
    return out[0], out[1], out[2]


def _pair_ptr(valid: Tensor) -> tuple[int, ...]:
    """(KK, N) bool -> (KK + 1,) offsets of each row's True entries in row-major order."""
    counts = valid.sum(dim=1).cumsum(0)
    return (0, *counts.tolist())


def _decode_keys(keys: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """(M,) linear keys -> (M, 4) coords (batch, r, theta, z); inverse of `linear_key`."""
    n_r, n_t, n_z = shape
    z = keys % n_z
    rest = keys // n_z
    r = rest % n_r
    rest = rest // n_r
    return torch.stack((rest // n_t, r, rest % n_t, z), dim=1)


def build_strided_rulebook(
    coords: Tensor,
    shape: tuple[int, int, int],
    batch_size: int,
    kernel: int | tuple[int, int],
    stride: tuple[int, int],
    plane: Plane,
) -> Rulebook:
    """Rule book of a (non-submanifold) strided conv; coords (N, 4) int64, any row order."""
    kernel = as_kernel(kernel)
    out_shape = conv_out_shape(shape, kernel, stride, plane)
    n, dev = coords.shape[0], coords.device
    k0, k1 = kernel
    out_pos, valid = [], []
    for ax, k, s in zip(plane.axes, kernel, stride, strict=True):
        ks = torch.arange(k, device=dev)
        q = coords[:, ax].unsqueeze(0) + (k // 2 - ks).unsqueeze(1)  # (K_i, N) = o * s when valid
        out_pos.append(torch.div(q, s, rounding_mode="floor"))  # (K_i, N)
        valid.append((q >= 0) & (q % s == 0) & (q < out_shape[ax - 1] * s))
    ok = (valid[0].unsqueeze(1) & valid[1].unsqueeze(0)).view(k0 * k1, n)  # (K0 K1, N)
    kk, site = ok.nonzero().unbind(1)  # (P,), (P,) grouped by kk
    st = _key_strides(out_shape)
    (a0, a1), fold = plane.axes, plane.fold_axis
    base = coords[:, BATCH] * st[BATCH] + coords[:, fold] * st[fold]  # (N,) key with plane axes at 0
    o0 = out_pos[0].view(-1).index_select(0, torch.div(kk, k1, rounding_mode="floor") * n + site)  # (P,)
    o1 = out_pos[1].view(-1).index_select(0, (kk % k1) * n + site)  # (P,)
    cand = base.index_select(0, site) + o0 * st[a0] + o1 * st[a1]  # (P,) output keys of the candidate pairs
    sorted_keys, perm = torch.sort(cand)
    is_new = torch.ones_like(sorted_keys, dtype=torch.bool)
    is_new[1:] = sorted_keys[1:] != sorted_keys[:-1]
    group = is_new.cumsum(0) - 1  # (P,) output row of each sorted candidate
    out_idx = torch.empty_like(perm).scatter_(0, perm, group)
    out_coords = _decode_keys(sorted_keys[is_new], out_shape)
    return Rulebook(
        site, out_idx, _pair_ptr(ok), kernel, plane, coords, shape, out_coords, out_shape, batch_size
    )


def _neighbour_keys(
    keys: Tensor, coords: Tensor, shape: tuple[int, int, int], kernel: tuple[int, int], plane: Plane
) -> tuple[Tensor, Tensor]:
    """Keys of all sites' plane neighbours and whether they are inside the grid: (KK, N) int64, (KK, N) bool.

    keys (N,) and coords (N, 4) in the same row order; row k = (k0, k1) is the neighbour at offset k - p.
    """
    n, dev = coords.shape[0], coords.device
    st = _key_strides(shape)
    (a0, a1), (k0, k1) = plane.axes, kernel
    d0 = torch.arange(k0, device=dev) - k0 // 2  # (K0,) offset k - p on the first axis
    d1 = torch.arange(k1, device=dev) - k1 // 2  # (K1,) on the second axis
    nb0 = coords[:, a0].unsqueeze(0) + d0.unsqueeze(1)  # (K0, N) neighbour coordinate on the first axis
    nb1 = coords[:, a1].unsqueeze(0) + d1.unsqueeze(1)  # (K1, N) on the second axis
    in0 = (nb0 >= 0) & (nb0 < shape[a0 - 1])
    in1 = (nb1 >= 0) & (nb1 < shape[a1 - 1])
    shift = (d0 * st[a0]).view(k0, 1) + (d1 * st[a1]).view(1, k1)  # (K0, K1)
    nkey = keys.view(1, 1, n) + shift.unsqueeze(2)  # (K0, K1, N)
    inside = in0.unsqueeze(1) & in1.unsqueeze(0)  # (K0, K1, N)
    return nkey.view(k0 * k1, n), inside.view(k0 * k1, n)


def build_subm_rulebook(
    coords: Tensor, shape: tuple[int, int, int], batch_size: int, kernel: int | tuple[int, int], plane: Plane
) -> Rulebook:
    """Rule book of a submanifold conv (output sites = input sites); coords (N, 4) int64, unique; K odd.

    Only the offsets before the centre are searched: the pair (i <- j) at offset d is the pair (j <- i) at
    offset -d (flat index KK - 1 - k), and the centre pairs are the identity.
    """
    kernel = as_kernel(kernel)
    n, dev = coords.shape[0], coords.device
    keys = linear_key(coords, shape)  # (N,)
    perm: Tensor | None = None
    if n > 1 and not bool((keys[1:] > keys[:-1]).all()):
        keys, perm = torch.sort(keys)
    sorted_coords = coords if perm is None else coords.index_select(0, perm)
    centre = kernel[0] * kernel[1] // 2
    nkey, inside = _neighbour_keys(keys, sorted_coords, shape, kernel, plane)
    nkey, inside = nkey[:centre], inside[:centre]  # (c, N) offsets before the centre
    if n == 0:
        pos, found = torch.zeros_like(nkey), inside
    else:
        pos = torch.searchsorted(keys, nkey).clamp_max_(n - 1)  # (c, N) row in sorted order
        found = inside & (keys.index_select(0, pos.view(-1)).view_as(pos) == nkey)
    kk, out_lo = found.nonzero().unbind(1)  # (P_lo,) grouped by kk; output rows in sorted order
    in_lo = pos.view(-1).index_select(0, kk * n + out_lo)
    if perm is not None:  # back to the caller's row order
        in_lo, out_lo = perm.index_select(0, in_lo), perm.index_select(0, out_lo)
    ident = torch.arange(n, device=dev)
    in_idx = torch.cat((in_lo, ident, out_lo.flip(0)))  # upper offsets: swapped pairs, groups reversed
    out_idx = torch.cat((out_lo, ident, in_lo.flip(0)))
    counts = found.sum(dim=1).tolist()
    sizes = [*counts, n, *counts[::-1]]
    ptr = (0, *itertools.accumulate(sizes))
    return Rulebook(in_idx, out_idx, ptr, kernel, plane, coords, shape, coords, shape, batch_size, centre)


def gather_mm_scatter(
    src: Tensor,
    weight: Tensor,
    src_idx: Tensor,
    dst_idx: Tensor,
    ptr: tuple[int, ...],
    n_dst: int,
    identity_offset: int | None = None,
    fused: bool | None = None,
) -> Tensor:
    """dst[dst_idx[j]] += src[src_idx[j]] @ weight[k] for every pair j of offset k.

    src (N_src, C_in), weight (KK, C_in, C_out), src_idx / dst_idx (P,) -> (n_dst, C_out). The pairs of
    `identity_offset`, if given, must be (i, i) for every row (N_src == n_dst): that offset is one matmul.
    Gathering per offset keeps each gathered block in cache for its matmul.

    `fused` (None: wherever it can run, i.e. float32 on CUDA with Triton): one Triton launch for all offsets
    (model/sparse_conv_triton.py) instead of this loop, its plain-torch twin. The log says which runs.
    """
    if fused is None:
        fused = triton_available(src.device) and src.dtype == weight.dtype == torch.float32
    fused = fused and src_idx.numel() > 0  # no pairs: nothing to launch
    if fused not in _announced:
        _announced.add(fused)
        log.info("sparse conv gather-matmul-scatter: %s", "triton" if fused else "torch")
    if fused:
        from model.sparse_conv_triton import gather_mm_scatter_triton

        return gather_mm_scatter_triton(src, weight, src_idx, dst_idx, ptr, n_dst, identity_offset)
    ident = identity_offset
    # products are cast back to src's dtype: under autocast they come out in bf16, the sums stay float32
    out = src.new_zeros(n_dst, weight.shape[2]) if ident is None else (src @ weight[ident]).to(src.dtype)
    for k in range(weight.shape[0]):
        lo, hi = ptr[k], ptr[k + 1]
        if hi > lo and k != ident:
            out.index_add_(0, dst_idx[lo:hi], (src.index_select(0, src_idx[lo:hi]) @ weight[k]).to(src.dtype))
    if src_idx.numel() == 0:  # keep the graph connected to the inputs and weights for empty inputs
        out = out + src.sum() * weight.sum() * 0.0
    return out


def _init_params(weight: Tensor, bias: Tensor | None, fan_in: int) -> None:
    """PyTorch's conv default (kaiming-uniform with a = sqrt(5)): U(-1/sqrt(fan_in), 1/sqrt(fan_in))."""
    bound = 1.0 / math.sqrt(fan_in)
    with torch.no_grad():
        weight.uniform_(-bound, bound)
        if bias is not None:
            bias.uniform_(-bound, bound)


class SparseConv2d(nn.Module):
    """Sparse (or submanifold) 2D conv on `plane`; weight (K0*K1, in_ch, out_ch)."""

    def __init__(
        self,
        in_ch: int,
        out_ch: int,
        kernel: int | tuple[int, int],
        stride: tuple[int, int],
        plane: Plane,
        subm: bool = False,
        bias: bool = False,
    ) -> None:
        super().__init__()
        k = as_kernel(kernel)
        if subm and (tuple(stride) != (1, 1) or k[0] % 2 == 0 or k[1] % 2 == 0):
            raise ValueError(f"a submanifold conv needs stride (1, 1) and an odd kernel: {stride}, {kernel}")
        self.kernel, self.plane, self.subm = k, plane, subm
        self.stride = (int(stride[0]), int(stride[1]))
        self.weight = nn.Parameter(torch.empty(k[0] * k[1], in_ch, out_ch))
        self.bias = nn.Parameter(torch.empty(out_ch)) if bias else None
        _init_params(self.weight, self.bias, k[0] * k[1] * in_ch)

    def rulebook(self, x: SparseTensor) -> Rulebook:
        if self.subm:
            return build_subm_rulebook(x.coords, x.spatial_shape, x.batch_size, self.kernel, self.plane)
        return build_strided_rulebook(
            x.coords, x.spatial_shape, x.batch_size, self.kernel, self.stride, self.plane
        )

    def forward(self, x: SparseTensor, rulebook: Rulebook | None = None) -> tuple[SparseTensor, Rulebook]:
        """x (N, in_ch) -> (M, out_ch) and the rule book; a given `rulebook` (built for x) is reused."""
        rb = self.rulebook(x) if rulebook is None else rulebook
        if rb.num_in != x.num_sites or rb.kernel != self.kernel or rb.plane != self.plane:
            raise ValueError("rule book does not match this conv / input")
        feats = gather_mm_scatter(
            x.features, self.weight, rb.in_idx, rb.out_idx, rb.offset_ptr, rb.num_out, rb.identity_offset
        )
        if self.bias is not None:
            feats = feats + self.bias
        return SparseTensor(feats, rb.out_coords, rb.out_shape, rb.batch_size), rb


class SparseInverseConv2d(nn.Module):
    """Transposed conv onto a paired conv's input sites via its rule book reversed.

    weight (K0*K1, in_ch, out_ch), with the paired conv's kernel.
    """

    def __init__(
        self, in_ch: int, out_ch: int, kernel: int | tuple[int, int], plane: Plane, bias: bool = False
    ) -> None:
        super().__init__()
        k = as_kernel(kernel)
        self.kernel, self.plane = k, plane
        self.weight = nn.Parameter(torch.empty(k[0] * k[1], in_ch, out_ch))
        self.bias = nn.Parameter(torch.empty(out_ch)) if bias else None
        _init_params(self.weight, self.bias, k[0] * k[1] * in_ch)

    def forward(self, y: SparseTensor, rulebook: Rulebook) -> SparseTensor:
        """y (M, in_ch) at the rule book's output sites -> (N, out_ch) at its input sites (same row order)."""
        rb = rulebook
        if rb.num_out != y.num_sites or rb.kernel != self.kernel or rb.plane != self.plane:
            raise ValueError("rule book does not match this inverse conv / input")
        feats = gather_mm_scatter(
            y.features, self.weight, rb.out_idx, rb.in_idx, rb.offset_ptr, rb.num_in, rb.identity_offset
        )
        if self.bias is not None:
            feats = feats + self.bias
        return SparseTensor(feats, rb.in_coords, rb.in_shape, rb.batch_size)
