"""Sparse 2D convs on one plane of the polar grid with fixed shapes: neighbour tables and implicit GEMM.

The fixed-shape twins of `model.geometry.rulebook` + `model.layers.sparse_conv` (same semantics, see the
rulebook docstring). Instead of a rule book of (input, output, offset) pairs, whose length depends on the
data, a conv gets a neighbour table of shape (cap_out, K0*K1): entry [o, k] is the input row feeding output
row o through flat kernel offset k (k = k0 * K1 + k1), or cap_in, the row of an appended zero row, where
none does. The conv is then one gather and one matmul (`model.ops.table_conv`: the implicit GEMM, on the
CPU a kernel that multiplies only the entries naming a row). Tables are built with `searchsorted` on the
sorted site keys (`model.ops.search`: on the CPU its kernel twin); padding rows (`Sites.valid` false) read
only the zero row.
"""

from __future__ import annotations

import torch
from torch import Tensor

from model.geometry.rulebook import Plane, as_kernel, conv_out_shape, key_strides
from model.geometry.sparse_tensor import BATCH, SENTINEL
from model.graph.sites import Sites, compact_sorted, make_sites
from model.ops.search import search
from model.ops.sort import sort_keys


def _lookup(
    target: Sites,
    coords: Tensor,
    valid: Tensor,
    plane: Plane,
    pos: tuple[Tensor, Tensor],
    ok: tuple[Tensor, Tensor],
) -> Tensor:
    """Rows of `target` at the plane positions pos of the query sites -> (n, K0*K1) int64, target.cap if none.

    coords (n, 4) and valid (n,) of the query sites (batch and fold coordinate are kept); pos[i] (K_i, n) the
    target coordinate on plane axis i per kernel index, ok[i] (K_i, n) whether it is inside the target grid.
    """
    st = key_strides(target.spatial_shape)
    (a0, a1), fold = plane.axes, plane.fold_axis
    k0, k1, n = pos[0].shape[0], pos[1].shape[0], coords.shape[0]
    base = coords[:, BATCH] * st[BATCH] + coords[:, fold] * st[fold]  # (n,) key with plane axes at 0
    key = base + (pos[0] * st[a0]).unsqueeze(1) + (pos[1] * st[a1]).unsqueeze(0)  # (K0, K1, n)
    inside = ok[0].unsqueeze(1) & ok[1].unsqueeze(0) & valid  # (K0, K1, n)
    key = torch.where(inside, key, SENTINEL).view(k0 * k1, n)  # (KK, n)
    row = search(target.keys, key).clamp_max_(target.cap - 1)  # (KK, n)
    found = inside.view(k0 * k1, n) & (target.keys[row] == key)  # (KK, n)
    return torch.where(found, row, target.cap).t().contiguous()  # (n, KK)


def subm_table(sites: Sites, kernel: int | tuple[int, int], plane: Plane) -> Tensor:
    """Neighbour table of a submanifold conv -> (cap, K0*K1) int64: [i, k] = row of the site at
    sites.coords[i] + (k - p) on the plane axes, or sites.cap (that site inactive, outside the grid, or row i
    padding)."""
    k0, k1 = as_kernel(kernel)
    pos, ok = [], []
    for ax, k in zip(plane.axes, (k0, k1), strict=True):
        d = torch.arange(k, device=sites.coords.device) - k // 2  # (K_i,) offset k - p
        q = sites.coords[:, ax].unsqueeze(0) + d.unsqueeze(1)  # (K_i, cap)
        pos.append(q)
        ok.append((q >= 0) & (q < sites.spatial_shape[ax - 1]))
    return _lookup(sites, sites.coords, sites.valid, plane, (pos[0], pos[1]), (ok[0], ok[1]))


def _strided_candidates(
    sites: Sites,
    kernel: tuple[int, int],
    stride: tuple[int, int],
    plane: Plane,
    out_shape: tuple[int, int, int],
) -> Tensor:
    """Output keys reached by each input site through each offset -> (K0*K1*cap,) int64, SENTINEL if none."""
    st = key_strides(out_shape)
    (a0, a1), fold = plane.axes, plane.fold_axis
    c = sites.coords
    opos, ok = [], []
    for ax, k, s in zip(plane.axes, kernel, stride, strict=True):
        ks = torch.arange(k, device=c.device)
        q = c[:, ax].unsqueeze(0) + (k // 2 - ks).unsqueeze(1)  # (K_i, cap) = o * s when valid
        opos.append(torch.div(q, s, rounding_mode="floor"))
        ok.append((q >= 0) & (q % s == 0) & (q < out_shape[ax - 1] * s))
    base = c[:, BATCH] * st[BATCH] + c[:, fold] * st[fold]  # (cap,)
    key = base + (opos[0] * st[a0]).unsqueeze(1) + (opos[1] * st[a1]).unsqueeze(0)  # (K0, K1, cap)
    inside = ok[0].unsqueeze(1) & ok[1].unsqueeze(0) & sites.valid  # (K0, K1, cap)
    return torch.where(inside, key, SENTINEL).view(-1)


def strided_sites(
    sites: Sites, kernel: int | tuple[int, int], stride: tuple[int, int], plane: Plane, out_cap: int
) -> tuple[Sites, Tensor]:
    """Output sites of a (non-submanifold) strided conv, compacted into out_cap rows (overflow: count >
    out_cap), and its table (out_cap, K0*K1) int64: [o, k] = row of the input site at o * s - p + k, or
    sites.cap."""
    kernel = as_kernel(kernel)
    out_shape = conv_out_shape(sites.spatial_shape, kernel, stride, plane)
    cand, _ = sort_keys(_strided_candidates(sites, kernel, stride, plane, out_shape))  # (KK * cap,)
    keys, _, count = compact_sorted(cand, out_cap)
    out = make_sites(keys, out_shape, sites.batch_size, count)
    pos, ok = [], []
    for ax, k, s in zip(plane.axes, kernel, stride, strict=True):
        ks = torch.arange(k, device=keys.device)
        q = out.coords[:, ax].unsqueeze(0) * s + (ks - k // 2).unsqueeze(1)  # (K_i, out_cap) input coordinate
        pos.append(q)
        ok.append((q >= 0) & (q < sites.spatial_shape[ax - 1]))
    return out, _lookup(sites, out.coords, out.valid, plane, (pos[0], pos[1]), (ok[0], ok[1]))


def inverse_table(
    in_sites: Sites, out_sites: Sites, kernel: int | tuple[int, int], stride: tuple[int, int], plane: Plane
) -> Tensor:
    """Table of the inverse (transposed) conv of a strided conv in_sites -> out_sites, onto in_sites ->
    (in_cap, K0*K1) int64: [i, k] = row o of out_sites with o * s - p + k = in_sites.coords[i] on the plane
    axes, or out_sites.cap."""
    kernel = as_kernel(kernel)
    pos, ok = [], []
    for ax, k, s in zip(plane.axes, kernel, stride, strict=True):
        ks = torch.arange(k, device=in_sites.keys.device)
        q = in_sites.coords[:, ax].unsqueeze(0) + (k // 2 - ks).unsqueeze(1)  # (K_i, in_cap) = o * s
        pos.append(torch.div(q, s, rounding_mode="floor"))
        ok.append((q >= 0) & (q % s == 0) & (q < out_sites.spatial_shape[ax - 1] * s))
    return _lookup(out_sites, in_sites.coords, in_sites.valid, plane, (pos[0], pos[1]), (ok[0], ok[1]))
