"""The polar voxelizer with fixed shapes: a padded batch of points -> `Sites` of a fixed capacity + features.

The fixed-shape twin of `PolarVoxelizer.forward` in eval mode, on the same modules and weights (its binning,
per-point feature columns and folded VFE layers). Points come as one padded (B, Np, C) tensor with a count
per batch item; padding points and out-of-range points go to a dump voxel (row cap) that is cut off at the
end, like the voxels beyond the capacity when there are more than `cap` (then `sites.overflow` is true).
"""

from __future__ import annotations

import torch
from torch import Tensor

from model.geometry.sparse_tensor import SENTINEL
from model.graph.sites import Sites, compact_sorted, make_sites, scatter_sum
from model.layers.voxelize import PolarVoxelizer
from model.ops.numba_support import numba_kernel
from model.ops.sort import sort_keys
from model.ops.voxelize_numba import grid_args, group_sorted, point_keys


def point_keys_torch(vox: PolarVoxelizer, points: Tensor, counts: Tensor) -> tuple[Tensor, ...]:
    """The plain twin of `model.ops.voxelize_numba.point_keys`. points (B, Np, C), counts (B,) -> voxel key
    per point (B * Np,) (SENTINEL unless kept), base rows (P + 5, B * Np) (`PolarVoxelizer.base_rows`,
    `bin_rows`), kept (B,), out of range (B,) per batch item."""
    n_b, n_pts, n_c = points.shape
    n_r, n_t, n_z = vox.spatial_shape
    dtype = vox.layers[0].linear.weight.dtype
    real = torch.arange(n_pts, device=points.device).unsqueeze(0) < counts.unsqueeze(1)  # (B, Np)
    clean = torch.where(real.unsqueeze(2), points, 0.0)  # padding rows may hold anything
    base = vox.base_rows([clean.reshape(n_b * n_pts, n_c)], points.device, dtype)  # (P + 5, B * Np)
    ri, ti, zi, in_range = vox.bin_rows(base)  # (B * Np,) each
    batch = torch.arange(n_b, device=base.device).unsqueeze(1).expand(n_b, n_pts).reshape(-1)  # (B * Np,)
    real = real.reshape(-1)
    kept = real & in_range  # (B * Np,)
    key = ((batch * n_t + ti) * n_r + ri) * n_z + zi  # (B * Np,) linear_key order
    key = torch.where(kept, key, SENTINEL)
    n_kept = kept.view(n_b, n_pts).sum(dim=1)  # (B,)
    n_out = (real & ~in_range).view(n_b, n_pts).sum(dim=1)  # (B,)
    return key, base, n_kept, n_out


def group_torch(
    vox: PolarVoxelizer, sorted_key: Tensor, order: Tensor, base: Tensor, cap: int
) -> tuple[Tensor, ...]:
    """The plain twin of `model.ops.voxelize_numba.group_sorted`. Sorted keys (n,), their order (n,) and base
    rows -> keys (cap,), voxel row per point (n,) (cap if
    none), count () of distinct real keys, VFE input (P + 9, n) (`PolarVoxelizer.vfe_input`)."""
    keys, vid, count = compact_sorted(sorted_key, cap)  # (cap,), (n,) in [0, cap], ()
    ones = torch.ones_like(sorted_key, dtype=base.dtype)
    npts = scatter_sum(torch.zeros(cap + 1, dtype=base.dtype, device=base.device), vid, ones)  # (cap + 1,)
    return keys, vid, count, vox.vfe_input(base, order, vid, npts.clamp_min(1.0))


@torch.no_grad()
def voxelize_fixed(
    vox: PolarVoxelizer, points: Tensor, counts: Tensor, cap: int, fast: bool | None = None
) -> tuple[Sites, Tensor, Tensor, Tensor]:
    """points (B, Np, C >= 4) float32, row j of item b real iff j < counts[b]; counts (B,) int64 ->
    (Sites of cap rows, features (cap, out_channels), points kept (B,), points out of range (B,)).

    Equals `vox.forward([points[b, :counts[b]] for b])` in eval mode on the real rows when cap >= the voxel
    count; padding rows of the features are zero. Needs `vox` in eval mode (the folded VFE). The per-point
    work runs through the kernels of `model.ops.voxelize_numba` where `fast` says (`numba_kernel`; None: a
    float32 model on the CPU), else through their twins here.
    """
    if vox.training:
        raise ValueError("voxelize_fixed runs the eval-mode VFE: call vox.eval() first")
    if fast is None and vox.layers[0].linear.weight.dtype != torch.float32:
        fast = False  # the kernels compute in float32
    kernels = numba_kernel("voxelize_fixed", points.device, fast)
    if kernels:
        key, base, n_kept, n_out = point_keys(points, counts, vox.point_features, *grid_args(vox.grid))
    else:
        key, base, n_kept, n_out = point_keys_torch(vox, points, counts)
    sorted_key, order = sort_keys(key)  # (B * Np,) stable
    if kernels:
        keys, vid, count, feats = group_sorted(sorted_key, order, base, cap)
    else:
        keys, vid, count, feats = group_torch(vox, sorted_key, order, base, cap)
    out = vox.encode(feats, vid, cap + 1)[:cap]  # (cap, out_channels)
    sites = make_sites(keys, vox.spatial_shape, points.shape[0], count)
    out = torch.where(sites.valid.unsqueeze(1), out, 0.0)
    return sites, out, n_kept, n_out
