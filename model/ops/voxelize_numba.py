"""The fixed-shape voxelizer's per-point work as CPU kernels (numba), torch custom ops.

Twins of the torch code in `model.graph.voxelize` (`point_keys_torch`, `group_torch`; `voxelize_fixed`
dispatches between them by `numba_support.numba_kernel`'s rule), which inductor
turns into scalar loops that recompute hypot and atan2 several times per point (~3 ms of a `tiny` step on
the 2-core machine). Here:

- `point_keys`: padded points (B, Np, C) -> each point's voxel key (SENTINEL unless kept), its base rows
  (raw columns, r, the three centre offsets, theta; `PolarVoxelizer.base_rows` and `bin_rows`) and the
  points kept and out of range per stream, in one pass;
- `group_sorted`: the keys sorted (outside, `model.ops.sort`) -> the compacted voxel keys, each
  point's voxel row and the VFE input rows (`PolarVoxelizer.vfe_input`), in two passes.

Arithmetic is float32 step by step as in the eager voxelizer, and hypot and atan2 are aten's (called in
the op, out of inductor's reach: its code calls the C library's), so voxel indices agree exactly; sums run
in another order than index_add's, so features agree to float rounding. One thread and numba, for
the reasons given in `model.ops.scan_numba`.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor

from model.config import PolarGridConfig
from model.geometry.sparse_tensor import SENTINEL

f32 = np.float32
GROUP_EXTRA = 4  # VFE input rows beyond the base rows: sin, cos and the three offsets from the voxel's mean


@numba.njit(cache=True, nogil=True)
def _bin(t, n):  # pragma: no cover - compiled
    """A scaled coordinate t -> its bin in [0, n): truncation (floor where in range) clamped, as aten's
    `.long().clamp_(0, n - 1)` does for finite t in int64's range, but clamped while a float: a huge, inf
    or NaN t (a point far out of range) has no int64, and converting it is undefined."""
    if not t > 0:
        return 0
    if t >= n - 1:
        return n - 1
    return np.int64(t)


@numba.njit(cache=True, nogil=True)
def _point_keys(points, counts, radius, azimuth, n_p, grid, shape, key, base, kept, out):  # pragma: no cover
    """points (B, Np, C) float32; counts (B,) int64; radius, azimuth (B, Np) float32: hypot and atan2 of
    the real points' x, y (0 on padding); grid (7,) float64: r_min, r_max, r_size, theta_size, z_min,
    z_max, z_size; shape (3,) int64: R, THETA, Z. Writes key (B * Np,) int64, base (P + 5, B * Np) float32,
    kept and out (B,) int64."""
    n_b, n_pts, n_c = points.shape
    n_r, n_t, n_z = shape[0], shape[1], shape[2]
    r_min, r_max, z_min, z_max = f32(grid[0]), f32(grid[1]), f32(grid[4]), f32(grid[5])
    inv_r, inv_t, inv_z = f32(1.0 / grid[2]), f32(1.0 / grid[3]), f32(1.0 / grid[6])
    r_size, t_size, z_size = f32(grid[2]), f32(grid[3]), f32(grid[6])
    r_c0, t_c0 = f32(grid[0] + 0.5 * grid[2]), f32(0.5 * grid[3] - math.pi)  # bin 0's centre
    z_c0, pi = f32(grid[4] + 0.5 * grid[6]), f32(math.pi)
    zero = f32(0.0)
    for b in range(n_b):
        kept[b] = 0
        out[b] = 0
        for j in range(n_pts):
            i = b * n_pts + j
            real = j < counts[b]
            for c in range(n_p):
                base[c, i] = points[b, j, c] if real and c < n_c else zero
            z, r, theta = base[2, i], radius[b, j], azimuth[b, j]
            ri = _bin((r - r_min) * inv_r, n_r)
            ti = _bin((theta + pi) * inv_t, n_t)
            zi = _bin((z - z_min) * inv_z, n_z)
            base[n_p, i] = r
            base[n_p + 1, i] = r - (f32(ri) * r_size + r_c0)
            base[n_p + 2, i] = r * (theta - (f32(ti) * t_size + t_c0))
            base[n_p + 3, i] = z - (f32(zi) * z_size + z_c0)
            base[n_p + 4, i] = theta
            in_range = r >= r_min and r < r_max and z >= z_min and z < z_max
            if real and in_range:
                key[i] = ((b * n_t + ti) * n_r + ri) * n_z + zi
                kept[b] += 1
            else:
                key[i] = SENTINEL
                if real:
                    out[b] += 1


@numba.njit(cache=True, nogil=True)
def _group_sorted(sorted_key, order, base, cap, keys, vid, feats):  # pragma: no cover - compiled
    """sorted_key, order (n,) int64; base (P + 5, n) float32. Writes keys (cap,) int64 (SENTINEL padded),
    vid (n,) int64 (cap for SENTINEL and beyond cap), feats (P + 9, n) float32; returns the count of
    distinct real keys (> cap: overflow)."""
    n = sorted_key.shape[0]
    n_p = base.shape[0] - 5
    keys[:] = SENTINEL
    npts = np.zeros(cap + 1, dtype=np.float32)  # points per voxel row
    total = np.zeros((cap + 1, 3), dtype=np.float32)
    count = 0
    for j in range(n):
        k = sorted_key[j]
        row = cap
        if k != SENTINEL:
            if j == 0 or k != sorted_key[j - 1]:
                count += 1
                if count <= cap:
                    keys[count - 1] = k
            if count <= cap:
                row = count - 1
        vid[j] = row
        npts[row] += f32(1.0)
        src = order[j]
        for c in range(n_p + 5):
            feats[c, j] = base[c, src]
        inv_r = f32(1.0) / max(feats[n_p, j], f32(1e-6))
        feats[n_p + 4, j] = feats[1, j] * inv_r  # sin(theta), over theta
        feats[n_p + 5, j] = feats[0, j] * inv_r  # cos(theta)
        for c in range(3):
            total[row, c] += feats[n_p + 1 + c, j]
    for j in range(n):
        row = vid[j]
        for c in range(3):
            feats[n_p + 6 + c, j] = feats[n_p + 1 + c, j] - total[row, c] / max(npts[row], f32(1.0))
    return count


@torch.library.custom_op("phim::point_keys", mutates_args=(), device_types="cpu")
def point_keys(
    points: Tensor, counts: Tensor, n_p: int, grid: list[float], shape: list[int]
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """points (B, Np, C) float32, counts (B,) int64 -> key (B * Np,) int64, base (P + 5, B * Np) float32,
    kept (B,) int64, out of range (B,) int64 (`grid`, `shape` from `grid_args`)."""
    n_b, n_pts, _ = points.shape
    key = torch.empty(n_b * n_pts, dtype=torch.int64)
    base = torch.empty(n_p + 5, n_b * n_pts, dtype=torch.float32)
    kept, out = torch.empty(n_b, dtype=torch.int64), torch.empty(n_b, dtype=torch.int64)
    real = torch.arange(n_pts).unsqueeze(0) < counts.unsqueeze(1)  # (B, Np)
    x, y = (torch.where(real, points[..., c], 0.0).float() for c in (0, 1))  # (B, Np) each
    # aten's (vectorised) hypot and atan2, as the eager voxelizer: the C library's atan2 differs from it in
    # the last bit for half the points of a KITTI sector, and that moves one of them to the next theta bin
    arrays = (points.float().contiguous(), counts.contiguous(), torch.hypot(x, y), torch.atan2(y, x))
    grid_a, shape_a = np.asarray(grid, dtype=np.float64), np.asarray(shape, dtype=np.int64)
    outs = (key, base, kept, out)
    _point_keys(*(a.numpy() for a in arrays), n_p, grid_a, shape_a, *(o.numpy() for o in outs))
    return outs


@point_keys.register_fake
def _(points, counts, n_p, grid, shape):
    n = points.shape[0] * points.shape[1]
    b = points.shape[0]
    long = torch.int64
    return (
        points.new_empty(n, dtype=long),
        points.new_empty(n_p + 5, n, dtype=torch.float32),
        points.new_empty(b, dtype=long),
        points.new_empty(b, dtype=long),
    )


@torch.library.custom_op("phim::group_sorted", mutates_args=(), device_types="cpu")
def group_sorted(
    sorted_key: Tensor, order: Tensor, base: Tensor, cap: int
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """sorted_key (n,) int64 (SENTINEL last), order (n,) int64, base (P + 5, n) float32 from `point_keys` ->
    keys (cap,) int64, vid (n,) int64, count () int64 (`compact_sorted`'s), feats (P + 9, n) float32."""
    n = sorted_key.shape[0]
    keys, vid = torch.empty(cap, dtype=torch.int64), torch.empty(n, dtype=torch.int64)
    feats = torch.empty(base.shape[0] + GROUP_EXTRA, n, dtype=torch.float32)
    arrays = (sorted_key.contiguous(), order.contiguous(), base.contiguous())
    count = _group_sorted(*(a.numpy() for a in arrays), cap, keys.numpy(), vid.numpy(), feats.numpy())
    return keys, vid, torch.tensor(count, dtype=torch.int64), feats


@group_sorted.register_fake
def _(sorted_key, order, base, cap):
    n = sorted_key.shape[0]
    long = torch.int64
    feats = base.new_empty(base.shape[0] + GROUP_EXTRA, n)
    return sorted_key.new_empty(cap), sorted_key.new_empty(n), sorted_key.new_empty((), dtype=long), feats


def grid_args(g: PolarGridConfig) -> tuple[list[float], list[int]]:
    """A voxelizer's grid as `point_keys` takes it."""
    shape = [g.r_bins, g.theta_bins, g.z_bins]
    return [g.r_min, g.r_max, g.r_size, g.theta_size, g.z_min, g.z_max, g.z_size], shape
