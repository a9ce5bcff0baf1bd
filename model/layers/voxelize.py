"""Polar dynamic voxelizer and voxel feature encoder (VFE): sectors of points -> sparse polar voxels.

Each batch item is one sector, given as (N_i, C) float points whose first columns are x, y, z, intensity
[, elongation]. The first `VFEConfig.point_features` (P) columns are used; an input with fewer columns (e.g.
a 4-column KITTI scan for a model trained with Waymo's elongation) is padded with zero columns, extra columns
are ignored.

Cylindrical coordinates: r = hypot(x, y), theta = atan2(y, x) in [-pi, pi], z. Voxel indices
    r_idx = floor((r - r_min) / r_size), theta_idx = floor((theta + pi) / theta_size),
    z_idx = floor((z - z_min) / z_size).
theta = +pi (the -180/+180 degree seam) is clamped into the last theta bin, so the wrap is seamless. Points
with r outside [r_min, r_max) or z outside [z_min, z_max) are dropped and counted in `VoxelStats`.

Per-point VFE input, P + 9 columns (metres or unitless), in this order:
    raw      x, y, z, intensity[, elongation]                 (P)
    radius   r                                                (1)  (z is among the raw columns)
    centre   r - r_c, r * (theta - theta_c), z - z_c         (3)  offset from the voxel centre along
                                                                   (radius, arc length, height)
    azimuth  sin(theta), cos(theta)                           (2)  continuous across the +/-pi seam
    cluster  centre offsets minus their mean over the voxel   (3)  offset from the voxel's point mean,
                                                                   in the same local frame
These are the polar analogue of the Cartesian dynamic VFE's absolute / cluster / centre features.

Dynamic VFE (no cap on points per voxel): for each width h in `VFEConfig.hidden`: Linear(no bias) ->
BatchNorm1d(eps 1e-3, momentum 0.01) -> ReLU, max over the voxel's points, and the voxel max concatenated back
to each point (width 2h); then Linear -> BN -> ReLU to `out_channels` and a max per voxel gives the voxel
feature. Points are processed sorted by voxel key, so the output rows come out sorted by `linear_key`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from model.config import PolarGridConfig, VFEConfig
from model.geometry.sparse_tensor import SparseTensor

BN_EPS, BN_MOMENTUM = 1e-3, 0.01
EXTRA_FEATURES = 9  # r (1) + centre offsets (3) + sin, cos (2) + cluster offsets (3)


class PointsError(ValueError):
    """Points that can't be run; the message names the field and what was expected."""


def validate_points(points: Tensor, min_features: int = 4) -> None:
    """Raise PointsError unless `points` is a finite (N, C >= min_features) floating tensor."""
    if not isinstance(points, Tensor):
        raise PointsError(f"points: got {type(points).__name__}; expected a torch.Tensor of shape (N, C)")
    if points.ndim != 2:
        raise PointsError(
            f"points: {points.ndim}-D tensor of shape {tuple(points.shape)}; "
            f"expected 2-D (N, C>={min_features})"
        )
    if points.shape[1] < min_features:
        raise PointsError(
            f"points: {points.shape[1]} columns; expected at least {min_features} (x, y, z, intensity[, ...])"
        )
    if not points.is_floating_point():
        raise PointsError(f"points: dtype {points.dtype}; expected a floating dtype (float32)")
    if bool(torch.isfinite(points.sum())):  # fast path; an overflowing sum falls through to the row check
        return
    bad = ~torch.isfinite(points).all(dim=1)  # (N,)
    n_bad = int(bad.sum())
    if n_bad == 0:
        return
    first = int(bad.nonzero()[0, 0])
    raise PointsError(
        f"points: {n_bad} rows contain NaN or inf values (row {first} first); expected finite float32"
    )


@dataclass(frozen=True)
class VoxelStats:
    """Per batch item (sector): points given, points voxelized, points dropped as out of range."""

    points_in: list[int]
    points_kept: list[int]
    points_out_of_range: list[int]


class _VoxelMax(torch.autograd.Function):
    """Max over each voxel's points, (n, C) -> (V, C). Backward splits the gradient evenly among ties.

    Same values and gradients as `scatter_reduce(..., "amax", include_self=False)`, whose autograd is about
    2.5x slower on CPU.
    """

    @staticmethod
    def forward(ctx, x: Tensor, vid: Tensor, num_voxels: int) -> Tensor:
        out = _scatter_max(x, vid, num_voxels)
        ctx.save_for_backward(x, vid, out)
        return out  # (V, C)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, None, None]:
        x, vid, out = ctx.saved_tensors
        is_max = (x == out.index_select(0, vid)).to(grad.dtype)  # (n, C)
        ties = torch.zeros_like(out).index_add_(0, vid, is_max)  # (V, C) >= 1
        return (grad / ties).index_select(0, vid) * is_max, None, None


def _scatter_max(x: Tensor, vid: Tensor, num_voxels: int) -> Tensor:
    """(n, C), (n,) voxel ids -> (V, C) max per voxel; 0 in a voxel without points."""
    idx = vid[:, None].expand_as(x)  # (n, C)
    return x.new_zeros(num_voxels, x.shape[1]).scatter_reduce_(0, idx, x, "amax", include_self=False)


def voxel_max(x: Tensor, vid: Tensor, num_voxels: int) -> Tensor:
    """(n, C) point features, (n,) int64 voxel ids in [0, V) -> (V, C) max per voxel (no voxel empty).

    Without autograd it is the plain scatter (which torch.compile traces; `model.graph.voxelize`)."""
    if torch.is_grad_enabled() and x.requires_grad:
        return _VoxelMax.apply(x, vid, num_voxels)
    return _scatter_max(x, vid, num_voxels)


def _batch_norm(bn: nn.BatchNorm1d, x: Tensor) -> Tensor:
    """BatchNorm1d that also accepts a single row in training mode (then it uses the running statistics)."""
    if bn.training and x.shape[0] < 2:
        return F.batch_norm(x, bn.running_mean, bn.running_var, bn.weight, bn.bias, False, 0.0, bn.eps)
    return bn(x)


class _VFELayer(nn.Module):
    """Linear(no bias) -> BN -> ReLU on [point feature, its voxel's max of the previous layer].

    The Linear's weight is split into a per-point part and a per-voxel part, so the voxel max is multiplied
    once per voxel and gathered, instead of gathered and concatenated to every point first (same result).
    In eval mode the BN is folded into the matmul, and `pooled` (the max per voxel of the output) adds the
    per-voxel term after the max: max_p relu(u_p + c) = relu(max_p u_p + c) exactly, as relu is monotone.
    """

    def __init__(self, c_point: int, c_voxel: int, c_out: int):
        super().__init__()
        self.c_point = c_point
        self.linear = nn.Linear(c_point + c_voxel, c_out, bias=False)
        self.norm = nn.BatchNorm1d(c_out, eps=BN_EPS, momentum=BN_MOMENTUM)

    def _folded(self, voxel: Tensor | None) -> tuple[Tensor, Tensor]:
        """Eval: -> (point weight (c_point, c_out) with the BN scale, per-voxel term (V or 1, c_out))."""
        bn, w = self.norm, self.linear.weight  # w: (c_out, c_point + c_voxel)
        scale = bn.weight * torch.rsqrt(bn.running_var + bn.eps)  # (c_out,)
        shift = bn.bias - bn.running_mean * scale  # (c_out,)
        w = w.t() * scale  # (c_point + c_voxel, c_out)
        if voxel is None:
            return w, shift[None]
        return w[: self.c_point], torch.addmm(shift, voxel, w[self.c_point :])

    def forward(self, x: Tensor, voxel: Tensor | None, vid: Tensor) -> Tensor:
        """x (n, c_point) point part, voxel (V, c_voxel) or None, vid (n,) -> (n, c_out)."""
        if self.training:
            w = self.linear.weight
            y = F.linear(x, w[:, : self.c_point])
            if voxel is not None:
                y = y + F.linear(voxel, w[:, self.c_point :]).index_select(0, vid)
            return torch.relu(_batch_norm(self.norm, y))
        w, term = self._folded(voxel)
        y = torch.mm(x, w)  # (n, c_out)
        return y.add_(term if voxel is None else term.index_select(0, vid)).relu_()

    def pooled(self, x: Tensor, voxel: Tensor | None, vid: Tensor, num_voxels: int) -> Tensor:
        """Max over each voxel's points of forward(x, voxel, vid) -> (V, c_out)."""
        if self.training:
            return voxel_max(self(x, voxel, vid), vid, num_voxels)
        w, term = self._folded(voxel)
        return voxel_max(torch.mm(x, w), vid, num_voxels).add_(term).relu_()


@dataclass(frozen=True)
class _Grouped:
    """Kept points in voxel-key order and their voxels."""

    features: Tensor  # (F_in, n) per-point VFE input, column j = j-th kept point in voxel-key order
    vid: Tensor  # (n,) int64 voxel id of each point, non-decreasing
    keys: Tensor  # (V,) int64 sorted unique voxel keys ((batch * T + theta) * R + r) * Z + z
    kept_per_item: Tensor  # (B,) int64


class PolarVoxelizer(nn.Module):
    """Points of B sectors -> SparseTensor of polar voxels with `out_channels` features, and VoxelStats."""

    def __init__(self, grid: PolarGridConfig, vfe: VFEConfig, out_channels: int):
        super().__init__()
        self.grid = grid
        self.point_features = vfe.point_features
        self.out_channels = out_channels
        layers, c_point, c_voxel = [], vfe.point_features + EXTRA_FEATURES, 0
        for width in (*vfe.hidden, out_channels):
            layers.append(_VFELayer(c_point, c_voxel, width))
            c_point = c_voxel = width  # next input: point feature + its voxel's max
        self.layers = nn.ModuleList(layers)

    @property
    def spatial_shape(self) -> tuple[int, int, int]:
        return (self.grid.r_bins, self.grid.theta_bins, self.grid.z_bins)

    def forward(self, points: list[Tensor]) -> tuple[SparseTensor, VoxelStats]:
        """points[i]: (N_i, C >= 4) float, the points of sector (batch item) i."""
        for p in points:
            validate_points(p)
        weight = self.layers[0].linear.weight
        device = points[0].device if points else weight.device
        counts = [int(p.shape[0]) for p in points]
        g = self._group(points, counts, device, weight.dtype)
        kept = g.kept_per_item.tolist()
        stats = VoxelStats(counts, kept, [n - k for n, k in zip(counts, kept, strict=True)])
        if g.vid.numel() == 0:
            feats = torch.zeros(0, self.out_channels, device=device, dtype=weight.dtype)
        else:
            feats = self.encode(g.features, g.vid, int(g.keys.shape[0]))
        return SparseTensor(feats, self._decode(g.keys), self.spatial_shape, len(points)), stats

    def base_rows(self, points: list[Tensor], device: torch.device, dtype: torch.dtype) -> Tensor:
        """-> (P + 5, N) contiguous rows: x, y, z, intensity, ... (zero-padded to P), r, 3 free, theta."""
        n_p = self.point_features
        base = torch.empty(n_p + 5, sum(int(p.shape[0]) for p in points), device=device, dtype=dtype)
        if base.shape[1] == 0:
            return base
        cols = []
        for p in points:
            c = p[:, :n_p].t().to(dtype)  # (<= P, N_i) view
            cols.append(F.pad(c, (0, 0, 0, n_p - c.shape[0])) if c.shape[0] < n_p else c)
        torch.cat(cols, dim=1, out=base[:n_p])
        torch.hypot(base[0], base[1], out=base[n_p])
        torch.atan2(base[1], base[0], out=base[n_p + 4])  # [-pi, pi]
        return base

    def _group(self, points: list[Tensor], counts: list[int], device: torch.device, dtype) -> _Grouped:
        """Bin points into voxels, drop out-of-range ones, sort by voxel key (= linear_key order)."""
        n_r, n_t, n_z = self.spatial_shape
        base = self.base_rows(points, device, dtype)  # (P + 5, N)
        ri, ti, zi, in_range = self.bin_rows(base)  # (N,) each
        batch = torch.repeat_interleave(
            torch.arange(len(counts), device=device),
            torch.tensor(counts, device=device, dtype=torch.int64),
            output_size=base.shape[1],
        )
        key = ((batch * n_t + ti) * n_r + ri) * n_z + zi  # (N,) linear_key order
        key = torch.where(in_range, key, len(counts) * n_t * n_r * n_z)  # out of range sorts last
        kept_per_item = torch.zeros(len(counts), dtype=torch.int64, device=device)
        kept_per_item.index_add_(0, batch, in_range.long())
        n_kept = int(kept_per_item.sum())
        sorted_key, order = torch.sort(key, stable=True)
        sorted_key, order = sorted_key[:n_kept], order[:n_kept]
        new_voxel = torch.ones_like(sorted_key, dtype=torch.bool)
        new_voxel[1:] = sorted_key[1:] != sorted_key[:-1]
        vid = new_voxel.long().cumsum_(0).sub_(1)  # (n,)
        keys = sorted_key[new_voxel]  # (V,)
        npts = torch.bincount(vid, minlength=int(keys.shape[0]))  # (V,) points per voxel
        return _Grouped(self.vfe_input(base, order, vid, npts), vid, keys, kept_per_item)

    def bin_rows(self, base: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Voxel indices of the points of `base` (P + 5, N), from `base_rows`: -> r, theta, z index (N,) int64
        and in range (N,) bool. Writes the offsets from the voxel centre into base's 3 free rows."""
        gr, n_p = self.grid, self.point_features
        n_r, n_t, n_z = self.spatial_shape
        z, r, theta = base[2], base[n_p], base[n_p + 4]
        # in range => scaled values >= 0, so truncation is floor; the clamp catches rounding at the top edge
        ri = ((r - gr.r_min) * (1.0 / gr.r_size)).long().clamp_(0, n_r - 1)
        ti = ((theta + math.pi) * (1.0 / gr.theta_size)).long().clamp_(0, n_t - 1)  # +pi -> last bin
        zi = ((z - gr.z_min) * (1.0 / gr.z_size)).long().clamp_(0, n_z - 1)
        # offsets from the voxel centre: radial, arc length r * dtheta, height
        torch.sub(r, ri * gr.r_size + (gr.r_min + 0.5 * gr.r_size), out=base[n_p + 1])
        torch.mul(r, theta - (ti * gr.theta_size + (0.5 * gr.theta_size - math.pi)), out=base[n_p + 2])
        torch.sub(z, zi * gr.z_size + (gr.z_min + 0.5 * gr.z_size), out=base[n_p + 3])
        in_range = (r >= gr.r_min) & (r < gr.r_max) & (z >= gr.z_min) & (z < gr.z_max)  # (N,)
        return ri, ti, zi, in_range

    def vfe_input(self, base: Tensor, order: Tensor, vid: Tensor, npts: Tensor) -> Tensor:
        """-> (P + 9, n) VFE input of the points base[:, order] (layout in the module docstring); vid (n,)
        their voxel ids, npts (V,) the points per voxel (>= 1 wherever a point lies)."""
        n_p = self.point_features
        feats = base.new_empty(n_p + EXTRA_FEATURES, order.shape[0])
        torch.index_select(base, 1, order, out=feats[: n_p + 5])  # raw, r, centre offsets, theta
        x, y, r, centre = feats[0], feats[1], feats[n_p], feats[n_p + 1 : n_p + 4]
        inv_r = 1.0 / r.clamp_min(1e-6)
        torch.mul(y, inv_r, out=feats[n_p + 4])  # sin(theta), overwrites theta
        torch.mul(x, inv_r, out=feats[n_p + 5])  # cos(theta)
        total = centre.new_zeros(3, npts.shape[0]).index_add_(1, vid, centre)  # (3, V)
        mean = total / npts.to(total.dtype)  # (3, V)
        torch.sub(centre, mean.index_select(1, vid), out=feats[n_p + 6 :])  # cluster offsets
        return feats

    def _decode(self, keys: Tensor) -> Tensor:
        """(V,) sorted voxel keys -> (V, 4) int64 coords (batch, r, theta, z)."""
        n_r, n_t, n_z = self.spatial_shape
        z = keys % n_z
        rest = keys // n_z
        r = rest % n_r
        rest = rest // n_r
        return torch.stack([rest // n_t, r, rest % n_t, z], dim=1)

    def encode(self, features: Tensor, vid: Tensor, num_voxels: int) -> Tensor:
        """Dynamic VFE over grouped points, features (P + 9, n) from `_features`, vid (n,) in [0, V) ->
        (V, out_channels) voxel features."""
        h, voxel = features.t(), None  # (n, P + 9) view of the column-major input
        for layer in self.layers[:-1]:
            h = layer(h, voxel, vid)  # (n, width)
            voxel = voxel_max(h, vid, num_voxels)  # (V, width)
        return self.layers[-1].pooled(h, voxel, vid, num_voxels)  # (V, out_channels)
