"""Rule books of sparse 2D convolutions on one plane of the 3D polar grid: which input site feeds which
output site through which kernel offset (the convs themselves: `model.layers.sparse_conv`).

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
(strided) or `torch.searchsorted` (submanifold); a conv is gather -> matmul per kernel offset -> index_add
(`model.ops.sparse_conv.gather_mm_scatter`). Every output tensor keeps its rows sorted by `linear_key`. Input
coordinates must be unique.
"""

from __future__ import annotations

import enum
import itertools
from dataclasses import dataclass

import torch
from torch import Tensor

from model.geometry.sparse_tensor import BATCH, THETA, Z, linear_key
from model.geometry.sparse_tensor import R as R_AX


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


def key_strides(shape: tuple[int, int, int]) -> tuple[int, int, int, int]:
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


def keys_to_coords(keys: Tensor, shape: tuple[int, int, int]) -> Tensor:
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
    st = key_strides(out_shape)
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
    out_coords = keys_to_coords(sorted_keys[is_new], out_shape)
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
    st = key_strides(shape)
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
